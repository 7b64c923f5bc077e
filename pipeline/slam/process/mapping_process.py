"""The mapping process: SLAM's mapping side, owning the Gaussians, their optimisation and the
keyframe store, fed tracked frames by the tracking process.

It never idles while there is work: a frame waiting is mapped first (offline each in turn;
live the newest, the older ones passed over); while none waits, refinement passes over the
stored keyframes improve the map, each ending as soon as a message arrives. Every mapped frame
and every pass publishes a map version into the shared map.

The parent owns shutdown: a terminal's Ctrl-C, `timeout` and a service manager signal the whole
process group, so this process ignores SIGINT and SIGTERM (the parent stops the run, has mapping
finish what it holds and says when to end); and it ends by itself the moment the parent ends,
however the parent ends (a kill -9 too), rather than refine an orphaned map for ever.
"""

from __future__ import annotations

import importlib
import queue
import signal
import time
import traceback
from dataclasses import dataclass
from typing import Any

import torch

from pipeline.config import Config
from pipeline.frame import DeviceFrame
from pipeline.processes import STOP_SIGNALS, end_with_the_parent
from pipeline.render import make_renderer
from pipeline.slam.cuda_graphs import synchronize_device
from pipeline.slam.handoff import TrackedFrame
from pipeline.slam.kernel_time import KernelTimer
from pipeline.slam.mapping.backend import BackendSettings, MappingBackend
from pipeline.slam.process import messages as m
from pipeline.slam.process.frame_ring import FrameRing, RingBookkeeping
from pipeline.slam.process.shared_map import MapControl, MapGeneration, MapWriter
from pipeline.slam.sides import backend_settings, loop_closer_for

BEAT_S = 0.2  # an idle mapping process shows a sign of life this often


@dataclass(frozen=True)
class MappingSetup:
    """What the mapping process starts with (pickled once, at spawn)."""

    config: Config
    device: str
    control: MapControl
    generation: MapGeneration  # the first slots to publish into
    heartbeat: torch.Tensor  # [1] float64 in shared memory: time.monotonic() of the last sign of life
    ring_books: RingBookkeeping  # the frame ring's free slots (the slots come by message)
    inbox: Any  # multiprocessing queue: tracking -> mapping
    outbox: Any  # mapping -> tracking
    live: bool
    threads: int  # torch's CPU threads in this process
    stop_refining: Any  # a multiprocessing event: set, a final refinement ends at its next step
    spawned: float  # time.monotonic() when the parent started this process (one clock for both)
    in_thread: bool  # a thread of the tracking process (`slam.schedule=thread`, mapping_thread.py)


def run_mapping_process(setup: MappingSetup) -> None:
    """The process's (or the thread's) target: the loop until Shutdown; a failure is reported,
    then raised."""
    entered = time.monotonic()
    if not setup.in_thread:  # a thread shares the process's signals, parent and CPU threads
        _leave_signals_to_the_parent()
        end_with_the_parent()  # nothing to save here: the parent owns the run's files
    try:
        if setup.in_thread:
            _use_a_stream_of_its_own(torch.device(setup.device))
        else:
            torch.set_num_threads(setup.threads)
        importlib.import_module("torch._dynamo")  # torch.optim's first optimiser imports it (seconds): start-up
        loop = MappingLoop(setup)
        setup.outbox.put(m.StartedUp(entered - setup.spawned, time.monotonic() - entered))
        loop.run()
    except BaseException as exc:
        setup.outbox.put(m.MappingFailed(f"{exc.__class__.__name__}: {exc}\n{traceback.format_exc()}"))
        raise


def _use_a_stream_of_its_own(device: torch.device) -> None:
    """A mapping thread's kernels on a CUDA stream of their own, beside tracking's (the current
    stream is per thread); the map slots and the frame ring synchronise the current stream."""
    if device.type == "cuda":
        torch.cuda.set_stream(torch.cuda.Stream(device))


