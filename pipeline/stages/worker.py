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
) -> EndOfStream:
    """Apply `fn` to every item in order in a thread of its own. At most `in_flight` items are
    handed over or finished but not yet passed on (a bound on memory). Once `stop` is set the
    thread finishes the item in hand and takes no other. -> the end marker passed on (END, or
    the StreamFailed of a stage before this one); a failure of `fn` itself is raised."""
    loop = asyncio.get_running_loop()
    handoff: queue.SimpleQueue[Any] = queue.SimpleQueue()  # bounded by `slots`; put never blocks
    finished: asyncio.Queue[Any] = asyncio.Queue()
    slots = asyncio.Semaphore(in_flight)
    halted = threading.Event()

    def post(value: Any) -> None:
        loop.call_soon_threadsafe(finished.put_nowait, value)

    def work() -> None:
        while not isinstance(item := handoff.get(), EndOfStream) and not halted.is_set():
            start = time.perf_counter()
            try:
                result = fn(item)
            except BaseException as exc:  # reported on the loop, which stops the graph
                post(StageFailure(name, frame_index(item), exc))
                return
            stats.record(time.perf_counter() - start)
            post(result)
        post(item if isinstance(item, EndOfStream) else END)

    async def feed() -> None:
        while True:
            item = await inbox.get()
            if stop.is_set():
                item = END
            if isinstance(item, EndOfStream):
                handoff.put(item)
                return
            await slots.acquire()
            handoff.put(item)

    thread = threading.Thread(target=work, name=f"{name}-worker", daemon=True)
    thread.start()
    feeder = asyncio.create_task(feed())
    try:
        while not isinstance(result := await finished.get(), EndOfStream):
            if isinstance(result, StageFailure):
                raise result
            await outbox.put(result)
            slots.release()
            if stop.is_set():
                halted.set()
    finally:
        feeder.cancel()
        halted.set()
        handoff.put(END)  # wakes the worker if it waits for an item
        await asyncio.to_thread(thread.join)
    await outbox.put(result)
    return result
