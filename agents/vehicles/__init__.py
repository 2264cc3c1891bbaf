"""Library vehicles (the thesis case studies)."""
