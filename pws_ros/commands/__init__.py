"""Subcommands of ``pws``: each module has ``register(subparsers)`` and ``run(args) -> int``."""
