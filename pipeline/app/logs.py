"""The log format of every gsplatam process: the command, and each session of `serve --ray`."""

from __future__ import annotations

import logging
import sys

CHATTY = ("aioice", "aiortc", "websockets")  # per-candidate ICE and per-connection logs at INFO


def configure_logging(prefix: str = "gsplatam") -> None:
    logging.basicConfig(level=logging.INFO, format=f"{prefix}: %(message)s", stream=sys.stderr)
    for name in CHATTY:
        logging.getLogger(name).setLevel(logging.WARNING)
