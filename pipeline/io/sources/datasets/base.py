"""A dataset on disk: a list of frame references, and the decoding of one reference.

Reading is split from decoding so the pipeline can list frames on the event loop and decode
them in worker threads.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.config import DatasetConfig
from pipeline.errors import DataError, UserError
from pipeline.frame import Frame
from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.files.images import read_color, read_depth, resize_rgbd
from pipeline.io.files.trajectory import read_numeric_table


@dataclass(frozen=True)
class FrameRef:
    """Where one frame lives on disk."""

    index: int  # position in the (sliced) sequence
    timestamp: float  # seconds
    color_path: Path
    depth_path: Path
    c2w_gt: np.ndarray | None  # [4, 4] camera-to-world relative to the first frame


@dataclass(frozen=True)
class Dataset:
    name: str
    format: str  # "replica" | "tum"
    refs: list[FrameRef]
    intrinsics: np.ndarray  # [3, 3] at the stored image size
    depth_scale: float  # stored uint16 units per metre
    resize: tuple[int, int] | None  # (width, height) or None for native
    size: tuple[int, int]  # (width, height) of the stored frames: the first frame's

    def __len__(self) -> int:
        return len(self.refs)

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) of the decoded frames."""
        return self.resize or self.size

    def decode(self, ref: FrameRef) -> Frame:
        """The frame `ref` at the working size. Raises DataError naming the file for a frame
        that cannot be read, of another size than the first, or (the first frame, which the
        map starts from) without any valid depth."""
        color = read_color(ref.color_path)
        width, height = self.size
        if color.shape[:2] != (height, width):
            raise DataError(
                f"colour image {ref.color_path} is {color.shape[1]}x{color.shape[0]}, "
                f"the sequence's frames are {width}x{height}"
            )
        depth = read_depth(ref.depth_path, self.depth_scale, color.shape[:2])
        if ref.index == 0 and not (depth > 0).any():
            raise DataError(f"depth image {ref.depth_path} holds no valid depth: the map cannot start from it")
        intrinsics = self.intrinsics.copy()
        if self.resize is not None:
            color, depth, intrinsics = resize_rgbd(color, depth, intrinsics, self.resize)
        return Frame(ref.index, ref.timestamp, color, depth, intrinsics, ref.c2w_gt)

    def frames(self) -> Iterator[Frame]:
        """Decode every frame in order (the synchronous path)."""
        for ref in self.refs:
            yield self.decode(ref)


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


INTRINSICS_FILE = "intrinsics.txt"  # optional "fx fy cx cy" beside a sequence, written by `synth`


def read_intrinsics_file(folder: Path) -> np.ndarray | None:
    path = folder / INTRINSICS_FILE
    if not path.exists():
        return None
    table = read_numeric_table(path, 4)
    if len(table) != 1:
        raise DataError(f"{path}: expected one line 'fx fy cx cy'")
    if not (table[0] > 0).all():
        raise DataError(f"{path}: fx fy cx cy must be positive, got {' '.join(f'{v:g}' for v in table[0])}")
    return intrinsics_matrix(*table[0])


def write_intrinsics_file(folder: Path, intrinsics: np.ndarray) -> None:
    fx, fy, cx, cy = (float(v) for v in (intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]))
    atomic_write_text(folder / INTRINSICS_FILE, f"{fx!r} {fy!r} {cx!r} {cy!r}\n")


def relative_poses(c2w: np.ndarray) -> np.ndarray:
    """[N, 4, 4] camera-to-world -> the same relative to the first: inv(T_0) @ T_i."""
    return np.linalg.inv(c2w[0])[None] @ c2w


def slice_refs(refs: list[FrameRef], config: DatasetConfig) -> list[FrameRef]:
    """Apply start/end/stride, re-base poses on the first kept frame and renumber."""
    end = len(refs) if config.end < 0 else min(config.end, len(refs))
    kept = refs[config.start : end : config.stride]
    if not kept:
        raise UserError(f"no frames left after start={config.start} end={config.end} stride={config.stride}")
    poses: list[np.ndarray | None] = [r.c2w_gt for r in kept]
    known = [p for p in poses if p is not None]
    if len(known) == len(poses):
        poses = list(relative_poses(np.stack(known)))
    return [FrameRef(i, r.timestamp, r.color_path, r.depth_path, pose) for i, (r, pose) in enumerate(zip(kept, poses))]


def check_listing(refs: list[FrameRef]) -> None:
    """Before any frame is decoded: DataError naming the first colour or depth image the
    listing names (rgb.txt, depth.txt, results/) that is missing or cannot be read."""
    for ref in refs:
        for kind, path in (("colour", ref.color_path), ("depth", ref.depth_path)):
            try:
                found = path.is_file()
            except OSError as exc:  # a folder on the way that cannot be searched
                raise DataError(f"cannot read the folder {path.parent} (for {path.name}): {exc.strerror}") from None
            if not found:
                raise DataError(f"the {kind} image of frame {ref.index} is missing: {path}")
            if not os.access(path, os.R_OK):
                raise DataError(f"cannot read the {kind} image of frame {ref.index}: {path}: permission denied")


def first_frame_size(refs: list[FrameRef]) -> tuple[int, int]:
    """(width, height) of the first frame's colour image (DataError naming it if unreadable)."""
    color = read_color(refs[0].color_path)
    return int(color.shape[1]), int(color.shape[0])
