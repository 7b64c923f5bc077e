"""The mapping side in a thread of the tracking process (`slam.schedule=thread`).

The same mapping loop as the process schedule's (mapping_process.py), the same messages, map
slots and frame ring, but started as a thread: no second interpreter, no second import of torch
and gsplat, no second CUDA context, the compiler imported once. Built because that start-up
looked like most of the process schedule's warm-up; measured on the H200 (bench/NOTES.md,
outcome at 009c174) it is not: `process` overlaps it with tracking's own warm-up, and both
schedules reach their third result after 9.0 s on a warm cache. What it costs: the two sides
share the GIL, so the mapping side's host work (densification, the loop search) runs between
tracking's (33-53 frames/s steady against `process`'s 50-69). Experimental, not a default.

`ThreadContext` stands in for multiprocessing's spawn context, so that the client and the
bookkeeping it shares are written once: queues, events, locks and semaphores of `threading`,
and a `Process` that is a thread. The mapping thread runs its kernels on a CUDA stream of its
own (torch's current stream is per thread), so that the two sides' kernels overlap as two
processes' would, and the stream synchronisations of the map slots and the frame ring order
them as they order two processes.
"""

from __future__ import annotations

import importlib
import queue
import threading
from collections.abc import Callable
from typing import Any


def import_the_compiler(compiled: bool) -> None:
    """torch.compile's modules imported in this thread before the mapping thread starts. Both
    sides import them lazily at their first compile, and two threads importing torch's compiler
    at once deadlock on its module locks or meet a module half imported (both measured on the
    H200 at 055e532); imported, dynamo's own lock serialises the compiles that follow."""
    importlib.import_module("torch._dynamo")  # torch.optim's first optimiser imports it too
    if compiled:
        importlib.import_module("torch._inductor.compile_fx")


class MappingThread(threading.Thread):
    """A thread with the parts of `multiprocessing.Process` the client uses."""

    def __init__(self, target: Callable[..., None], args: tuple[Any, ...], name: str, daemon: bool) -> None:
        super().__init__(name=name, daemon=daemon)
        self._work, self._work_args = target, args
        self.exitcode: int | None = None  # None while it runs; 0 at its end, 1 after an exception

    def run(self) -> None:
        try:
            self._work(*self._work_args)
        except BaseException:
            self.exitcode = 1  # the loop reported the failure (MappingFailed) before raising it
            return
        self.exitcode = 0

    def kill(self) -> None:
        """A thread cannot be killed: a hung mapping thread is left behind (a daemon, it ends
        with the process); the client stops waiting for it all the same."""


class ThreadLock:
    """threading's lock with multiprocessing's `acquire(block=True, timeout=None)` (threading's
    takes -1, not None, for no timeout)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()

    def acquire(self, block: bool = True, timeout: float | None = None) -> bool:
        return self._lock.acquire(block, -1 if timeout is None or not block else timeout)

    def release(self) -> None:
        self._lock.release()

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


class ThreadContext:
    """multiprocessing's context, for a mapping side in a thread."""

    Queue = queue.Queue
    Event = threading.Event
    Lock = ThreadLock
    Semaphore = threading.Semaphore

    @staticmethod
    def Process(target: Callable[..., None], args: tuple[Any, ...], name: str, daemon: bool) -> MappingThread:  # noqa: N802 (as multiprocessing)
        return MappingThread(target, args, name, daemon)
