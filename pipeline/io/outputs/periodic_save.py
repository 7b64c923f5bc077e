"""Saving a live run while it goes on: map, trajectory and checkpoint every few seconds."""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from pipeline.frame import DeviceFrame
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.slam.results import FrameResult
from pipeline.slam.splatam import SplaTAM
from pipeline.slam.state import Checkpoint

log = logging.getLogger("gsplatam")


class PeriodicSave:
    """A SLAM-stage observer. At a frame boundary, once `every_s` seconds have passed, it copies
    the SLAM state to the host (in the SLAM thread: the only moment the map is consistent) and
    writes the files in a thread of its own, so SLAM waits for the copy, not the disk."""

    def __init__(self, folder: RunFolder, every_s: float) -> None:
        self.folder = folder
        self.every_s = every_s
        self.timestamps: list[float] = []  # seconds, one per processed frame
        self._last = time.monotonic()
        self._writer = ThreadPoolExecutor(1, thread_name_prefix="save")
        self._pending: Future[None] | None = None

    def __call__(self, slam: SplaTAM, frame: DeviceFrame, result: FrameResult) -> None:
        self.timestamps.append(result.timestamp)
        if time.monotonic() - self._last >= self.every_s and (self._pending is None or self._pending.done()):
            self._last = time.monotonic()
            self._pending = self._writer.submit(self._write, slam.checkpoint(), np.array(self.timestamps))

    def _write(self, checkpoint: Checkpoint, timestamps: np.ndarray) -> None:
        try:
            self.folder.write_state(checkpoint, timestamps, None)
            log.info(
                "saved %d frames and %d Gaussians to %s", len(timestamps), len(checkpoint.gaussians), self.folder.path
            )
        except OSError as exc:
            log.error("periodic save to %s failed: %s", self.folder.path, exc)

    def save_now(self, slam: SplaTAM) -> None:
        """The final save (after SLAM stopped): waits for a save in progress, then writes."""
        self.close()
        self._write(slam.checkpoint(), np.array(self.timestamps))

    def close(self) -> None:
        self._writer.shutdown(wait=True)
