"""The run folder: config, per-frame CSV, metrics, trajectories, map and checkpoint."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.config import Config, to_toml
from pipeline.errors import DataError
from pipeline.io.outputs.atomic import atomic_write_text
from pipeline.io.outputs.checkpoint import LEGACY_NAME, read_checkpoint, write_checkpoint
from pipeline.io.outputs.intrinsics import CameraIntrinsics, read_intrinsics
from pipeline.io.outputs.ply import write_ply
from pipeline.io.trajectory import write_tum_trajectory
from pipeline.render.types import Gaussians
from pipeline.slam.state import Checkpoint

FRAME_COLUMNS = [
    "index", "timestamp", "tracking_s", "densify_s", "mapping_s", "total_s",
    "gaussians", "added", "tracking_loss", "coverage", "lost", "warning", "mapped", "map_version",
    "age_at_start_s", "age_s",
]  # fmt: skip


class RunFolder:
    """The files of one run. `run_info` (JSON-able: dataset, image size, map kind) is stored in
    every checkpoint, so a resume can tell it continues the same run."""

    def __init__(self, path: Path, run_info: dict[str, Any] | None = None) -> None:
        self.path = path
        self.run_info = run_info or {}
        path.mkdir(parents=True, exist_ok=True)
        self.config = path / "config.toml"
        self.frames_csv = path / "frames.csv"
        self.metrics = path / "metrics.json"
        self.trajectory = path / "trajectory.txt"  # estimated camera-to-world, TUM format
        self.groundtruth = path / "groundtruth.txt"  # reference camera-to-world, TUM format
        self.map = path / "map.ply"
        self.checkpoint = path / "checkpoint.safetensors"
        self.intrinsics = path / "intrinsics.json"  # the camera at SLAM's working size (IntrinsicsRecorder)

    @staticmethod
    def existing(path: Path) -> RunFolder:
        """A run folder written before (DataError when `path` holds no checkpoint)."""
        if not (path / "checkpoint.safetensors").is_file():
            raise DataError(f"{path} is not a run folder (no checkpoint.safetensors)")
        return RunFolder(path)

    def write_config(self, config: Config) -> None:
        atomic_write_text(self.config, to_toml(config))

    def append_frames(self, rows: list[dict[str, Any]]) -> None:
        new = not self.frames_csv.exists()
        with open(self.frames_csv, "a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=FRAME_COLUMNS)
            if new:
                writer.writeheader()
            writer.writerows(rows)

    def write_trajectories(self, timestamps: np.ndarray, estimated: np.ndarray, reference: np.ndarray | None) -> None:
        write_tum_trajectory(self.trajectory, timestamps, estimated)
        if reference is not None:
            write_tum_trajectory(self.groundtruth, timestamps, reference)

    def write_map(self, gaussians: Gaussians) -> None:
        write_ply(self.map, gaussians)

    def write_state(self, checkpoint: Checkpoint, timestamps: np.ndarray, reference: np.ndarray | None) -> None:
        """Trajectory (and reference), map and checkpoint from a SLAM checkpoint (on the host);
        `timestamps` [N] seconds and `reference` [N, 4, 4] camera-to-world per pose."""
        self.write_trajectories(timestamps, checkpoint.poses.double().numpy(), reference)
        self.write_map(checkpoint.gaussians)
        write_checkpoint(self.checkpoint, checkpoint, self.run_info)

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

    def write_metrics(self, metrics: dict[str, Any]) -> None:
        atomic_write_text(self.metrics, json.dumps(metrics, indent=2, sort_keys=True) + "\n")
