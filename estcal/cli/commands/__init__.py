"""Subcommands of the estcal CLI, one module each, defined at module level with
:func:`estcal.cli.app.command`."""
