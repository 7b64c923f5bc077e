"""The stage contract: read a bounded queue until END, transform in an executor, write the next queue.

Every stage keeps its own statistics and names itself and its frame when it fails.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from functools import partial
from typing import Any

from torch.profiler import record_function

from pipeline.errors import StageFailure
from pipeline.stages.queues import EndOfStream, StageQueue, StreamFailed


@dataclass
class StageStats:
    name: str
    items: int = 0
    busy_s: float = 0.0
    latencies_s: list[float] = field(default_factory=list)

    def record(self, seconds: float) -> None:
        self.items += 1
        self.busy_s += seconds
        self.latencies_s.append(seconds)

    def summary(self) -> dict[str, float]:
        lat = sorted(self.latencies_s)
        return {
            "items": self.items,
            "busy_s": self.busy_s,
            "mean_ms": 1000 * self.busy_s / max(self.items, 1),
            "p95_ms": 1000 * lat[int(0.95 * (len(lat) - 1))] if lat else 0.0,
            "max_ms": 1000 * lat[-1] if lat else 0.0,
        }


def frame_index(item: Any) -> int | None:
    for holder in (item, getattr(item, "frame", None)):
        index = getattr(holder, "index", None)
        if isinstance(index, int):
            return index
    return None


def _in_range(name: str, fn: Callable[[Any], Any], item: Any) -> Any:
    with record_function(name):
        return fn(item)


async def transform_stage(
    name: str,
    fn: Callable[[Any], Any],
    inbox: StageQueue[Any],
    outbox: StageQueue[Any],
    executor: Executor,
    stats: StageStats,
) -> None:
    """Apply `fn` to every item in order, off the event loop, inside a profiler range named
    `name`. An item for which `fn` returns None is dropped (a live frame found unusable). When
    `fn` raises, the stream ends there: the items before it go on, then StreamFailed."""
    loop = asyncio.get_running_loop()
    ranged = partial(_in_range, name, fn)
    while not isinstance(item := await inbox.get(), EndOfStream):
        start = time.perf_counter()
        try:
            result = await loop.run_in_executor(executor, ranged, item)
        except Exception as exc:
            await outbox.put(StreamFailed(StageFailure(name, frame_index(item), exc)))
            return
        stats.record(time.perf_counter() - start)
        if result is not None:
            await outbox.put(result)
    await outbox.put(item)  # the end marker as it came: END, or an upstream StreamFailed
