"""The run folder: config, per-frame CSV, metrics, trajectories, map and checkpoint."""

from __future__ import annotations

import contextlib
import csv
import json
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from pipeline.config import Config, to_toml
from pipeline.errors import DataError, OutputError
from pipeline.files.atomic import atomic_write_all, atomic_write_text, bytes_writer
from pipeline.files.trajectory import tum_trajectory_text
from pipeline.outputs.checkpoint import LEGACY_NAME, checkpoint_bytes, read_checkpoint
from pipeline.outputs.intrinsics import CameraIntrinsics, read_intrinsics
from pipeline.outputs.ply import gaussian_ply_bytes, write_ply
from pipeline.render.types import Gaussians
from pipeline.slam.state import Checkpoint

FRAME_COLUMNS = [
    "index", "timestamp", "tracking_s", "densify_s", "mapping_s", "total_s",
    "gaussians", "added", "tracking_loss", "coverage", "lost", "warning", "mapped", "map_version",
    "age_at_start_s", "age_s",
]  # fmt: skip
CONFIG_NAME = "config.toml"
RESULT_FILES = (
    "frames.csv", "metrics.json", "trajectory.txt", "groundtruth.txt", "map.ply", "checkpoint.safetensors",
    "trace.json", "profile.txt", "intrinsics.json",
)  # fmt: skip
RUN_FILES = (CONFIG_NAME, *RESULT_FILES)  # every file a run writes (an --overwrite removes these, nothing else)


class RunFolder:
    """The files of one run, in an existing folder. `run_info` (JSON-able: dataset, image size,
    map kind) is stored in every checkpoint, so a resume can tell it continues the same run."""

    def __init__(self, path: Path, run_info: dict[str, Any] | None = None) -> None:
        self.path = path
        self.run_info = run_info or {}
        self.config = path / CONFIG_NAME
        self.frames_csv = path / "frames.csv"
        self.metrics = path / "metrics.json"
        self.trajectory = path / "trajectory.txt"  # estimated camera-to-world, TUM format
        self.groundtruth = path / "groundtruth.txt"  # reference camera-to-world, TUM format
        self.map = path / "map.ply"
        self.checkpoint = path / "checkpoint.safetensors"
        self.intrinsics = path / "intrinsics.json"  # the camera at SLAM's working size (IntrinsicsRecorder)
        self._frames_file: IO[str] | None = None

    @staticmethod
    def existing(path: Path) -> RunFolder:
        """A run folder written before (DataError when `path` holds no checkpoint)."""
        if not (path / "checkpoint.safetensors").is_file():
            raise DataError(f"{path} is not a run folder (no checkpoint.safetensors)")
        return RunFolder(path)

    @staticmethod
    def results_in(path: Path) -> list[Path]:
        """The result files an earlier run left in `path`."""
        return [path / name for name in RESULT_FILES if (path / name).exists()]

    def write_config(self, config: Config) -> None:
        with _writing(self.config):
            atomic_write_text(self.config, to_toml(config))

    def append_frames(self, rows: list[dict[str, Any]]) -> None:
        """One CSV line per frame, flushed at once: the one file appended to rather than replaced,
        so a kill loses no line written before it (a line cut off by a full disk is dropped by
        `keep_frames` on resume)."""
        if self._frames_file is None:
            new = not self.frames_csv.exists() or self.frames_csv.stat().st_size == 0
            self._frames_file = open(self.frames_csv, "a", newline="")
            if new:
                csv.DictWriter(self._frames_file, fieldnames=FRAME_COLUMNS).writeheader()
        writer = csv.DictWriter(self._frames_file, fieldnames=FRAME_COLUMNS)
        for row in rows:
            writer.writerow(row)
            self._frames_file.flush()

    def close(self) -> None:
        frames_file, self._frames_file = self._frames_file, None
        if frames_file is not None:
            frames_file.close()

    def keep_frames(self, frames_done: int) -> None:
        """Drop the frames.csv lines of frames after the first `frames_done` (written after the
        checkpoint a resume continues from) and any incomplete last line."""
        if not self.frames_csv.exists():
            return
        lines = self.frames_csv.read_text(errors="replace").splitlines(keepends=True)
        kept = [line for line in lines if line.endswith("\n") and _row_index(line) in range(frames_done)]
        with _writing(self.frames_csv):
            atomic_write_text(self.frames_csv, "".join([",".join(FRAME_COLUMNS) + "\r\n", *kept]))

    def write_state(self, checkpoint: Checkpoint, timestamps: np.ndarray, reference: np.ndarray | None) -> None:
        """Trajectory (and reference), map and checkpoint from a SLAM checkpoint (on the host);
        `timestamps` [N] seconds and `reference` [N, 4, 4] camera-to-world per pose. All of them
        are replaced, or (a write failing, e.g. on a full disk) none: the last complete set stays."""
        files = {
            self.trajectory: tum_trajectory_text(timestamps, checkpoint.poses.double().numpy()).encode(),
            self.map: gaussian_ply_bytes(checkpoint.gaussians),
            self.checkpoint: checkpoint_bytes(checkpoint, self.run_info),
        }
        if reference is not None:
            files[self.groundtruth] = tum_trajectory_text(timestamps, reference).encode()
        atomic_write_all({path: bytes_writer(data) for path, data in files.items()})

    def write_map(self, gaussians: Gaussians) -> None:
        write_ply(self.map, gaussians)

    def read_checkpoint(self) -> tuple[Checkpoint, dict[str, Any]]:
        """-> (the checkpoint, the run description it was saved with); DataError if there is none
        or it is not one this version reads."""
        legacy = self.path / LEGACY_NAME
        if not self.checkpoint.exists() and legacy.exists():
            raise DataError(
                f"{legacy} is a checkpoint of gsplatam 0.1, a pickle, which is never loaded (unpickling can run "
                f"code): run the sequence again to get {self.checkpoint.name}"
            )
        return read_checkpoint(self.checkpoint)

    def read_intrinsics(self) -> CameraIntrinsics:
        return read_intrinsics(self.intrinsics)

    def read_metrics(self) -> dict[str, Any] | None:
        """metrics.json as written, or None where there is none (or it cannot be read)."""
        try:
            metrics = json.loads(self.metrics.read_text())
        except (OSError, ValueError):
            return None
        return metrics if isinstance(metrics, dict) else None

    def write_metrics(self, metrics: dict[str, Any]) -> None:
        with _writing(self.metrics):
            atomic_write_text(self.metrics, json.dumps(metrics, indent=2, sort_keys=True) + "\n")


@contextlib.contextmanager
def _writing(path: Path) -> Iterator[None]:
    """An OSError writing `path` as the OutputError a user sees (one line, exit code 2)."""
    try:
        yield
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None


def _row_index(line: str) -> int | None:
    """The frame index of a complete frames.csv line, None for the header or a malformed line."""
    fields = next(csv.reader([line]), [])
    if len(fields) != len(FRAME_COLUMNS) or not fields[0].isdigit():
        return None
    return int(fields[0])
