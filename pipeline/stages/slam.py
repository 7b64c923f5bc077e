"""The SLAM stage: one SplaTAM step per frame on the compute stream, with GPU gap timing."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch.profiler import record_function

from pipeline.frame import DeviceFrame
from pipeline.slam.splatam import FrameResult, SplaTAM
from pipeline.stages.upload import UploadedFrame

FrameObserver = Callable[[SplaTAM, DeviceFrame, FrameResult], None]


class SlamStep:
    """Callable run in the SLAM worker thread. On CUDA it brackets every frame with events on
    the compute stream, so the idle time between one frame's GPU work and the next is measured
    on the GPU's own clock. `observers` run after each frame, in this thread, at the one moment
    the map is not being changed (periodic saves, viewer snapshots); they must be quick."""

    def __init__(self, slam: SplaTAM, last_index: int | None, observers: Sequence[FrameObserver] = ()) -> None:
        self.slam = slam
        self.last_index = last_index
        self.observers = list(observers)
        self.cuda = slam.device.type == "cuda"
        self._events: list[tuple[torch.cuda.Event, torch.cuda.Event]] = []

    def __call__(self, uploaded: UploadedFrame) -> FrameResult:
        with record_function("slam_step"):
            if self.cuda:
                torch.cuda.set_device(self.slam.device)
                start = torch.cuda.Event(enable_timing=True)
                start.record()
            frame = uploaded.wait()
            result = self.slam.step(frame, is_last=frame.index == self.last_index)
            if self.cuda:
                end = torch.cuda.Event(enable_timing=True)
                end.record()
                self._events.append((start, end))
            for observe in self.observers:
                observe(self.slam, frame, result)
        return result

    def gpu_gaps_ms(self) -> list[float]:
        """Idle time on the compute stream between consecutive frames, milliseconds."""
        if not self._events:
            return []
        torch.cuda.synchronize()
        return [prev_end.elapsed_time(start) for (_, prev_end), (start, _) in zip(self._events, self._events[1:])]

    def gpu_busy_ms(self) -> float:
        """Sum of the spans from each frame's start event to its end event."""
        if not self._events:
            return 0.0
        torch.cuda.synchronize()
        return sum(start.elapsed_time(end) for start, end in self._events)

    def gpu_wall_ms(self) -> float:
        if not self._events:
            return 0.0
        torch.cuda.synchronize()
        return self._events[0][0].elapsed_time(self._events[-1][1])
