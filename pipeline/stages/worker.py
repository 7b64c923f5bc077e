"""A stage whose function runs in one dedicated thread that takes the next item the moment it
finishes the last one.

`transform_stage` hands each item to an executor and resumes on the event loop when it is done,
so between two items there is a round trip through the loop (and whatever else the loop is
doing). For the SLAM stage that round trip is GPU idle time. Here the worker thread blocks on a
thread-safe hand-off that the loop keeps filled, and posts results back with
`call_soon_threadsafe`; the loop is off the critical path.
"""

from __future__ import annotations

import asyncio
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pipeline.errors import StageFailure
from pipeline.stages.gpu_spans import GpuSpans
from pipeline.stages.queues import END, EndOfStream, StageQueue, StreamFailed
from pipeline.stages.stage import StageStats, frame_index


@dataclass
class ThreadedStage:
    """A stage for the runtime that runs in a thread of its own: its function, and how it takes
    its inbox. `pass_over`: a live stage's treatment of the items it does not process because a
    newer one is waiting (None: every item is processed; it may return None: dropped)."""

    name: str
    run: Callable[[Any], Any]
    spans: GpuSpans
    pass_over: Callable[[Any], Any] | None = None
    dropped: int = 0  # live: frames not started because a newer one was waiting, or used to warm up

    def drop(self, item: Any) -> None:
        """The pass-over of a live stage that takes frames: never start a stale frame."""
        self.dropped += 1


class DedicatedThread:
    """Applies `stage.run` to every item of `inbox` in order, in a thread of its own, and puts
    the results in `outbox`. At most two items (one with `pass_over`: the newest is chosen when
    it starts) are handed over or finished but not yet passed on, a bound on memory. Once `stop`
    is set the thread finishes the item in hand and takes no other. With `pass_over`, of the items waiting only the newest
    goes to `run`; the older ones go, in order, to `pass_over`."""

    def __init__(
        self,
        stage: ThreadedStage,
        inbox: StageQueue[Any],
        outbox: StageQueue[Any],
        stats: StageStats,
        stop: asyncio.Event,
    ) -> None:
        self.stage = stage
        self.inbox = inbox
        self.outbox = outbox
        self.stats = stats
        self.stop = stop
        self._handoff: queue.SimpleQueue[Any] = queue.SimpleQueue()  # bounded by `_slots`; put never blocks
        self._halted = threading.Event()

    async def run(self) -> EndOfStream:
        """-> the end marker passed on (END, or the StreamFailed of a stage before this one or of
        the stage's function itself). The results before a failure are passed on first, so the
        sink takes every item finished before it (frames.csv holds every frame a save holds)."""
        loop = asyncio.get_running_loop()
        finished: asyncio.Queue[Any] = asyncio.Queue()
        slots = asyncio.Semaphore(1 if self.stage.pass_over else 2)

        def post(value: Any) -> None:
            loop.call_soon_threadsafe(finished.put_nowait, value)

        thread = threading.Thread(target=self._work, args=(post,), name=f"{self.stage.name}-worker", daemon=True)
        thread.start()
        feeder = asyncio.create_task(self._feed(slots))
        watcher = asyncio.create_task(self._halt_on_stop())
        try:
            while not isinstance(results := await finished.get(), EndOfStream):
                if isinstance(results, StageFailure):
                    results = StreamFailed(results)
                    break
                for result in results:
                    if result is not None:  # a passed-over item that is dropped
                        await self.outbox.put(result)
                slots.release()
                if self._stopping():
                    self._halted.set()
        finally:
            feeder.cancel()
            watcher.cancel()
            self._halted.set()
            self._handoff.put(END)  # wakes the worker if it waits for an item
            await asyncio.to_thread(thread.join)
        await self.outbox.put(results)
        return results

    def _run_batch(self, batch: list[Any]) -> list[Any]:
        """The newest item through `run`, the older ones (if any) through `pass_over`, in order."""
        pass_over = self.stage.pass_over
        results = []
        for item in batch[:-1]:
            assert pass_over is not None
            results.append(pass_over(item))
        start = time.perf_counter()
        results.append(self.stage.run(batch[-1]))
        self.stats.record(time.perf_counter() - start)
        return results

    def _work(self, post: Callable[[Any], None]) -> None:
        """The worker thread: batches until the end marker or a halt; a failure is posted to the
        loop, which stops the graph."""
        while not isinstance(batch := self._handoff.get(), EndOfStream) and not self._halted.is_set():
            try:
                post(self._run_batch(batch))
            except BaseException as exc:
                post(StageFailure(self.stage.name, frame_index(batch[-1]), exc))
                return
        post(batch if isinstance(batch, EndOfStream) else END)

    def _stopping(self) -> bool:
        return self.stop.is_set()

    async def _feed(self, slots: asyncio.Semaphore) -> None:
        """Hand over one batch per free slot: the next item, and with `pass_over` every item
        waiting behind it, so that the newest is the one processed."""
        while True:
            await slots.acquire()
            waiting = [await self.inbox.get()]
            if self.stage.pass_over is not None:
                waiting += self.inbox.take_ready()
            ends = isinstance(waiting[-1], EndOfStream)  # END comes last, if at all
            batch = waiting[:-1] if ends else waiting
            if batch and not self._stopping():
                self._handoff.put(batch)
            if ends or self._stopping():
                self._handoff.put(waiting[-1] if ends and not self._stopping() else END)
                return

    async def _halt_on_stop(self) -> None:
        """The moment a stop is asked for, the worker takes no new item (not one more frame)."""
        await self.stop.wait()
        self._halted.set()
