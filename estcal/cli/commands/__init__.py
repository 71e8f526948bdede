"""Subcommands of the estcal CLI; each module defines register(app)."""
