"""Library controllers (the thesis case studies and swarm protocols)."""
