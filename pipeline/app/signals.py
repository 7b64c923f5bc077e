"""SIGINT and SIGTERM while a run writes its outputs or evaluates: noted, not obeyed at once.

Outside the SLAM graph (whose runtime finishes the current frame on a signal) a signal would
end the process between two files; inside `signals_noted()` it only sets the returned event,
which the evaluation reads to stop early, so every output is still written and the command
still exits 0.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from types import FrameType

from pipeline.runtime import catchable_signals

log = logging.getLogger("gsplatam")


@contextlib.contextmanager
def signals_noted() -> Iterator[threading.Event]:
    """While inside, SIGINT/SIGTERM set the event yielded (and say so once); the handlers
    before are restored on leaving. Signals reach the main thread only: elsewhere (a Ray
    actor's method) nothing is installed and the event stays clear (its caller stops the
    session by other means, app/remote_control.py)."""
    noted = threading.Event()

    def note(signum: int, frame: FrameType | None) -> None:
        if not noted.is_set():
            log.info("%s: stopping once the outputs are written", signal.Signals(signum).name)
        noted.set()

    previous = {sig: signal.signal(sig, note) for sig in catchable_signals()}
    try:
        yield noted
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
