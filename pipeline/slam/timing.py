"""Per-stage timing of a frame: CUDA events on the GPU, read only at the frame boundary."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch.profiler import record_function


class StageClock:
    """Measures named stages; `read()` waits for the stages' end events (on their stream, not the
    whole device: other SLAM stages run on other streams) and returns seconds per stage."""

    def __init__(self, device: torch.device) -> None:
        self.cuda = device.type == "cuda"
        self._spans: dict[str, tuple[object, object]] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        with record_function(name):
            start = self._mark()
            yield
            self._spans[name] = (start, self._mark())

    def _mark(self) -> object:
        if self.cuda:
            event = torch.cuda.Event(enable_timing=True)
            event.record()
            return event
        return time.perf_counter()

    def read(self) -> dict[str, float]:
        if self.cuda:
            for _, end in self._spans.values():
                end.synchronize()  # type: ignore[attr-defined]  # this stream's work only: other stages run on
            times = {name: start.elapsed_time(end) / 1000.0 for name, (start, end) in self._spans.items()}  # type: ignore[attr-defined]
        else:
            times = {name: end - start for name, (start, end) in self._spans.items()}  # type: ignore[operator]
        self._spans.clear()
        return times
