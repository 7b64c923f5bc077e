"""The run folder: config, per-frame CSV, metrics, trajectories, map and checkpoint."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.config import Config, to_toml
from pipeline.io.ply import write_ply
from pipeline.io.trajectory import write_tum_trajectory
from pipeline.render.types import Gaussians
from pipeline.slam.gaussian_map import PARAMETER_NAMES

FRAME_COLUMNS = [
    "index", "timestamp", "tracking_s", "densify_s", "mapping_s", "total_s",
    "gaussians", "added", "tracking_loss", "coverage", "lost",
]  # fmt: skip


class RunFolder:
    def __init__(self, path: Path) -> None:
        self.path = path
        path.mkdir(parents=True, exist_ok=True)
        self.config = path / "config.toml"
        self.frames_csv = path / "frames.csv"
        self.metrics = path / "metrics.json"
        self.trajectory = path / "trajectory.txt"  # estimated camera-to-world, TUM format
        self.groundtruth = path / "groundtruth.txt"  # reference camera-to-world, TUM format
        self.map = path / "map.ply"
        self.checkpoint = path / "checkpoint.pt"

    def write_config(self, config: Config) -> None:
        _atomic_write_text(self.config, to_toml(config))

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
        tmp = self.map.with_suffix(".ply.tmp")
        write_ply(tmp, gaussians)
        os.replace(tmp, self.map)

    def write_checkpoint(self, payload: dict[str, Any]) -> None:
        tmp = self.checkpoint.with_suffix(".pt.tmp")
        torch.save(payload, tmp)
        os.replace(tmp, self.checkpoint)

    def write_state(self, slam_state: dict[str, Any], timestamps: np.ndarray, reference: np.ndarray | None) -> None:
        """Trajectory (and reference), map and checkpoint from a SplaTAM `state_dict()` (on the
        host); `timestamps` [N] seconds and `reference` [N, 4, 4] camera-to-world per pose."""
        estimated = slam_state["poses"].double().numpy()
        self.write_trajectories(timestamps, estimated, reference)
        self.write_map(Gaussians(**{n: slam_state["gaussians"][n] for n in PARAMETER_NAMES}))
        self.write_checkpoint({"slam": slam_state, "frames_done": len(estimated)})

    def write_metrics(self, metrics: dict[str, Any]) -> None:
        _atomic_write_text(self.metrics, json.dumps(metrics, indent=2, sort_keys=True) + "\n")


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
