"""Feeding rerun without slowing SLAM.

At a frame boundary (the SLAM-stage observer) only what is cheap is taken: the poses of the
frames since the last boundary taken and the frame's images at the display size, copied to the
host (asynchronously on CUDA), and, when a map snapshot is due (`map_every_s`) and none is
waiting, a device copy of the Gaussians. A thread of its own copies that
to the host on its own CUDA stream and logs everything (`RerunRecording`). At most QUEUE_FRAMES
boundaries wait for it; while they do (the logger behind), a frame's images are not logged and
its pose goes with the next boundary taken, so the trajectory stays whole.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.config import ViewerConfig
from pipeline.frame import DeviceFrame
from pipeline.render import Gaussians
from pipeline.slam.handoff import FrameResult
from pipeline.slam.view import SlamView
from pipeline.ui.rerun_recording import MapSplats, RerunRecording
from pipeline.ui.thumbnail import Thumbnail, thumbnail

log = logging.getLogger("gsplatam")

QUEUE_FRAMES = 32  # boundaries waiting for the logger at most (images of 320x240: ~0.5 MB each)


@dataclass
class Boundary:
    """What the logger takes of one frame boundary."""

    first: int  # the position of poses[0] in the trajectory
    poses: torch.Tensor  # [K, 4, 4] camera-to-world on the host: the frames since the last boundary taken
    images: Thumbnail | None  # on the host: the frame's (None: the end of the run)
    map: Gaussians | None  # a copy on SLAM's device, when a snapshot was due
    ready: torch.cuda.Event | None  # recorded on SLAM's stream after the copies


class RerunFeed:
    """The SLAM-stage observer that logs the run to `recording` (a LiveFeed): every frame's pose
    and images, the trajectory, and the map at most every `map_every_s`. `device`: SLAM's."""

    def __init__(self, recording: RerunRecording, map_every_s: float, device: torch.device) -> None:
        self.recording = recording
        self.map_every_s = map_every_s
        self.cuda = device.type == "cuda"
        self.released = threading.Event()  # the LiveFeed contract: nothing here pauses SLAM
        self.skipped = 0  # frames whose images were not logged: the logger was behind
        self._taken = 0  # poses handed to the logger
        self._map_at = -float("inf")
        self._map_waiting = threading.Event()  # a map snapshot is in the queue
        self._slam: SlamView | None = None
        self._queue: queue.Queue[Boundary | None] = queue.Queue(maxsize=QUEUE_FRAMES)
        self._stream: torch.cuda.Stream | None = None  # the logger's, for the map's host copy
        self._centres = np.zeros((0, 3))  # the logger's: every camera centre logged
        self._thread = threading.Thread(target=self._work, name="rerun", daemon=True)
        self._thread.start()

    def __call__(self, slam: SlamView, frame: DeviceFrame, result: FrameResult) -> None:
        self._slam = slam
        if self._queue.full():
            self.skipped += 1
            return
        due = time.monotonic() - self._map_at >= self.map_every_s and not self._map_waiting.is_set()
        self._queue.put_nowait(self._take(slam, frame, due))

    def _take(self, slam: SlamView, frame: DeviceFrame | None, with_map: bool) -> Boundary:
        """The poses since the last boundary taken and `frame`'s images, on their way to the host;
        with `with_map`, a copy of the map on its device."""
        poses = slam.poses
        new = poses[self._taken :]
        boundary = Boundary(
            first=self._taken,
            poses=(torch.stack(new) if new else torch.zeros(0, 4, 4)).to("cpu", non_blocking=True),
            images=None if frame is None else _thumbnail_on_host(thumbnail(frame)),
            map=self._map_copy(slam.gaussians) if with_map and slam.gaussians is not None else None,
            ready=torch.cuda.Event() if self.cuda else None,
        )
        if boundary.ready is not None:
            boundary.ready.record()
        self._taken = len(poses)
        return boundary

    def _map_copy(self, gaussians: Gaussians) -> Gaussians:
        self._map_at = time.monotonic()
        self._map_waiting.set()
        fields = (gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits, gaussians.colors)
        return Gaussians(*(t.detach().to(torch.float32, copy=True) for t in fields))

    def finish(self) -> None:
        """SLAM has stopped: log the poses not logged yet and the final map, due or not."""
        self.released.set()
        if self._slam is not None:
            self._queue.put(self._take(self._slam, None, with_map=True))

    def linger(self, summary: str) -> None:
        """Log the run's summary; rerun's viewer is a process of its own and stays up without us."""
        self.recording.summary(summary)

    def close(self) -> None:
        """Log what is queued, then complete the recording (a `.rrd` renamed into place); safe twice."""
        if not self._thread.is_alive():
            return
        self._queue.put(None)
        self._thread.join()
        self.recording.close()

    def _work(self) -> None:
        while (boundary := self._queue.get()) is not None:
            try:
                self._log(boundary)
            except Exception:  # the sink must never stop SLAM
                log.exception("rerun: logging failed")

    def _log(self, boundary: Boundary) -> None:
        if boundary.ready is not None:
            boundary.ready.synchronize()
        rec, poses = self.recording, boundary.poses.double().numpy()
        for number, c2w in enumerate(poses, start=boundary.first):
            rec.at(number)
            rec.pose(c2w)
        self._centres = np.concatenate([self._centres, poses[:, :3, 3]])
        rec.trajectory("trajectory", self._centres, since=boundary.first)
        if boundary.images is not None:
            small = boundary.images
            rec.view(small.intrinsics.double().numpy(), small.width, small.height)
            rec.images(small.color.numpy(), small.depth.numpy())
        if boundary.map is not None:
            rec.map(self._map_on_host(boundary.map))
            self._map_waiting.clear()

    def _map_on_host(self, gaussians: Gaussians) -> MapSplats:
        """The map's host copy, on the logger's own CUDA stream (SLAM's does not wait for it)."""
        cuda = gaussians.means.is_cuda
        if cuda and self._stream is None:
            self._stream = torch.cuda.Stream(gaussians.means.device)
        with torch.cuda.stream(self._stream) if cuda else contextlib.nullcontext():
            return MapSplats.of(gaussians)


def _thumbnail_on_host(small: Thumbnail) -> Thumbnail:
    """Host copies, asynchronous from CUDA (read them after the boundary's `ready`)."""
    return Thumbnail(*(t.to("cpu", non_blocking=True) for t in (small.color, small.depth, small.intrinsics)))


def attach_rerun(config: ViewerConfig, device: torch.device, name: str) -> RerunFeed:
    """The feed of `--viewer rerun`: to a spawned rerun viewer, or to `config.rerun_save`."""
    recording = RerunRecording(name, Path(config.rerun_save) if config.rerun_save else None)
    return RerunFeed(recording, config.map_every_s, device)
