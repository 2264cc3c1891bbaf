"""Simulation: plant models, the simulated board hooks and simulated motion capture."""
