"""Another thread's handle on a running `serve` session: read its status, ask it to stop.

`serve --ray` runs each session in a Ray actor, whose methods run in threads of their own:
the session's graph runs in one, and the driver's status and stop calls arrive in others. The
control joins them through a service of the graph, which hands over its event loop, its stop
event and its status reader for as long as the graph runs.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pipeline.runtime import Service

StatusReader = Callable[[], dict[str, Any]]


@dataclass
class _Running:
    loop: asyncio.AbstractEventLoop
    stop: asyncio.Event
    read: StatusReader


class RemoteControl:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._running: _Running | None = None
        self._stop_requested = False

    def service(self, read: StatusReader) -> Service:
        """The graph service that attaches this control to the graph until the graph ends."""

        async def attach(stop: asyncio.Event) -> None:
            with self._lock:
                self._running = _Running(asyncio.get_running_loop(), stop, read)
                if self._stop_requested:
                    stop.set()
            try:
                await asyncio.Event().wait()  # until the graph ends and cancels its services
            finally:
                with self._lock:
                    self._running = None

        return attach

    def status(self, timeout_s: float = 5.0) -> dict[str, Any] | None:
        """The session's status, read on its event loop; None while its graph is not running."""
        with self._lock:
            running = self._running
        if running is None:
            return None

        async def read() -> dict[str, Any]:
            return running.read()

        try:
            return asyncio.run_coroutine_threadsafe(read(), running.loop).result(timeout_s)
        except (RuntimeError, concurrent.futures.TimeoutError, concurrent.futures.CancelledError):
            return None  # the loop closed or stopped in between

    def request_stop(self) -> None:
        """Stop the session as SIGINT would (the frame in SLAM finishes, then the final save);
        asked before the graph runs, it stops as soon as it starts."""
        with self._lock:
            self._stop_requested = True
            running = self._running
        if running is not None:
            try:
                running.loop.call_soon_threadsafe(running.stop.set)
            except RuntimeError:  # the loop closed in between: the session has ended anyway
                pass
