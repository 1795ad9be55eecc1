"""The ``plenocl`` command line (:func:`main`); one module per group of subcommands."""

from .main import main

__all__ = ["main"]
