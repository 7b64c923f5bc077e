"""A nerfstudio dataset of a run: `transforms.json`, images, depth and a seed point cloud.

Its images are the keyframes (`frames="keyframes"`) or every frame tracked well (`"all"`,
decoded again from the run's dataset), at SLAM's working size or the dataset's own
(`size="native"`: its images and depth as stored, with its own intrinsics, those of the
working size scaled).

nerfstudio's `nerfstudio-data` parser (splatfacto, depth-nerfacto) reads it as it is:
- camera-to-world `transform_matrix` per frame in nerfstudio's OpenGL camera axes (x right,
  y up, z backwards): the OpenCV pose with its y and z axes negated;
- one pinhole camera `fl_x fl_y cx cy w h` (pixel centres at +0.5, as here);
- colour as PNG, depth as 16-bit PNG in millimetres: nerfstudio's default
  `depth_unit_scale_factor` of 1e-3 turns them into metres (0 = no depth);
- `ply_file_path`: the Gaussian centres with colours, splatfacto's initial points;
- `train_filenames`, `val_filenames`, `test_filenames` (the parser takes all three or none):
  every EVAL_EVERY-th image held out for evaluation, at least one once there are two images
  (nerfstudio's default 90/10 split of 3 keyframes leaves evaluation empty); a single image
  is in every split.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.config import Config
from pipeline.errors import DataError
from pipeline.io.files.atomic import atomic_write_bytes, atomic_write_text
from pipeline.io.files.folders import atomic_folder
from pipeline.io.files.images import encode_color, encode_depth_png
from pipeline.io.outputs.exports.job import ExportJob, Frames, Size
from pipeline.io.outputs.exports.pointcloud import write_pointcloud
from pipeline.io.outputs.intrinsics import CameraIntrinsics
from pipeline.io.sources.datasets.base import Dataset
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.render.types import Gaussians
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.state import Checkpoint

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # right-multiplied: flips the camera's y and z axes
DEPTH_UNITS_PER_METRE = 1000.0  # millimetres; nerfstudio's depth_unit_scale_factor is the inverse, 1e-3
POINTS_FILE = "sparse_pc.ply"
EVAL_EVERY = 8  # every 8th image held out for evaluation (nerfstudio's own eval_interval)
TIMESTAMP_TOLERANCE_S = 2e-6  # frames.csv keeps 6 decimals of a second
WRITTEN = ("images/frame_*.png", "depth/frame_*.png", "transforms.json", POINTS_FILE)  # in its folder

DEFAULT_NAME = "nerfstudio"  # a folder: transforms.json, images/, depth/, sparse_pc.ply
FOR = "a nerfstudio dataset to train a full model on (splatfacto, depth-nerfacto)"
NEEDS: str | None = None


def opengl_c2w(c2w_opencv: np.ndarray) -> np.ndarray:
    """[4, 4] camera-to-world with OpenCV camera axes -> the same camera with OpenGL axes."""
    return c2w_opencv @ OPENCV_TO_OPENGL


def transforms(frames: list[tuple[str, str, np.ndarray]], camera: CameraIntrinsics) -> dict[str, Any]:
    """transforms.json for (image path, depth path, OpenCV camera-to-world [4, 4]) per frame."""
    return {
        "camera_model": "OPENCV",
        "fl_x": camera.fx,
        "fl_y": camera.fy,
        "cx": camera.cx,
        "cy": camera.cy,
        "w": camera.width,
        "h": camera.height,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "ply_file_path": POINTS_FILE,
        "frames": [
            {"file_path": image, "depth_file_path": depth, "transform_matrix": opengl_c2w(c2w).tolist()}
            for image, depth, c2w in frames
        ],
        **split([image for image, _, _ in frames]),
    }


def split(images: list[str]) -> dict[str, list[str]]:
    """train/val/test file lists: every EVAL_EVERY-th image from the middle of the first
    EVAL_EVERY held out (at least one of two or more); one image alone is in every split."""
    held = set(images[min(EVAL_EVERY // 2, len(images) // 2) :: EVAL_EVERY]) if len(images) > 1 else set()
    train = [image for image in images if image not in held] or images
    evaluated = [image for image in images if image in held] or images
    return {"train_filenames": train, "val_filenames": evaluated, "test_filenames": evaluated}


@dataclass
class View:
    """One image of the export."""

    index: int  # the frame's position in the run
    color: np.ndarray  # [H, W, 3] uint8 RGB
    depth: np.ndarray  # [H, W] float32 metres, 0 = no depth
    c2w: np.ndarray  # [4, 4] float64 camera-to-world, OpenCV camera axes


def views_of(
    checkpoint: Checkpoint,
    config: Config,
    camera: CameraIntrinsics,
    frames: Frames,
    size: Size,
    timestamps: Mapping[int, float],
) -> tuple[Iterator[View], CameraIntrinsics]:
    """The images `frames` and `size` ask for, and their camera. Keyframes at the working size
    come from the checkpoint; the rest are decoded again from the run's dataset, once it is
    known to be the one the run read (`timestamps`: frame index -> seconds, from frames.csv)."""
    if frames == "keyframes" and size == "working":
        return (_keyframe_view(k) for k in checkpoint.keyframes), camera
    chosen = [k.index for k in checkpoint.keyframes] if frames == "keyframes" else _tracked(checkpoint)
    dataset = open_dataset(config.dataset if size == "working" else replace(config.dataset, width=0, height=0))
    _check_frames(dataset, chosen, timestamps)
    refs = [dataset.refs[i] for i in chosen]
    first = dataset.decode(refs[0])
    height, width = first.depth.shape
    _check_camera(dataset, first.intrinsics, (width, height), camera, size)
    poses = checkpoint.poses.double().numpy()
    decoded = itertools.chain([first], (dataset.decode(ref) for ref in refs[1:]))  # the first, decoded once
    views = (View(f.index, f.color, f.depth.astype(np.float32), poses[f.index]) for f in decoded)
    return views, CameraIntrinsics.of_matrix(first.intrinsics, width, height)


def _check_frames(dataset: Dataset, chosen: list[int], timestamps: Mapping[int, float]) -> None:
    """DataError naming the first frame of `chosen` that the dataset no longer holds as the run
    read it: missing, or of another timestamp than frames.csv gives it (frames removed from or
    added to its lists pair other images with the run's poses)."""
    where = f"the dataset {dataset.refs[0].color_path.parent if dataset.refs else ''}"
    for index in chosen:
        if index >= len(dataset.refs):
            raise DataError(
                f"{where} now has {len(dataset.refs)} frames (as the run sliced it), the run had frame {index}"
            )
        recorded, now = timestamps.get(index), dataset.refs[index].timestamp
        if recorded is not None and abs(recorded - now) > TIMESTAMP_TOLERANCE_S:
            raise DataError(
                f"frame {index} of {where} is at {now:.6f} s, the run's frames.csv has it at {recorded:.6f} s: "
                "the dataset changed since the run, its images would be paired with other frames' poses"
            )


def _check_camera(
    dataset: Dataset, intrinsics: np.ndarray, size: tuple[int, int], camera: CameraIntrinsics, asked: Size
) -> None:
    """DataError where the dataset's first frame (`intrinsics` [3, 3] at `size` (width, height)),
    brought to the run's working size, is not the run's camera: its images were replaced by
    others of another size."""
    sx, sy = camera.width / size[0], camera.height / size[1]
    scaled = np.array([intrinsics[0, 0] * sx, intrinsics[1, 1] * sy, intrinsics[0, 2] * sx, intrinsics[1, 2] * sy])
    working = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
    if (asked == "working" and size != (camera.width, camera.height)) or not np.allclose(scaled, working, rtol=1e-4):
        raise DataError(
            f"the frames of {dataset.refs[0].color_path.parent} are now {size[0]}x{size[1]} with intrinsics "
            f"fx={intrinsics[0, 0]:g} fy={intrinsics[1, 1]:g}, which is not the run's camera "
            f"({camera.width}x{camera.height}, fx={camera.fx:g}): the dataset changed since the run"
        )


def _keyframe_view(keyframe: Keyframe) -> View:
    color, depth = keyframe.color_u8.cpu().numpy(), keyframe.depth.float().cpu().numpy()
    return View(keyframe.index, color, depth, keyframe.c2w.double().cpu().numpy())


def _tracked(checkpoint: Checkpoint) -> list[int]:
    """Every frame of the run but those tracking judged lost (their poses are not trusted)."""
    lost = set(checkpoint.tracking.lost_frames)
    return [i for i in range(checkpoint.frames_done) if i not in lost]


def write_nerfstudio(folder: Path, views: Iterable[View], camera: CameraIntrinsics, gaussians: Gaussians) -> int:
    """Write the dataset into `folder` (created): transforms.json, images/, depth/ and the
    points. -> the number of images."""
    for sub in ("images", "depth"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    frames = []
    for view in views:
        image, depth = f"images/frame_{view.index:06d}.png", f"depth/frame_{view.index:06d}.png"
        atomic_write_bytes(folder / image, encode_color(view.color, ".png"))
        atomic_write_bytes(folder / depth, encode_depth_png(view.depth, DEPTH_UNITS_PER_METRE))
        frames.append((image, depth, view.c2w))
    write_pointcloud(folder / POINTS_FILE, gaussians)
    atomic_write_text(folder / "transforms.json", json.dumps(transforms(frames, camera), indent=2) + "\n")
    return len(frames)


def export(job: ExportJob) -> str:
    """The dataset, written into a temporary folder beside `job.target` and renamed into it."""
    options, working, stamps = job.nerfstudio, job.run.read_intrinsics(), job.run.frame_timestamps()
    views, camera = views_of(job.checkpoint, job.run.read_config(), working, options.frames, options.size, stamps)
    counts: list[int] = []
    atomic_folder(
        job.target, lambda staged: counts.append(write_nerfstudio(staged, views, camera, job.checkpoint.gaussians))
    )
    what = "keyframes" if options.frames == "keyframes" else "frames"
    return f"{counts[0]} {what} at {camera.width}x{camera.height} with depth, transforms.json"
