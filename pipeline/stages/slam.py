"""The SLAM stages: SLAM per frame in one thread (the sequential schedule, and the process
schedule, whose mapping runs in a process of its own), or tracking and mapping in two threads
with their own CUDA streams (the overlapped schedule).

Observers run after each frame in the thread that finished it, at the one moment the published
map and the poses up to that frame are consistent (periodic saves, viewer snapshots); they must
be quick.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence

import torch
from torch.profiler import record_function

from pipeline.frame import DeviceFrame
from pipeline.slam.frontend import TrackedFrame
from pipeline.slam.results import FrameResult
from pipeline.slam.splatam import SplaTAM
from pipeline.slam.view import SlamView, SteppedSlam
from pipeline.stages.gpu_spans import GpuSpans
from pipeline.stages.upload import UploadedFrame
from pipeline.stages.worker import ThreadedStage

log = logging.getLogger("gsplatam")

FrameObserver = Callable[[SlamView, DeviceFrame, FrameResult], None]


@contextlib.contextmanager
def _on_stream(stream: torch.cuda.Stream | None) -> Iterator[None]:
    if stream is None:
        yield
        return
    with torch.cuda.stream(stream):
        yield


def _stream_for(slam: SplaTAM) -> torch.cuda.Stream | None:
    return torch.cuda.Stream(slam.device) if slam.device.type == "cuda" else None


class LeadGate:
    """Tracking waits here before each frame: for the first map (tracking needs one), and
    offline for mapping to be at most `max_lead` frames behind (None: no bound, live)."""

    def __init__(self, max_lead: int | None) -> None:
        self.max_lead = max_lead
        self._tracked = 0
        self._passed = 0
        self._open = threading.Event()  # set when the graph stops: nothing waits any more
        self._changed = threading.Condition()

    def enter(self) -> None:
        with self._changed:
            self._changed.wait_for(self._room)
            self._tracked += 1

    def _room(self) -> bool:
        if self._open.is_set() or self._tracked == 0:
            return True
        if self._passed == 0:
            return False  # the first frame makes the map that tracking needs
        return self.max_lead is None or self._tracked - self._passed <= self.max_lead

    def passed(self) -> None:
        with self._changed:
            self._passed += 1
            self._changed.notify_all()

    def open(self) -> None:
        with self._changed:
            self._open.set()
            self._changed.notify_all()


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


def sequential_stages(
    slam: SteppedSlam,
    last_index: int | None,
    observers: Sequence[FrameObserver],
    live: bool = False,
    warm_up: bool = False,
) -> list[ThreadedStage]:
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
    return [stage]


def overlapped_stages(
    slam: SplaTAM,
    last_index: int | None,
    observers: Sequence[FrameObserver],
    max_lead: int,
    live: bool,
    warm_up: bool = False,
) -> list[ThreadedStage]:
    """Tracking and mapping in two threads and two CUDA streams. Offline, tracking runs at most
    `max_lead` frames ahead of mapping; live, it never waits for mapping, and mapping takes the
    newest tracked frame, passing the older ones on unmapped; and tracking starts only the newest
    uploaded frame (the older ones are dropped and counted). With `warm_up` (live only) the first
    frame warms both sides up in the tracking thread, before mapping has anything, and is dropped."""
    gate = LeadGate(None if live else max_lead)
    track_spans, map_spans = GpuSpans(slam.device), GpuSpans(slam.device)
    track_stream, map_stream = _stream_for(slam), _stream_for(slam)
    warmed = warm_up_on_first(slam) if warm_up else _never
    view = SlamView(slam)

    def track(uploaded: UploadedFrame) -> TrackedFrame | None:
        with _on_stream(track_stream):
            if warmed(uploaded.wait()):
                tracking.dropped += 1
                return None
        gate.enter()
        with record_function("tracking_stage"), _on_stream(track_stream), track_spans.frame():
            return slam.frontend.track(uploaded.wait(), slam.backend.latest)

    def finish(tracked: TrackedFrame, result: FrameResult) -> FrameResult:
        gate.passed()
        for observe in observers:
            observe(view, tracked.frame, result)
        return result

    def map_frame(tracked: TrackedFrame) -> FrameResult:
        with record_function("mapping_stage"), _on_stream(map_stream):
            with map_spans.frame():
                result = slam.backend.map(tracked, is_last=tracked.frame.index == last_index)
            return finish(tracked, result)

    def skip(tracked: TrackedFrame) -> FrameResult:
        with _on_stream(map_stream):
            return finish(tracked, slam.backend.skip(tracked))

    tracking = ThreadedStage("tracking", track, track_spans, interrupt=gate.open)
    if live:
        tracking.pass_over = tracking.drop
    return [
        tracking,
        ThreadedStage("mapping", map_frame, map_spans, pass_over=skip if live else None, finish_on_stop=True),
    ]
