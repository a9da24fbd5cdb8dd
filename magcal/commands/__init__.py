"""One module per ``magcal`` subcommand: ``HELP``, ``add_arguments(parser)``, ``run(args)``.

Shared option helpers live in ``magcal.commands.common``.
"""
