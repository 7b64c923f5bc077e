"""Bounded queues between stages, with an explicit overflow policy and an end-of-stream marker."""

from __future__ import annotations

import asyncio
from typing import Generic, Literal, TypeVar

from pipeline.errors import StageFailure

T = TypeVar("T")
Policy = Literal["block", "keep_newest"]


class EndOfStream:
    """The marker a stage sends after its last item."""

    def __repr__(self) -> str:
        return "END"


END = EndOfStream()


class StreamFailed(EndOfStream):
    """The end of a stream cut short by a failing stage: the stages after it finish the items
    before it, then the runtime raises `failure`."""

    def __init__(self, failure: StageFailure) -> None:
        self.failure = failure

    def __repr__(self) -> str:
        return f"END({self.failure})"


class StageQueue(Generic[T]):
    """A bounded FIFO. `block`: a full queue makes the producer wait (nothing lost, for offline
    data). `keep_newest`: a full queue drops its oldest item and counts it (for live sources)."""

    def __init__(self, maxsize: int, policy: Policy = "block") -> None:
        self._queue: asyncio.Queue[T | EndOfStream] = asyncio.Queue(maxsize)
        self.policy = policy
        self.dropped = 0
        self.max_depth = 0

    async def put(self, item: T | EndOfStream) -> None:
        if self.policy == "keep_newest" and not isinstance(item, EndOfStream):
            while self._queue.full():
                self._queue.get_nowait()
                self.dropped += 1
            self._queue.put_nowait(item)
        else:
            await self._queue.put(item)
        self.max_depth = max(self.max_depth, self._queue.qsize())

    async def get(self) -> T | EndOfStream:
        return await self._queue.get()

    def take_ready(self) -> list[T | EndOfStream]:
        """Every item already waiting, without waiting for more."""
        ready: list[T | EndOfStream] = []
        while not self._queue.empty():
            ready.append(self._queue.get_nowait())
        return ready
