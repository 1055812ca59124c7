"""CLI sub-commands; each module exposes ``register(subparsers)`` (see :mod:`torm.cli`)."""
