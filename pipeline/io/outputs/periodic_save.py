"""Saving a run while it goes on (map, trajectories and checkpoint every few seconds), and what
a run does when its folder cannot be written (a full disk)."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from pipeline.errors import OutputError
from pipeline.frame import DeviceFrame
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.slam.handoff import FrameResult
from pipeline.slam.state import Checkpoint
from pipeline.slam.view import SlamView

log = logging.getLogger("gsplatam")

FrameStamp = tuple[float, np.ndarray | None]  # (timestamp s, reference camera-to-world [4, 4] or None)


class PeriodicSave:
    """A SLAM-stage observer. At a frame boundary, once `every_s` seconds have passed, it copies
    the SLAM state to the host (in the SLAM thread: the only moment the map is consistent) and
    writes the files in a thread of its own, so SLAM waits for the copy, not the disk.

    A failed write (a save, or a frames.csv line: `report_failure`) is logged once, until a save
    works again, and kept in `error` for the status; the files of the last complete save stay.
    With `stop_on_failure` the next frame boundary then raises OutputError, ending the run (a
    dataset run stops; a live daemon goes on). `run` describes the run in every checkpoint;
    `earlier` holds the frames a resumed run did before."""

    def __init__(
        self,
        folder: RunFolder,
        run: RunDescription,
        every_s: float,
        earlier: Sequence[FrameStamp] = (),
        stop_on_failure: bool = False,
    ) -> None:
        self.folder = folder
        self.run = run
        self.every_s = every_s
        self.stop_on_failure = stop_on_failure
        self.stamps: list[FrameStamp] = list(earlier)  # one per frame SLAM has done
        self.error = ""  # why the last write failed; empty while writes work
        self.saved_frames = len(self.stamps)  # frames in the last complete save (a resumed run's checkpoint)
        self._last = time.monotonic()
        self._writer = ThreadPoolExecutor(1, thread_name_prefix="save")
        self._pending: Future[bool] | None = None

    def __call__(self, slam: SlamView, frame: DeviceFrame, result: FrameResult) -> None:
        reference = None if result.c2w_gt is None else result.c2w_gt.double().numpy()
        self.stamps.append((result.timestamp, reference))
        if self.error and self.stop_on_failure:
            raise OutputError(self.error)
        due = time.monotonic() - self._last >= self.every_s and slam.gaussians is not None  # a map to save
        if due and (self._pending is None or self._pending.done()):
            self._last = time.monotonic()
            self._pending = self._writer.submit(self._save, slam.checkpoint(), list(self.stamps))

    def report_failure(self, what: str, exc: OSError) -> None:
        """A write of the run folder failed (`what`: the file or files)."""
        if not self.error:
            log.error("cannot write %s in %s: %s; %s", what, self.folder.path, exc.strerror or exc, self._kept())
        self.error = f"cannot write {what} in {self.folder.path}: {exc.strerror or exc}"

    def save_now(self, checkpoint: Checkpoint) -> None:
        """The final save (after SLAM stopped) of `checkpoint`: waits for a save in progress,
        then writes. Raises OutputError when it cannot write (the last complete save stays)."""
        self.close()
        if not self._save(checkpoint, self.stamps):
            raise OutputError(f"{self.error}; {self._kept()}")

    def wait(self) -> None:
        """Until the save in progress, if any, has ended."""
        if self._pending is not None:
            self._pending.result()

    def close(self) -> None:
        self._writer.shutdown(wait=True)

    def _save(self, checkpoint: Checkpoint, stamps: Sequence[FrameStamp]) -> bool:
        """Write trajectory, map and checkpoint of the first `checkpoint.frames_done` frames."""
        stamps = stamps[: checkpoint.frames_done]
        references = [r for _, r in stamps if r is not None]
        reference = np.stack(references) if references and len(references) == len(stamps) else None
        log.debug("saving trajectory, map and checkpoint of %d frames to %s", len(stamps), self.folder.path)
        started = time.perf_counter()
        try:
            self.folder.write_state(checkpoint, self.run, np.array([t for t, _ in stamps]), reference)
        except OSError as exc:
            self.report_failure("trajectory, map and checkpoint", exc)
            return False
        if self.error:
            log.info("saving to %s works again", self.folder.path)
            self.error = ""
        self.saved_frames = checkpoint.frames_done
        log.debug("trajectory, map and checkpoint written in %.2f s", time.perf_counter() - started)
        log.info("saved %d frames and %d Gaussians to %s", len(stamps), len(checkpoint.gaussians), self.folder.path)
        return True

    def _kept(self) -> str:
        if self.saved_frames:
            return f"the last complete save ({self.saved_frames} frames) is kept"
        return "nothing is saved yet"
