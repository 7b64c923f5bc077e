"""Opening a dataset folder or a bag: detect its layout, read it, slice it, resize it."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

from pipeline.config import DatasetConfig
from pipeline.errors import UserError
from pipeline.io.sources.datasets import replica, tum
from pipeline.io.sources.datasets.base import Dataset, check_listing, intrinsics_matrix, slice_refs

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


def dataset_folder(config: DatasetConfig) -> Path:
    """The folder `config.path` names or, where it is gone (a run folder's absolute path after a
    move), `config.path_as_given` where that is a folder from here; UserError naming both if neither is."""
    path = Path(config.path)
    if path.exists():  # a folder, or a bag's file
        return path
    given = Path(config.path_as_given) if config.path_as_given else None
    if given is not None and given.exists():
        return given
    also = f" (given as {given})" if given is not None and str(given) != str(path) else ""
    raise UserError(f"dataset folder not found: {path}{also}")


def open_dataset(config: DatasetConfig) -> Dataset:
    """Open the dataset that `config.path` names, in the layout `config.format` (or detected), at
    `config.depth_scale` (or its layout's; a bag's depth comes in its own units); DataError naming
    the first file an image folder's listing names that is missing or unreadable."""
    path = dataset_folder(config)
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
    refs = slice_refs(dataset.refs, config)
    if layout == "rosbag":
        return replace(dataset, refs=refs, resize=resize)
    check_listing(refs)
    return replace(dataset, refs=refs, resize=resize, depth_scale=config.depth_scale or dataset.depth_scale)
