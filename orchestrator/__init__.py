"""hilswarm orchestrator: experiment files, graph checks, launcher, instance manager, recorder, CLI."""
