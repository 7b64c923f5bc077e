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
from typing import Any

from pipeline.errors import StageFailure
from pipeline.stages.queues import END, EndOfStream, StageQueue
from pipeline.stages.stage import StageStats, frame_index


async def dedicated_thread_stage(
    name: str,
    fn: Callable[[Any], Any],
    inbox: StageQueue[Any],
    outbox: StageQueue[Any],
    stats: StageStats,
    stop: asyncio.Event,
    in_flight: int = 2,
    pass_over: Callable[[Any], Any] | None = None,
    finish_on_stop: bool = False,
    interrupt: Callable[[], None] | None = None,
) -> EndOfStream:
    """Apply `fn` to every item in order in a thread of its own. At most `in_flight` items are
    handed over or finished but not yet passed on (a bound on memory). Once `stop` is set the
    thread finishes the item in hand and takes no other, unless `finish_on_stop` (then it goes
    on to the inbox's end). With `pass_over`, of the items waiting in the inbox only the newest
    goes to `fn`; the older ones go, in order, to `pass_over` (which may return None: dropped). `interrupt` is called when the
    stage ends, to unblock an `fn` that waits for another stage. -> the end marker passed on (END,
    or the StreamFailed of a stage before this one); a failure of `fn` itself is raised."""
    loop = asyncio.get_running_loop()
    handoff: queue.SimpleQueue[Any] = queue.SimpleQueue()  # bounded by `slots`; put never blocks
    finished: asyncio.Queue[Any] = asyncio.Queue()
    slots = asyncio.Semaphore(in_flight)
    halted = threading.Event()

    def post(value: Any) -> None:
        loop.call_soon_threadsafe(finished.put_nowait, value)

    def run_batch(batch: list[Any]) -> list[Any]:
        """The newest item through `fn`, the older ones (if any) through `pass_over`, in order."""
        results = []
        for item in batch[:-1]:
            assert pass_over is not None
            results.append(pass_over(item))
        start = time.perf_counter()
        results.append(fn(batch[-1]))
        stats.record(time.perf_counter() - start)
        return results

    def work() -> None:
        while not isinstance(batch := handoff.get(), EndOfStream) and not halted.is_set():
            try:
                post(run_batch(batch))
            except BaseException as exc:  # reported on the loop, which stops the graph
                post(StageFailure(name, frame_index(batch[-1]), exc))
                return
        post(batch if isinstance(batch, EndOfStream) else END)

    def stopping() -> bool:
        return stop.is_set() and not finish_on_stop

    async def feed() -> None:
        """Hand over one batch per free slot: the next item, and with `pass_over` every item
        waiting behind it, so that the newest is the one processed."""
        while True:
            await slots.acquire()
            waiting = [await inbox.get()]
            if pass_over is not None:
                waiting += inbox.take_ready()
            ends = isinstance(waiting[-1], EndOfStream)  # END comes last, if at all
            batch = waiting[:-1] if ends else waiting
            if batch and not stopping():
                handoff.put(batch)
            if ends or stopping():
                handoff.put(waiting[-1] if ends and not stopping() else END)
                return

    async def halt_on_stop() -> None:
        """The moment a stop is asked for, the worker takes no new item (not one more frame)."""
        await stop.wait()
        if not finish_on_stop:
            halted.set()

    thread = threading.Thread(target=work, name=f"{name}-worker", daemon=True)
    thread.start()
    feeder = asyncio.create_task(feed())
    watcher = asyncio.create_task(halt_on_stop())
    try:
        while not isinstance(results := await finished.get(), EndOfStream):
            if isinstance(results, StageFailure):
                raise results
            for result in results:
                if result is not None:  # a passed-over item that is dropped
                    await outbox.put(result)
            slots.release()
            if stopping():
                halted.set()
    finally:
        feeder.cancel()
        watcher.cancel()
        halted.set()
        if interrupt is not None:
            interrupt()
        handoff.put(END)  # wakes the worker if it waits for an item
        await asyncio.to_thread(thread.join)
    await outbox.put(results)
    return results