def _leave_signals_to_the_parent() -> None:
    """Ignore the group's stop signals. They are blocked from before this process started
    (`processes.signals_blocked`), so one sent during its start-up is discarded here, never
    delivered as a KeyboardInterrupt halfway through an import."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


class MappingLoop:
    def __init__(self, setup: MappingSetup) -> None:
        self.setup = setup
        self.config = setup.config
        self.device = torch.device(setup.device)
        renderer = make_renderer(self.config.render, self.config.gaussians, self.device)
        self.settings: BackendSettings = backend_settings(self.config, renderer, self.device)
        self.backend = self._new_backend()
        self.writer = MapWriter(setup.control, setup.generation, self._grow)
        self.ring: FrameRing | None = None
        self.waiting: list[m.MapFrame] = []
        self.deferred: list[Any] = []  # messages that came while waiting for new slots
        self.running = True
        self.kernel_timer = KernelTimer()

    def _new_backend(self) -> MappingBackend:
        backend = MappingBackend(self.settings, loop_closer_for(self.config, self.settings), self.device)
        backend.on_step = self._beat
        return backend

    def run(self) -> None:
        while self.running:
            self._beat()
            for message in self._receive(block=not self._has_work()):
                self._handle(message)
            if self.waiting:
                self._map_waiting(everything=False)
            elif self._can_refine():
                self._refine()

    def _beat(self) -> None:
        self.setup.heartbeat[0] = time.monotonic()

    def _has_work(self) -> bool:
        return bool(self.waiting) or self._can_refine()

    def _can_refine(self) -> bool:
        back = self.backend
        return self.config.mapping.refine_while_idle and bool(back.keyframes) and back.intrinsics is not None

    def _receive(self, block: bool) -> list[Any]:
        """Every message waiting (after the deferred ones); with `block`, at least one or a beat."""
        received, self.deferred = self.deferred, []
        try:
            if block and not received:
                received.append(self.setup.inbox.get(timeout=BEAT_S))
            while True:
                received.append(self.setup.inbox.get_nowait())
        except queue.Empty:
            pass
        return received

    def _handle(self, message: Any) -> None:
        if isinstance(message, m.MapFrame):
            self.waiting.append(message)
        elif isinstance(message, m.UseFrameRing):
            self.ring = FrameRing(message.slots, self.setup.ring_books)
        elif isinstance(message, m.SendState):
            state = m.PackedBackendState.of(self.backend.state()) if self.backend.gaussians is not None else None
            self.setup.outbox.put(m.StateSent(message.request, state, self.writer.number))
        elif isinstance(message, m.RestoreState):
            saved = message.state.unpacked()
            self.backend.restore(saved)
            self._publish()
            self.setup.outbox.put(m.Done())
        elif isinstance(message, m.StartAfresh):
            self._map_waiting(everything=True)  # the warm-up's frames: their mapping compiles too
            self.backend = self._new_backend()
            self.setup.outbox.put(m.Done())
        elif isinstance(message, m.Finish):
            self._map_waiting(everything=True)
            stop = self.setup.stop_refining.is_set
            renders = self.backend.finish(message.final_renders, stop) if message.final_renders else 0
            if renders:
                self._publish()
            self.setup.outbox.put(m.Done(renders))
        elif isinstance(message, m.SampleKernels):
            self._sample_kernels(message.step)
        elif isinstance(message, m.Shutdown):
            self.running = False
        else:
            raise TypeError(f"the mapping process got an unknown message {message!r}")

    def _sample_kernels(self, step: str) -> None:
        """Start, stop or read the kernel recording; one that fails reads NaN, never a failure."""
        try:
            if step == "start":
                self.kernel_timer.start()
            elif step == "stop":
                synchronize_device()
                self.kernel_timer.stop()
        except (RuntimeError, AssertionError):
            self.kernel_timer = KernelTimer()
        if step == "read":
            try:
                busy_ms = self.kernel_timer.busy_ms()
            except (RuntimeError, AssertionError):
                busy_ms = float("nan")
            self.setup.outbox.put(m.KernelsSampled(busy_ms))

    def _map_waiting(self, everything: bool) -> None:
        """Offline, the oldest waiting frame (`everything`: all of them, in order); live, the newest,
        the older ones passed over."""
        if everything or not self.setup.live:
            batch, self.waiting = (self.waiting, []) if everything else (self.waiting[:1], self.waiting[1:])
            for frame in batch:
                self._map(frame)
            return
        *older, newest = self.waiting
        self.waiting = []
        assert self.ring is not None
        for frame in older:
            self.ring.take(frame.slot)  # frees the slot
            self.setup.outbox.put(m.FrameMapped(frame.index, False, 0, 0.0, 0.0))
        self._map(newest)

    def _map(self, handed: m.MapFrame) -> None:
        assert self.ring is not None
        slot = self.ring.take(handed.slot)
        frame = DeviceFrame(handed.index, handed.timestamp, slot.color, slot.depth, slot.intrinsics, None)
        tracked = TrackedFrame(frame, slot.c2w, handed.position, keyframe=handed.keyframe, lost=handed.lost)
        published = self.backend.latest
        done = self.backend.map(tracked, is_last=handed.is_last)
        if self.backend.latest is not published:  # a lost frame searched in vain changes no map: no copy
            self._publish()
        report = m.FrameMapped(handed.index, done.mapped, done.added, done.densify_s, done.mapping_s, done.closed)
        self.setup.outbox.put(report)

    def _refine(self) -> None:
        started = time.perf_counter()
        renders = self.backend.refine(self.config.mapping.iters, should_stop=self._interrupted)
        if renders:
            self._publish()
            self.setup.outbox.put(m.Refined(renders, time.perf_counter() - started))

    def _interrupted(self) -> bool:
        """Asked before each refinement step: a message waits (a frame, most often)."""
        return bool(self.deferred) or not self.setup.inbox.empty()

    def _publish(self) -> None:
        back = self.backend
        assert back.gaussians is not None
        self.writer.publish(back.gaussians, [k.pose for k in back.keyframes])

    def _grow(self, capacity: int, keyframe_capacity: int) -> MapGeneration:
        """Ask the tracking side for larger slots; other messages meanwhile are kept for later."""
        self.setup.outbox.put(m.GrowMap(capacity, keyframe_capacity))
        while True:
            self._beat()
            try:
                message = self.setup.inbox.get(timeout=BEAT_S)
            except queue.Empty:
                continue
            if isinstance(message, m.UseGeneration):
                return message.generation
            self.deferred.append(message)
