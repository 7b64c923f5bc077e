"""The Replica layout of NICE-SLAM/iMAP: results/frame%06d.jpg, results/depth%06d.png, traj.txt."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from pipeline.config import DATASET_DEFAULTS
from pipeline.errors import DataError
from pipeline.io.files.images import write_color, write_depth_png
from pipeline.io.files.trajectory import read_numeric_table
from pipeline.io.sources.datasets.base import (
    Dataset,
    FrameRef,
    first_frame_size,
    intrinsics_matrix,
    read_intrinsics_file,
    relative_poses,
    write_intrinsics_file,
)

DEPTH_SCALE = DATASET_DEFAULTS["replica"]["dataset.depth_scale"]  # uint16 units per metre (6553.5: 10 m at 65535)
NATIVE_INTRINSICS = intrinsics_matrix(600.0, 600.0, 599.5, 339.5)  # at 1200x680
FPS = 30.0  # Replica has no timestamps; frame i is stamped i / FPS


def open_replica(path: Path, intrinsics: np.ndarray | None = None) -> Dataset:
    table = read_numeric_table(path / "traj.txt", 16)
    if len(table) == 0:
        raise DataError(f"{path / 'traj.txt'} holds no poses")
    results = path / "results"
    colors = sorted(results.glob("frame*.jpg"))
    if len(colors) > len(table):
        raise DataError(f"{path / 'traj.txt'} has {len(table)} poses but {results} holds {len(colors)} colour frames")
    poses = relative_poses(table.reshape(-1, 4, 4))
    refs = [
        FrameRef(i, i / FPS, results / f"frame{i:06d}.jpg", results / f"depth{i:06d}.png", poses[i])
        for i in range(len(table))
    ]
    if intrinsics is None:
        intrinsics = read_intrinsics_file(path)
    if intrinsics is None:
        intrinsics = NATIVE_INTRINSICS
    return Dataset(path.name, "replica", refs, intrinsics, DEPTH_SCALE, None, first_frame_size(refs))


def write_replica(
    path: Path, frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], intrinsics: np.ndarray
) -> int:
    """Write (colour [H,W,3] uint8, depth [H,W] metres, camera-to-world [4,4]) frames; -> count."""
    results = path / "results"
    results.mkdir(parents=True, exist_ok=True)
    rows = []
    for i, (color, depth, c2w) in enumerate(frames):
        write_color(results / f"frame{i:06d}.jpg", color)
        write_depth_png(results / f"depth{i:06d}.png", depth, DEPTH_SCALE)
        rows.append(" ".join(f"{v:.12e}" for v in np.asarray(c2w).reshape(-1)))
    (path / "traj.txt").write_text("\n".join(rows) + "\n")
    write_intrinsics_file(path, intrinsics)
    return len(rows)
