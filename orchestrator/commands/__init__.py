"""One module per ``hilswarm`` subcommand: ``HELP``, ``add_arguments(parser)``, ``run(args)``."""
