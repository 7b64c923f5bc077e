"""A nerfstudio dataset of the keyframes: `transforms.json`, images, depth and a seed point cloud.

nerfstudio's `nerfstudio-data` parser (splatfacto, depth-nerfacto) reads it as it is:
- camera-to-world `transform_matrix` per frame in nerfstudio's OpenGL camera axes (x right,
  y up, z backwards): the OpenCV pose with its y and z axes negated;
- one pinhole camera `fl_x fl_y cx cy w h` (pixel centres at +0.5, as here);
- colour as PNG, depth as 16-bit PNG in millimetres: nerfstudio's default
  `depth_unit_scale_factor` of 1e-3 turns them into metres (0 = no depth);
- `ply_file_path`: the Gaussian centres with colours, splatfacto's initial points.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.files.atomic import atomic_write_bytes, atomic_write_text
from pipeline.files.images import encode_color, encode_depth_png
from pipeline.outputs.exports.pointcloud import write_pointcloud
from pipeline.outputs.intrinsics import CameraIntrinsics
from pipeline.render.types import Gaussians
from pipeline.slam.keyframes import Keyframe

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # right-multiplied: flips the camera's y and z axes
DEPTH_UNITS_PER_METRE = 1000.0  # millimetres; nerfstudio's depth_unit_scale_factor is the inverse, 1e-3
POINTS_FILE = "sparse_pc.ply"
WRITTEN = ("images/frame_*.png", "depth/frame_*.png", "transforms.json", POINTS_FILE)  # in its folder


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
    }


def write_nerfstudio(folder: Path, keyframes: list[Keyframe], camera: CameraIntrinsics, gaussians: Gaussians) -> None:
    """Write the dataset into `folder` (created): transforms.json, images/, depth/ and the points."""
    for sub in ("images", "depth"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    frames = []
    for keyframe in keyframes:
        image, depth = f"images/frame_{keyframe.index:06d}.png", f"depth/frame_{keyframe.index:06d}.png"
        atomic_write_bytes(folder / image, encode_color(keyframe.color_u8.cpu().numpy(), ".png"))
        metres = keyframe.depth.float().cpu().numpy()
        atomic_write_bytes(folder / depth, encode_depth_png(metres, DEPTH_UNITS_PER_METRE))
        frames.append((image, depth, keyframe.c2w.double().cpu().numpy()))
    write_pointcloud(folder / POINTS_FILE, gaussians)
    atomic_write_text(folder / "transforms.json", json.dumps(transforms(frames, camera), indent=2) + "\n")
