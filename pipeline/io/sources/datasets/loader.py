"""Opening a dataset folder or a bag: detect its layout, read it, slice it, resize it."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

from pipeline.config import DatasetConfig
from pipeline.errors import UserError
from pipeline.io.sources.datasets import replica, tum
from pipeline.io.sources.datasets.base import Dataset, intrinsics_matrix, slice_refs

BAG_FILES = (".bag", ".db3", ".mcap")  # ROS 1 (and RealSense) bags, a ROS 2 bag's SQLite or MCAP file
ROS2_METADATA = "metadata.yaml"  # a ROS 2 bag's folder holds it


def detect_format(path: Path) -> str:
    if (path.suffix in BAG_FILES and path.is_file()) or (path / ROS2_METADATA).is_file():
        return "rosbag"
    if (path / "results").is_dir() and (path / "traj.txt").exists():
        return "replica"
    if (path / "rgb.txt").exists() and (path / "depth.txt").exists():
        return "tum"
    raise UserError(
        f"cannot tell the layout of {path}: expected Replica (results/, traj.txt), TUM (rgb.txt, depth.txt) "
        f"or a bag ({', '.join(BAG_FILES)}, a ROS 2 bag's folder with {ROS2_METADATA})"
    )


def open_dataset(config: DatasetConfig) -> Dataset:
    """Open the dataset that `config.path` names, in the layout `config.format` (or detected)."""
    path = Path(config.path)
    layout: str = config.format
    if layout == "auto" and path.is_file():
        layout = detect_format(path)
    elif layout != "rosbag":
        if not path.is_dir():
            raise UserError(f"dataset folder not found: {path}")
        if not os.access(path, os.R_OK | os.X_OK):
            raise UserError(f"cannot read the dataset folder {path}: permission denied")
        layout = detect_format(path) if layout == "auto" else layout
    explicit = intrinsics_matrix(*config.intrinsics) if config.intrinsics else None
    dataset: Dataset
    if layout == "rosbag":
        from pipeline.io.sources.datasets.rosbag import open_bag  # rosbags: the 'rosbag' extra

        dataset = open_bag(path, explicit, config)
    else:
        dataset = (replica.open_replica if layout == "replica" else tum.open_tum)(path, explicit)
    resize = (config.width, config.height) if config.width > 0 else None
    return replace(dataset, refs=slice_refs(dataset.refs, config), resize=resize)
