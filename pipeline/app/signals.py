"""SIGINT and SIGTERM while a run finishes (final mapping, writing its outputs, evaluating):
noted, not obeyed at once.

Outside the SLAM graph (whose runtime finishes the current frame on a signal) a signal would
end the process between two files; inside `signals_noted()` the first only sets the returned
event, which cuts a final refinement and the evaluation short, so every output is still written
and the command still exits 0. A second one calls `on_again` (SLAM then waits no more for a part
running elsewhere and saves what is complete).
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Callable, Iterator
from types import FrameType

from pipeline.runtime import catchable_signals

log = logging.getLogger("gsplatam")


@contextlib.contextmanager
def signals_noted(on_again: Callable[[], None] | None = None) -> Iterator[threading.Event]:
    """While inside, SIGINT/SIGTERM set the event yielded (and say so once), and a later one
    calls `on_again` (it must be safe in a signal handler); the handlers before are restored on
    leaving. Signals reach the main thread only: elsewhere (a Ray actor's method) nothing is
    installed and the event stays clear (its caller stops the session by other means,
    app/remote_control.py)."""
    noted = threading.Event()

    def note(signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if not noted.is_set():
            log.info("%s: stopping (a final refinement or the evaluation is cut short; the outputs are written)", name)
            noted.set()
        elif on_again is not None:
            log.info("%s again: waiting for nothing more, saving what is complete", name)
            on_again()

    previous = {sig: signal.signal(sig, note) for sig in catchable_signals()}
    try:
        yield noted
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
