"""Opening a dataset folder: detect its layout, read it, slice it, resize it."""

from __future__ import annotations

import os
from pathlib import Path

from pipeline.config import DatasetConfig
from pipeline.errors import UserError
from pipeline.io.sources.datasets import replica, tum
from pipeline.io.sources.datasets.base import Dataset, check_listing, intrinsics_matrix, slice_refs


def detect_format(path: Path) -> str:
    if (path / "results").is_dir() and (path / "traj.txt").exists():
        return "replica"
    if (path / "rgb.txt").exists() and (path / "depth.txt").exists():
        return "tum"
    raise UserError(
        f"cannot tell the layout of {path}: expected Replica (results/, traj.txt) or TUM (rgb.txt, depth.txt)"
    )


def dataset_folder(config: DatasetConfig) -> Path:
    """The folder `config.path` names or, where it is gone (a run folder's absolute path after a
    move), `config.path_as_given` where that is a folder from here; UserError naming both if neither is."""
    path = Path(config.path)
    if path.is_dir():
        return path
    given = Path(config.path_as_given) if config.path_as_given else None
    if given is not None and given.is_dir():
        return given
    also = f" (given as {given})" if given is not None and str(given) != str(path) else ""
    raise UserError(f"dataset folder not found: {path}{also}")


def open_dataset(config: DatasetConfig) -> Dataset:
    """Open the dataset that `config.path` names, in the layout `config.format` (or detected), at
    `config.depth_scale` (or its layout's); DataError naming the first file its listing names
    that is missing or unreadable."""
    path = dataset_folder(config)
    if not os.access(path, os.R_OK | os.X_OK):
        raise UserError(f"cannot read the dataset folder {path}: permission denied")
    layout = detect_format(path) if config.format == "auto" else config.format
    explicit = intrinsics_matrix(*config.intrinsics) if config.intrinsics else None
    opener = replica.open_replica if layout == "replica" else tum.open_tum
    dataset = opener(path, explicit)
    resize = (config.width, config.height) if config.width > 0 else None
    refs = slice_refs(dataset.refs, config)
    check_listing(refs)
    depth_scale = config.depth_scale or dataset.depth_scale
    return Dataset(dataset.name, dataset.format, refs, dataset.intrinsics, depth_scale, resize, dataset.size)
