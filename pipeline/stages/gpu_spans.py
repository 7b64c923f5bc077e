"""Each frame's span of work on a stage's CUDA stream, measured on the GPU's own clock."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

from pipeline.slam.cuda_graphs import synchronize_device


class GpuSpans:
    """Events recorded on the current stream around each frame; read only after the run."""

    def __init__(self, device: torch.device) -> None:
        self.cuda = device.type == "cuda"
        self._events: list[tuple[torch.cuda.Event, torch.cuda.Event]] = []

    @contextmanager
    def frame(self) -> Iterator[None]:
        if not self.cuda:
            yield
            return
        start = torch.cuda.Event(enable_timing=True)
        start.record()
        yield
        end = torch.cuda.Event(enable_timing=True)
        end.record()
        self._events.append((start, end))

    def gaps_ms(self) -> list[float]:
        """Idle time on the stream between consecutive frames, milliseconds."""
        if not self._events:
            return []
        synchronize_device()
        return [prev_end.elapsed_time(start) for (_, prev_end), (start, _) in zip(self._events, self._events[1:])]
