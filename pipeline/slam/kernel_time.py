"""How busy the GPU's kernels keep it: kernel time over wall time, from CUDA's own records of
each kernel and copy (CUPTI, through torch.profiler), over a sampled window of frames.

Why a window: CUPTI's activity records cost a few microseconds per launch and memory per
record, too much for a whole run; one window after the first frames (compilation, graph
recording) shows the steady state. Only the device's activity is recorded (no host ops, no
shapes, no stacks). The busy time is the union of the kernel and copy intervals, so kernels of
two streams running at once count once. A process records only its own kernels; a mapping
process records its own over the same window, and the two add up, since kernels of two
processes never run at once on one GPU without MPS (the GPU time-slices their contexts).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, TypeVar

from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

from pipeline.frame import DeviceFrame
from pipeline.slam.cuda_graphs import synchronize_device
from pipeline.slam.handoff import FrameResult
from pipeline.slam.view import SlamView

log = logging.getLogger("gsplatam")
T = TypeVar("T")

WINDOW_START = 10  # frames done before the window opens
WINDOW_FRAMES = 50  # frames the window spans


def union_ms(intervals: Iterable[tuple[float, float]]) -> float:
    """The length of the union of (start, end) intervals, in their unit."""
    total, reach = 0.0, -float("inf")
    for start, end in sorted(intervals):
        if end <= reach:
            continue
        total += end - max(start, reach)
        reach = end
    return total


class _ProfilerThread:
    """Kineto, behind torch.profiler, must be started and stopped in one thread, and the same
    thread for the whole process (another raises "External init callback must run in same
    thread as registerClient" and can crash): every start and stop of this process runs here."""

    _shared: _ProfilerThread | None = None
    _creating = threading.Lock()

    def __init__(self) -> None:
        self._calls: queue.SimpleQueue[tuple[Callable[[], Any], Future[Any]]] = queue.SimpleQueue()
        threading.Thread(target=self._serve, name="kernel-profiler", daemon=True).start()

    @classmethod
    def shared(cls) -> _ProfilerThread:
        with cls._creating:
            if cls._shared is None:
                cls._shared = _ProfilerThread()
            return cls._shared

    def call(self, fn: Callable[[], T]) -> T:
        return self.submit(fn).result()

    def submit(self, fn: Callable[[], T]) -> Future[T]:
        done: Future[T] = Future()
        self._calls.put((fn, done))
        return done

    def _serve(self) -> None:
        while True:
            fn, done = self._calls.get()
            try:
                done.set_result(fn())
            except BaseException as exc:  # handed to the caller
                done.set_exception(exc)


class KernelTimer:
    """Records this process's kernels and copies between `start()` and `stop()`. The stop is
    handed to the profiler's thread without waiting, and the records are read (seconds of
    parsing) only by `busy_ms()`, after the run: the window costs SLAM CUPTI's own overhead
    per launch, nothing at its ends."""

    def __init__(self) -> None:
        self._profile: profile | None = None
        self._stopped: Future[None] | None = None
        self._started = 0.0
        self.wall_ms = 0.0

    def start(self) -> None:
        self._profile = profile(activities=[ProfilerActivity.CUDA])
        _ProfilerThread.shared().call(self._profile.start)
        self._started = time.perf_counter()

    def stop(self) -> None:
        assert self._profile is not None
        self.wall_ms = 1000 * (time.perf_counter() - self._started)
        self._stopped = _ProfilerThread.shared().submit(self._profile.stop)

    def busy_ms(self) -> float:
        """The union of kernel and copy intervals of the window, milliseconds."""
        assert self._profile is not None and self._stopped is not None
        self._stopped.result()
        recording, self._profile, self._stopped = self._profile, None, None
        device = [
            (e.time_range.start, e.time_range.end)
            for e in recording.events()
            if e.device_type == DeviceType.CUDA and not e.is_user_annotation
        ]
        return union_ms(device) / 1000.0


@dataclass(frozen=True)
class KernelSample:
    busy_fraction: float  # kernel and copy time over wall time, all processes of the session
    busy_ms: float
    window_ms: float
    frames: tuple[int, int]  # frames done when the window opened and closed


class KernelSampler:
    """A SLAM-stage observer: opens the window after WINDOW_START frames and closes it
    WINDOW_FRAMES later (or at the end of a shorter run); `close()` reads the sample after the
    run. `elsewhere(step)` does the same in the session's other processes: "start", "stop", and
    "read", which returns their busy ms."""

    def __init__(self, elsewhere: Callable[[str], float]) -> None:
        self.elsewhere = elsewhere
        self.timer = KernelTimer()
        self.sample: KernelSample | None = None
        self.failed = False
        self._window: tuple[int, int | None] | None = None  # frames done when it opened and closed

    def __call__(self, slam: SlamView, frame: DeviceFrame, result: FrameResult) -> None:
        done = slam.frames_done
        if self._window is None and not self.failed and done >= WINDOW_START:
            self._window = (done, None)
            self._measured(self._open)
        elif self._window is not None and self._window[1] is None and done >= self._window[0] + WINDOW_FRAMES:
            self._window = (self._window[0], done)
            self._measured(self._stop)

    def close(self, frames_done: int) -> None:
        """After the run: close a window still open, and read the sample."""
        if self._window is None or self.failed:
            return
        if self._window[1] is None:
            self._window = (self._window[0], frames_done)
            self._measured(self._stop)
        self._measured(self._read)

    def _measured(self, step: Callable[[], None]) -> None:
        """A measurement that fails is reported once and given up; it never stops the run."""
        try:
            step()
        except (RuntimeError, AssertionError) as exc:
            log.warning("kernel busy fraction not measured: %s", exc)
            self.failed = True

    def _open(self) -> None:
        self.elsewhere("start")
        self.timer.start()

    def _stop(self) -> None:
        synchronize_device()
        self.timer.stop()
        self.elsewhere("stop")

    def _read(self) -> None:
        assert self._window is not None and self._window[1] is not None
        busy_ms = self.timer.busy_ms() + self.elsewhere("read")
        wall_ms = self.timer.wall_ms
        fraction = busy_ms / wall_ms if wall_ms > 0 else float("nan")
        self.sample = KernelSample(fraction, busy_ms, wall_ms, (self._window[0], self._window[1]))
