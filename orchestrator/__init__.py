"""hilswarm orchestrator: experiment files, graph checks, launcher, ticks, recorder, CLI."""
