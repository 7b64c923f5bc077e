"""A dataset on disk as a frame source."""

from __future__ import annotations

from collections.abc import AsyncIterator

from pipeline.frame import Frame
from pipeline.io.sources.datasets.base import Dataset, FrameRef
from pipeline.source import SourceCounters


class DatasetSource:
    """The frames of an offline dataset in order, from `start_at` (a resumed run). Not live:
    the runtime's queues block, so offline data loses no frame."""

    live = False

    def __init__(self, dataset: Dataset, start_at: int = 0) -> None:
        self.dataset = dataset
        self.start_at = start_at
        self.name = dataset.name
        self.counters = SourceCounters()

    @property
    def last_index(self) -> int | None:
        return len(self.dataset) - 1

    async def __aiter__(self) -> AsyncIterator[FrameRef]:
        for ref in self.dataset.refs[self.start_at :]:
            self.counters.received += 1
            yield ref

    def decode(self, ref: FrameRef) -> Frame:
        return self.dataset.decode(ref)
