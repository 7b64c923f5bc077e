"""The log format of every gsplatam process: the command, and each session of `serve --ray`."""

from __future__ import annotations

import logging
import sys

# Libraries that log at INFO what a user need not read: per-candidate ICE and per-connection logs,
# NumExpr's thread count (imported by pandas, which Ray imports), matplotlib's font cache.
CHATTY = ("aioice", "aiortc", "websockets", "numexpr", "matplotlib")


def configure_logging(prefix: str = "gsplatam") -> None:
    logging.basicConfig(level=logging.INFO, format=f"{prefix}: %(message)s", stream=sys.stderr)
    for name in CHATTY:
        logging.getLogger(name).setLevel(logging.WARNING)
