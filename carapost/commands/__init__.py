"""Implementations of the ``carapost`` sub-commands (the parser lives in :mod:`carapost.cli`)."""
