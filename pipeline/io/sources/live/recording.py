"""Keeping a live capture: every frame a live source decodes, saved in the TUM RGB-D layout.

`RecordingSource` wraps a source and hands each decoded frame to a `TumRecorder`, which writes
it from a thread of its own: `rgb/` and `depth/` PNGs (depth 16-bit, 5000 per metre as TUM),
`rgb.txt` and `depth.txt`, `groundtruth.txt` with the device's poses when the frames carry
them (NeRFCapture's ARKit pose, as used for tracking or as reference), and `intrinsics.txt`.
The folder is a dataset: `gsplatam run FOLDER` re-runs the session offline.

What is recorded is what SLAM receives: frames dropped before decoding (the live queue keeps
the newest) are not in it. The recorder's queue is bounded; when the disk falls behind, decoding
waits for it (and the live queue drops older frames), so the recording never has gaps that SLAM
did not also have.

The listings are rewritten after the first frame, every LISTING_EVERY frames and at the end, so a
recording cut short (a kill, a full disk) lists frames that were written whole and stays a
dataset. A write that fails (a full disk) is reported once, until writes work again, and never
ends the session: SLAM's own results come first (`error` says what failed).
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import AsyncIterator, Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.frame import Frame
from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.files.folders import make_folder
from pipeline.io.files.images import write_color, write_depth_png
from pipeline.io.files.trajectory import write_tum_trajectory
from pipeline.io.sources.datasets.base import INTRINSICS_FILE, write_intrinsics_file
from pipeline.io.sources.datasets.tum import DEPTH_SCALE
from pipeline.source import Source

log = logging.getLogger("gsplatam")

QUEUE_FRAMES = 32  # frames waiting for the disk at most
COLOR_LIST = "rgb.txt"  # the listings of the TUM layout (and groundtruth.txt with poses)
DEPTH_LIST = "depth.txt"
POSES = "groundtruth.txt"
WRITTEN = ("rgb/*.png", "depth/*.png", COLOR_LIST, DEPTH_LIST, POSES, INTRINSICS_FILE)  # in its folder
LISTING_EVERY = 30  # rgb.txt, depth.txt and groundtruth.txt are rewritten after this many frames (and at the end)


class TumRecorder:
    """Writes frames into `folder` in the TUM layout from its own thread; `close()` flushes."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        for sub in ("rgb", "depth"):
            make_folder(folder / sub, "the recording's folder")
        self.frames = 0  # written whole
        self.listed = 0  # in the listings on disk (a re-run reads these)
        self.error = ""  # why the last failed write failed; empty while none has
        self._failing = False  # the last write failed (reported once, until one works again)
        self._rows: list[tuple[float, str, np.ndarray | None]] = []  # timestamp, file name, pose
        self._queue: queue.Queue[Frame | None] = queue.Queue(maxsize=QUEUE_FRAMES)
        self._thread = threading.Thread(target=self._work, name="recorder", daemon=True)
        self._thread.start()
        self._closed = False

    def put(self, frame: Frame) -> None:
        """Queue a frame (waits while QUEUE_FRAMES are queued)."""
        self._queue.put(frame)

    def _work(self) -> None:
        while (frame := self._queue.get()) is not None:
            self._attempt(f"frame {frame.index}", partial(self._write, frame))

    def _attempt(self, what: str, write: Callable[[], None]) -> None:
        """`write()`; a failure (a full disk) is logged once, until a write works again."""
        try:
            write()
        except OSError as exc:
            if not self._failing:
                log.error(
                    "recording to %s failed (%s): %s; the session goes on, the recording keeps the frames listed",
                    self.folder, what, exc.strerror or exc,
                )  # fmt: skip
            self.error = f"recording to {self.folder} failed ({what}): {exc.strerror or exc}"
            self._failing = True
            return
        if self._failing:
            log.info("recording to %s works again", self.folder)
            self._failing = False

    def _write(self, frame: Frame) -> None:
        name = f"{frame.index:06d}.png"
        write_color(self.folder / "rgb" / name, frame.color)
        write_depth_png(self.folder / "depth" / name, frame.depth, DEPTH_SCALE)
        if not self._rows:
            write_intrinsics_file(self.folder, frame.intrinsics)
        pose = frame.c2w_gt if frame.c2w_gt is not None else frame.c2w_prior
        self._rows.append((frame.timestamp, name, pose))
        self.frames += 1
        if self.frames == 1 or self.frames % LISTING_EVERY == 0:
            self._write_listings()

    def _write_listings(self) -> None:
        rows = sorted(self._rows, key=lambda row: row[0])  # decode threads may finish out of order
        header = "# recorded by gsplatam serve (live.record)\n# timestamp filename\n"
        for kind, listing in (("rgb", COLOR_LIST), ("depth", DEPTH_LIST)):
            lines = "".join(f"{t:.6f} {kind}/{name}\n" for t, name, _ in rows)
            atomic_write_text(self.folder / listing, header + lines)
        posed = [(t, pose) for t, _, pose in rows if pose is not None]
        if posed:
            times, poses = zip(*posed)
            write_tum_trajectory(self.folder / POSES, np.array(times), np.stack(poses))
        self.listed = len(rows)

    def close(self) -> None:
        """Write what is queued and the listings (a failure is logged, never raised); safe to call twice."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join()
        if self._rows:
            self._attempt("the listings", self._write_listings)
            log.info("recorded %d frames to %s", self.listed, self.folder)


class RecordingSource:
    """`source`, with every frame it decodes also recorded into `folder` (a decode-side tap)."""

    def __init__(self, source: Source, folder: Path) -> None:
        self.source = source
        self.name = source.name
        self.live = source.live
        self.counters = source.counters  # the same object: the source's counts
        self.recorder = TumRecorder(folder)

    @property
    def last_index(self) -> int | None:
        return self.source.last_index

    def __aiter__(self) -> AsyncIterator[Any]:
        return self.source.__aiter__()

    def decode(self, ref: Any) -> Frame | None:
        frame = self.source.decode(ref)
        if frame is not None:
            self.recorder.put(frame)
        return frame

    @property
    def error(self) -> str:
        """Why the recording's last failed write failed; empty while none has."""
        return self.recorder.error

    def close(self) -> None:
        self.recorder.close()
