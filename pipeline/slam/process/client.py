"""The tracking process's handle on the mapping process: starts it (spawn), hands it frames,
reads its map versions, asks for its state, and watches that it lives.

A listener thread takes the mapping process's messages as they come (requests for larger map
slots are answered at once, so mapping never waits on tracking's frame clock) and checks, every
WATCH_S, that the process is alive and has shown a sign of life within `slam.backend_timeout_s`
of this process's own running time: a stretch in which this process did not run itself (Ctrl-Z
on the terminal, SIGSTOP to the group) says nothing of the mapping process and is not counted.
A failure is kept and raised (MappingProcessFailed) from the next call on the tracking side.

This process owns shutdown: the mapping process is started with SIGINT and SIGTERM blocked (it
then ignores them; mapping_process.py) and ends when this process ends.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import torch
import torch.multiprocessing as mp

from pipeline.config import Config, switched_on
from pipeline.errors import MappingProcessFailed
from pipeline.frame import DeviceFrame
from pipeline.processes import signals_blocked
from pipeline.slam.loops.detection import closed_loop_line
from pipeline.slam.map_version import MapVersion
from pipeline.slam.process import messages as m
from pipeline.slam.process.frame_ring import FrameRing, RingBookkeeping
from pipeline.slam.process.mapping_process import MappingSetup, run_mapping_process
from pipeline.slam.process.mapping_thread import ThreadContext, import_the_compiler
from pipeline.slam.process.shared_map import (
    NEWEST_SLOT,
    VERSION,
    MapControl,
    MapReader,
    SharedMemoryShort,
    share,
    shared_memory_advice,
)
from pipeline.slam.state import BackendState

log = logging.getLogger("gsplatam")

WATCH_S = 0.2  # how often the listener checks the mapping process (a death is noticed this soon)
STARTUP_S = 120.0  # a mapping process that has not begun its loop this long after its start has failed
SHUTDOWN_S = 30.0  # a mapping process that does not end this long after Shutdown is terminated
MAX_WATCH_STEP_S = 2 * WATCH_S  # a longer gap between two watches: this process was not running
ABANDONED = "stopped waiting for the mapping process (a second signal)"


class MappingProcess:
    def __init__(self, config: Config, device: torch.device, live: bool) -> None:
        """Start the mapping side: a process of its own, or under `slam.schedule=thread` a thread
        of this process (mapping_thread.py)."""
        self.in_thread = config.slam.schedule == "thread"
        self.side = "the mapping thread" if self.in_thread else "the mapping process"  # in what it reports
        context: Any = ThreadContext() if self.in_thread else mp.get_context("spawn")
        if self.in_thread:
            import_the_compiler(switched_on(config.run.compile, device.type == "cuda"))
        self.config = config
        self.device = device
        self.live = live
        self.control = MapControl.create(context)
        self.reader = MapReader(self.control, 1 if config.gaussians.isotropic else 3, device)
        self.heartbeat = share(torch.zeros(1, dtype=torch.float64))  # 0 until the process's first beat
        self._last_beat, self._silent_s, self._last_watch = 0.0, 0.0, time.monotonic()
        self.to_mapping = context.Queue()
        self.from_mapping = context.Queue()
        self.ring_books = RingBookkeeping.create(2 if live else max(1, config.slam.max_lead), context)
        self.stop_refining = context.Event()
        setup = MappingSetup(
            config, str(device), self.control, self.reader.first, self.heartbeat, self.ring_books,
            self.to_mapping, self.from_mapping, live, max(1, torch.get_num_threads() // 2), self.stop_refining,
            time.monotonic(), self.in_thread,
        )  # fmt: skip
        self.process = context.Process(target=run_mapping_process, args=(setup,), name="gsplatam-mapping", daemon=True)
        with signals_blocked():
            self.process.start()
        self.ring: FrameRing | None = None
        self.failure = ""  # why the mapping process is taken as failed; empty while it works
        self.abandoned = False  # no longer waited for (a second signal): what is complete is used
        self.handed: list[int] = []  # the index of every frame handed over, in order
        self.mapped: list[m.FrameMapped] = []  # one per frame handed over and taken, in order
        self.refinement_renders = 0
        self.refinement_s = 0.0
        self.started_up: m.StartedUp | None = None  # None until the process's loop is ready
        self._requests = itertools.count()
        self._state_replies: dict[int, Future[m.StateSent]] = {}
        self._kernels: Future[m.KernelsSampled] = Future()
        self._done: queue.SimpleQueue[m.Done | None] = queue.SimpleQueue()  # None: the process failed
        self._changed = threading.Condition()  # notified whenever the mapping process says anything
        self._closing = threading.Event()
        self._ended = threading.Event()  # set by close() once the mapping side ended (or was left behind)
        self._listener = threading.Thread(target=self._listen, name="mapping-listener", daemon=True)
        self._listener.start()

    # The tracking side's calls (one thread).

    def check(self) -> None:
        """Raise MappingProcessFailed if the mapping process died, hung or failed, or is no
        longer waited for."""
        if self.failure or self.abandoned:
            raise MappingProcessFailed(self.failure or ABANDONED)

    def stop_waiting(self) -> None:
        """Wait for the mapping process no more (a second signal): every wait on it ends at once
        with MappingProcessFailed, and what is complete is used. Safe in a signal handler."""
        self.abandoned = True  # (not stop_refining.set(): its lock is not reentrant; close() ends the process)
        self._done.put(None)  # SimpleQueue.put is reentrant: a handler may call it during a get

    def unmapped(self) -> list[int]:
        """The frames handed over that mapping never took (it ended first)."""
        taken = {report.index for report in self.mapped}
        return [index for index in self.handed if index not in taken]

    def newest_version(self) -> int:
        """The number of the newest complete version (0 before the first)."""
        fields = self.control.fields
        with self.control.lock:
            slot = int(fields[NEWEST_SLOT])
            return 0 if slot < 0 else int(fields[VERSION + slot])

    def hold_newest(self, at_least: int) -> MapVersion:
        """The newest map version, waiting until one of number `at_least` or later exists."""
        self._wait_for(lambda: self.newest_version() >= at_least)
        version = self.reader.hold()
        assert version is not None
        return version

    def hand_over(
        self,
        frame: DeviceFrame,
        c2w: torch.Tensor,
        position: int,
        is_last: bool,
        keyframe: bool = False,
        lost: bool = False,
    ) -> bool:
        """Give a tracked frame (pose `c2w` [4, 4] camera-to-world, `position` among the run's
        poses; `keyframe`: chosen as one by the tracking side; `lost`: judged lost, to be searched
        for a loop, never mapped) to mapping. Offline it waits
        for a free ring slot (a bound on tracking's lead); live it never waits. -> whether the
        frame was handed over (live: False when mapping holds every slot)."""
        self.check()
        ring = self._ring_for(frame)
        slot = ring.put(frame, c2w, 0.0 if self.live else WATCH_S)
        while slot is None and not self.live:
            self.check()
            slot = ring.put(frame, c2w, WATCH_S)
        if slot is None:
            return False
        self.to_mapping.put(m.MapFrame(slot, frame.index, position, frame.timestamp, is_last, keyframe, lost))
        self.handed.append(frame.index)
        return True

    def caught_up(self) -> bool:
        """Mapping has reported on every frame handed over: a version held from now on holds
        every one it mapped."""
        return len(self.mapped) >= len(self.handed)

    def state(self) -> tuple[BackendState | None, int]:
        """The mapping side's state now (a host copy; None before the first frame) and the map
        version it belongs to."""
        request = next(self._requests)
        reply: Future[m.StateSent] = Future()
        self._state_replies[request] = reply
        self.to_mapping.put(m.SendState(request))
        self._wait_for(reply.done)
        sent = reply.result()
        return (None if sent.state is None else sent.state.unpacked()), sent.version

    def sample_kernels(self, step: str) -> float:
        """Start, stop or read the recording of the mapping process's kernels (`KernelSampler`);
        a read returns their busy ms."""
        if step != "read":
            self.to_mapping.put(m.SampleKernels(step))
            return 0.0
        reply: Future[m.KernelsSampled] = Future()
        self._kernels = reply
        self.to_mapping.put(m.SampleKernels(step))
        self._wait_for(reply.done)
        return reply.result().busy_ms

    def restore(self, state: BackendState) -> None:
        self._call(m.RestoreState(m.PackedBackendState.of(state)))

    def start_afresh(self) -> None:
        self._call(m.StartAfresh())

    def finish(self, final_renders: int, should_stop: Callable[[], bool] | None = None) -> int:
        """Map every frame still waiting, then `final_renders` view renders of refinement over
        every keyframe, which ends at its next step once `should_stop()`. -> the renders done."""
        return self._call(m.Finish(final_renders), should_stop).renders

    def close(self) -> None:
        """End the mapping process (after what it was given) and the listener; safe twice."""
        if self._closing.is_set():
            return
        self._closing.set()
        self.stop_refining.set()
        if self.process.is_alive() and not self.failure and not self.abandoned:
            self.to_mapping.put(m.Shutdown())
            self.process.join(SHUTDOWN_S)
        if self.process.is_alive():
            if not self.failure:
                log.warning(
                    "%s did not end within %.0f s: %s", self.side, SHUTDOWN_S, "left" if self.in_thread else "killed"
                )
            self.process.kill()  # SIGKILL: a hung (even a stopped) process ends too
            if not self.in_thread:  # (a thread cannot be killed: a hung one is left, a daemon)
                self.process.join()
        self._ended.set()
        self._listener.join()
        self.reader.release()

    def _ring_for(self, frame: DeviceFrame) -> FrameRing:
        if self.ring is None:
            self.ring = FrameRing.allocate(self.ring_books, frame.height, frame.width, self.device)
            self.to_mapping.put(m.UseFrameRing(self.ring.slots))
        if not self.ring.fits(frame):
            raise ValueError(f"frame {frame.index} is {frame.width}x{frame.height}, unlike the frames before it")
        return self.ring

    def _call(self, message: Any, should_stop: Callable[[], bool] | None = None) -> m.Done:
        """Send a request that the mapping process answers with Done; wait for it (once
        `should_stop()`, a refinement it runs ends at its next step)."""
        self.check()
        self.to_mapping.put(message)
        while True:
            try:
                done = self._done.get(timeout=WATCH_S)
            except queue.Empty:
                if should_stop is not None and should_stop():
                    self.stop_refining.set()
                continue
            if done is None:
                self.check()
            assert done is not None
            return done

    def _wait_for(self, ready: Callable[[], bool]) -> None:
        """Until `ready()`, or the mapping process fails (then MappingProcessFailed)."""
        with self._changed:
            while not ready():
                self.check()
                self._changed.wait(WATCH_S)
        self.check()

    # The listener thread.

    def _listen(self) -> None:
        while True:
            try:
                message = self.from_mapping.get(timeout=WATCH_S)
            except queue.Empty:
                message = None
            if message is not None:
                self._dispatch(message)
            if self._ended.is_set():
                return
            if not self.failure and not self._closing.is_set():
                self._watch()
            with self._changed:
                self._changed.notify_all()

    def _dispatch_the_rest(self) -> None:
        """Dispatch what the mapping side put before it ended: the listener's last wait may have
        timed out just before its last message came (seen: a thread's MappingFailed, read as an
        unexplained end)."""
        while True:
            try:
                self._dispatch(self.from_mapping.get(timeout=WATCH_S))
            except queue.Empty:
                return

    def _dispatch(self, message: Any) -> None:
        if isinstance(message, m.GrowMap):
            try:
                generation = self.reader.grow(message.capacity, message.keyframe_capacity)
            except SharedMemoryShort as exc:
                self._fail(f"the map outgrew the shared memory: {exc}")
                return
            log.debug("map slots grown to %d Gaussians, %d keyframes", message.capacity, message.keyframe_capacity)
            self.to_mapping.put(m.UseGeneration(generation))
        elif isinstance(message, m.FrameMapped):
            self.mapped.append(message)
            for loop in message.closed:
                log.info(closed_loop_line(loop))
        elif isinstance(message, m.StartedUp):
            self.started_up = message
            log.debug(
                "%s started: interpreter and imports %.1f s, set-up %.1f s",
                self.side, message.interpreter_s, message.setup_s,
            )  # fmt: skip
        elif isinstance(message, m.Refined):
            self.refinement_renders += message.renders
            self.refinement_s += message.seconds
        elif isinstance(message, m.StateSent):
            self._state_replies.pop(message.request).set_result(message)
        elif isinstance(message, m.KernelsSampled):
            self._kernels.set_result(message)
        elif isinstance(message, m.Done):
            self._done.put(message)
        elif isinstance(message, m.MappingFailed):
            advice = f"; {shared_memory_advice()}" if "unable to allocate shared memory" in message.error else ""
            self._fail(f"{self.side} failed: {message.error.splitlines()[0]}{advice}")
            log.debug("the mapping process's traceback:\n%s", message.error)

    def _watch(self) -> None:
        if not self.process.is_alive():
            self._dispatch_the_rest()  # its MappingFailed, put just before it ended, names the cause
            self._fail(f"{self.side} ended unexpectedly (exit code {self.process.exitcode})")
            return
        now = time.monotonic()
        step, self._last_watch = min(now - self._last_watch, MAX_WATCH_STEP_S), now
        beat = float(self.heartbeat[0])
        if beat != self._last_beat:
            self._last_beat, self._silent_s = beat, 0.0
            return
        self._silent_s += step  # counted in this process's own running time only
        timeout = self.config.slam.backend_timeout_s
        if beat == 0.0:  # still starting (importing torch, initialising CUDA)
            if self._silent_s > max(STARTUP_S, timeout):
                self._fail(f"{self.side} did not start within {max(STARTUP_S, timeout):.0f} s")
            return
        if self._silent_s > timeout:
            self._fail(f"{self.side} has shown no sign of life for {self._silent_s:.0f} s (slam.backend_timeout_s)")

    def _fail(self, why: str) -> None:
        if not self.failure:
            self.failure = why
            self._done.put(None)
