"""The TUM RGB-D layout: rgb.txt, depth.txt, groundtruth.txt and the image folders."""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from pipeline.config import DATASET_DEFAULTS
from pipeline.errors import DataError, UserError
from pipeline.io.files.images import write_color, write_depth_png
from pipeline.io.files.trajectory import matrix_to_quat_xyzw, pose_from_tum_row, read_tum_poses
from pipeline.io.sources.datasets.base import (
    INTRINSICS_FILE,
    Dataset,
    FrameRef,
    first_frame_size,
    intrinsics_matrix,
    read_intrinsics_file,
    relative_poses,
    write_intrinsics_file,
)

log = logging.getLogger("gsplatam")

DEPTH_SCALE = DATASET_DEFAULTS["tum"]["dataset.depth_scale"]  # uint16 units per metre (5000: the Kinect's 0.2 mm)
MAX_DT = 0.08  # seconds between associated colour, depth and pose
CAMERAS = {
    "fr1": intrinsics_matrix(517.3, 516.5, 318.6, 255.3),
    "fr2": intrinsics_matrix(520.9, 521.0, 325.1, 249.7),
    "fr3": intrinsics_matrix(535.4, 539.2, 320.1, 247.6),
}


def camera_from_name(name: str) -> np.ndarray | None:
    match = re.search(r"(?:freiburg|fr)([123])", name.lower())
    return CAMERAS[f"fr{match.group(1)}"] if match else None


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """`timestamp relative/path` rows -> (timestamps, paths) in timestamp order (rows out of
    order are sorted, as the benchmark's tools do, with a warning)."""
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise DataError(f"missing file: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot read {path}: {exc}") from None
    stamps, names = [], []
    for number, line in enumerate(lines, start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            stamp = float(parts[0])
        except ValueError:
            stamp = math.nan
        if not math.isfinite(stamp):
            raise DataError(f"{path}:{number}: bad timestamp '{parts[0]}'")
        stamps.append(stamp)
        if len(parts) < 2:
            raise DataError(f"{path}:{number}: expected 'timestamp filename'")
        names.append(parts[1])
    order = np.argsort(stamps, kind="stable")
    if (np.diff(stamps) < 0).any():
        log.warning("%s: timestamps out of order; sorted (as the TUM benchmark's tools do)", path)
    return np.asarray(stamps)[order], [names[i] for i in order]


def associate(
    color_t: np.ndarray, depth_t: np.ndarray, pose_t: np.ndarray | None, max_dt: float = MAX_DT
) -> list[tuple[int, int, int]]:
    """For each colour time the nearest depth and pose times; kept when both lie within max_dt.

    -> (colour index, depth index, pose index or -1 without poses) triples in colour order.
    """
    if len(depth_t) == 0:
        return []
    triples = []
    for i, t in enumerate(color_t):
        j = int(np.argmin(np.abs(depth_t - t)))
        if abs(depth_t[j] - t) >= max_dt:
            continue
        k = -1
        if pose_t is not None:
            k = int(np.argmin(np.abs(pose_t - t)))
            if abs(pose_t[k] - t) >= max_dt:
                continue
        triples.append((i, j, k))
    return triples


def open_tum(path: Path, intrinsics: np.ndarray | None = None) -> Dataset:
    color_t, color_names = read_file_list(path / "rgb.txt")
    depth_t, depth_names = read_file_list(path / "depth.txt")
    gt_path = path / "groundtruth.txt"
    pose_t = gt_rows = None
    if gt_path.exists():
        pose_t, gt_rows = read_tum_poses(gt_path)
    triples = associate(color_t, depth_t, pose_t)
    if not triples:
        raise DataError(f"no colour frame of {path} has depth (and pose) within {MAX_DT} s")
    poses = None
    if gt_rows is not None:
        poses = relative_poses(np.stack([pose_from_tum_row(gt_rows[k]) for _, _, k in triples]))
    refs = [
        FrameRef(
            n, float(color_t[i]), path / color_names[i], path / depth_names[j], None if poses is None else poses[n]
        )
        for n, (i, j, _) in enumerate(triples)
    ]
    if intrinsics is None:
        intrinsics = read_intrinsics_file(path)
    if intrinsics is None:
        intrinsics = camera_from_name(path.resolve().name)
    if intrinsics is None:
        raise UserError(
            f"cannot tell the TUM camera (fr1, fr2, fr3) from the folder name '{path.name}': "
            f"set dataset.intrinsics=fx,fy,cx,cy or add {INTRINSICS_FILE}"
        )
    return Dataset(path.name, "tum", refs, intrinsics, DEPTH_SCALE, None, first_frame_size(refs))


def write_tum(
    path: Path,
    frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
    intrinsics: np.ndarray,
    fps: float = 30.0,
    depth_noise: float = 0.0,
    hole_fraction: float = 0.0,
    time_jitter: float = 0.0,
    seed: int = 0,
) -> int:
    """Write (colour, depth metres, camera-to-world) frames in the TUM layout; -> count.

    Optional Kinect-like corruption: depth noise with std `depth_noise` x depth^2 (metres),
    a fraction of pixels zeroed in blobs, and depth/pose timestamps offset by up to
    `time_jitter` seconds from the colour ones.
    """
    rng = np.random.default_rng(seed)
    (path / "rgb").mkdir(parents=True, exist_ok=True)
    (path / "depth").mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines, gt_lines = [], [], []
    count = 0
    for i, (color, depth, c2w) in enumerate(frames):
        t = 1.0 + i / fps
        td = t + rng.uniform(-time_jitter, time_jitter)
        tp = t + rng.uniform(-time_jitter, time_jitter)
        depth = depth.astype(np.float64)
        if depth_noise > 0:
            depth = depth + rng.normal(size=depth.shape) * depth_noise * depth**2
        if hole_fraction > 0:
            depth = depth * ~_holes(depth.shape, hole_fraction, rng)
        write_color(path / "rgb" / f"{t:.6f}.png", color)
        write_depth_png(path / "depth" / f"{td:.6f}.png", np.maximum(depth, 0.0), DEPTH_SCALE)
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
        q = matrix_to_quat_xyzw(c2w[:3, :3])
        x, y, z = c2w[:3, 3]
        gt_lines.append(f"{tp:.6f} {x:.9f} {y:.9f} {z:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
        count += 1
    header = "# written by gsplatam synth\n# timestamp filename\n"
    (path / "rgb.txt").write_text(header + "\n".join(rgb_lines) + "\n")
    (path / "depth.txt").write_text(header + "\n".join(depth_lines) + "\n")
    (path / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt_lines) + "\n")
    write_intrinsics_file(path, intrinsics)
    return count


def _holes(shape: tuple[int, ...], fraction: float, rng: np.random.Generator) -> np.ndarray:
    """A boolean mask [H, W] of roughly `fraction` of the pixels, in square blobs."""
    height, width = shape
    side = max(2, min(height, width) // 16)
    mask = np.zeros(shape, dtype=bool)
    blobs = int(round(fraction * height * width / side**2))
    for y, x in zip(rng.integers(0, height, blobs), rng.integers(0, width, blobs)):
        mask[y : y + side, x : x + side] = True
    return mask
