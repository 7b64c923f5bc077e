"""Source stages: where frames enter the pipeline."""

from __future__ import annotations

from collections.abc import AsyncIterator

from pipeline.io.dataset import Dataset, FrameRef


class DatasetSource:
    """Frame references of an offline dataset, in order (`run` puts them on a blocking queue:
    offline data loses no frame)."""

    name = "source"

    def __init__(self, dataset: Dataset, start_at: int = 0) -> None:
        self.dataset = dataset
        self.start_at = start_at

    @property
    def last_index(self) -> int | None:
        return len(self.dataset) - 1

    async def __aiter__(self) -> AsyncIterator[FrameRef]:
        for ref in self.dataset.refs[self.start_at :]:
            yield ref
