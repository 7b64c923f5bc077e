"""Opening a dataset folder: detect its layout, read it, slice it, resize it."""

from __future__ import annotations

import os
from pathlib import Path

from pipeline.config import DatasetConfig
from pipeline.errors import UserError
from pipeline.io.sources.datasets import replica, tum
from pipeline.io.sources.datasets.base import Dataset, intrinsics_matrix, slice_refs


def detect_format(path: Path) -> str:
    if (path / "results").is_dir() and (path / "traj.txt").exists():
        return "replica"
    if (path / "rgb.txt").exists() and (path / "depth.txt").exists():
        return "tum"
    raise UserError(
        f"cannot tell the layout of {path}: expected Replica (results/, traj.txt) or TUM (rgb.txt, depth.txt)"
    )


def open_dataset(config: DatasetConfig) -> Dataset:
    """Open the dataset that `config.path` names, in the layout `config.format` (or detected)."""
    path = Path(config.path)
    if not path.is_dir():
        raise UserError(f"dataset folder not found: {path}")
    if not os.access(path, os.R_OK | os.X_OK):
        raise UserError(f"cannot read the dataset folder {path}: permission denied")
    layout = detect_format(path) if config.format == "auto" else config.format
    explicit = intrinsics_matrix(*config.intrinsics) if config.intrinsics else None
    opener = replica.open_replica if layout == "replica" else tum.open_tum
    dataset = opener(path, explicit)
    resize = (config.width, config.height) if config.width > 0 else None
    refs = slice_refs(dataset.refs, config)
    return Dataset(dataset.name, dataset.format, refs, dataset.intrinsics, dataset.depth_scale, resize, dataset.size)
