"""The SLAM stage: SLAM per frame in one thread (the sequential schedule, and the process
schedule, whose mapping runs in a process of its own).

Observers run after each frame in the thread that finished it, at the one moment the published
map and the poses up to that frame are consistent (periodic saves, viewer snapshots); they must
be quick.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

from torch.profiler import record_function

from pipeline.frame import DeviceFrame
from pipeline.slam.handoff import FrameResult
from pipeline.slam.view import SlamView, SteppedSlam
from pipeline.stages.gpu_spans import GpuSpans
from pipeline.stages.upload import UploadedFrame
from pipeline.stages.worker import ThreadedStage

log = logging.getLogger("gsplatam")

FrameObserver = Callable[[SlamView, DeviceFrame, FrameResult], None]


def warm_up_on_first(slam: SteppedSlam) -> Callable[[DeviceFrame], bool]:
    """-> `warmed(frame)`: the first call, before any frame was tracked, warms SLAM up on `frame`
    (`SplaTAM.warm_up`) and returns True: the stage drops that frame and takes the newest next.
    Later calls return False."""
    pending = True

    def warmed(frame: DeviceFrame) -> bool:
        nonlocal pending
        if not pending or slam.frontend.frames_done:
            return False
        pending = False
        started = time.perf_counter()
        slam.warm_up(frame)
        seconds = time.perf_counter() - started
        log.info("SLAM warmed up on frame %d in %.1f s; it starts from the newest frame", frame.index, seconds)
        return True

    return warmed


def _never(frame: DeviceFrame) -> bool:
    return False


def slam_stage(
    slam: SteppedSlam,
    last_index: int | None,
    observers: Sequence[FrameObserver],
    live: bool = False,
    warm_up: bool = False,
) -> ThreadedStage:
    """Track and map each frame in one thread, on the thread's current stream. Live, a frame is
    started only when no newer one is waiting (the older ones are dropped and counted). With
    `warm_up` (live only) the first frame warms SLAM up and is dropped (`warm_up_on_first`)."""
    spans = GpuSpans(slam.device)
    warmed = warm_up_on_first(slam) if warm_up else _never
    view = SlamView(slam)

    def step(uploaded: UploadedFrame) -> FrameResult | None:
        with record_function("slam_step"), spans.frame():
            frame = uploaded.wait()
            if warmed(frame):
                stage.dropped += 1
                return None
            result = slam.step(frame, is_last=frame.index == last_index)
        for observe in observers:
            observe(view, frame, result)
        return result

    stage = ThreadedStage("slam", step, spans)
    if live:
        stage.pass_over = stage.drop
    return stage
