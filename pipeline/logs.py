"""Progress messages through the standard `logging`: each module logs to its own logger
(`pipeline.<package>.<module>`), and a function that reports progress takes `log: Log`, by default
its module logger's `info`, so a caller may send the messages elsewhere (a test collects them).

Nothing is shown until an entry point (a stage, `needlecue retrain`) calls `setup`: INFO and above
of every `pipeline` logger on stderr, each line prefixed with the entry point's name if it has one."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable

Log = Callable[[str], None]  # one progress message


def setup(prefix: str = "") -> Log:
    """Show the package's INFO messages on stderr (`prefix: message`); returns the `info` of the
    entry point's own logger. Called again, it replaces the handler instead of adding one."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f"{prefix}: %(message)s" if prefix else "%(message)s"))
    package = logging.getLogger("pipeline")
    package.handlers[:] = [handler]
    package.setLevel(logging.INFO)
    package.propagate = False  # not twice through a root handler another library set up
    return logging.getLogger(f"pipeline.{prefix or 'main'}").info
