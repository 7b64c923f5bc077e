"""What a process of ours started from another (the mapping process, a benchmark cell) needs:
its start with the stop signals held back, and its end when its parent ends.

A terminal's Ctrl-C, `timeout` and a service manager signal the whole process group; the parent
decides what a child makes of SIGINT and SIGTERM. Started inside `signals_blocked()`, a child
holds any stop signal sent during its start-up until it has chosen (ignore it, or obey the one
its parent forwards), so none arrives as a KeyboardInterrupt halfway through an import.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
from collections.abc import Iterator
from types import FrameType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
EXIT_ORPHANED = 3  # the exit code of a child process whose parent ended first


@contextlib.contextmanager
def signals_blocked() -> Iterator[None]:
    """SIGINT and SIGTERM held back from this thread while inside; a process started meanwhile
    starts with them blocked (fork keeps the mask, exec too). One sent meanwhile is delivered to
    this process once they are unblocked again."""
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def end_with_the_parent() -> None:
    """A thread that ends this process (EXIT_ORPHANED, nothing saved) once its parent has
    ended: multiprocessing's sentinel of the parent (a pipe whose other end only the parent
    holds) becomes readable then, whichever thread started this process and however the parent
    ended (a kill -9 too). Nothing without a multiprocessing parent."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        multiprocessing.connection.wait([parent.sentinel])
        os._exit(EXIT_ORPHANED)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def terminate_as_interrupt(signum: int, frame: FrameType | None) -> None:
    """A SIGTERM handler: the command stops as on Ctrl-C (outside a run, whose runtime handles both)."""
    raise KeyboardInterrupt
