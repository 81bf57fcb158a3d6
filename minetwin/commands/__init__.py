"""Subcommands of the ``minetwin`` CLI, one module each (see minetwin.cli)."""
