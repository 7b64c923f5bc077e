"""A RealSense SDK recording (`.bag`, written by realsense-viewer or `rs2::recorder`): a ROS 1
bag in the SDK's own topic layout, and depth aligned to colour as the SDK's `rs2::align` does.

The layout (librealsense src/media/ros/ros_file_format.h, file version 2 and up):
`/file_version` (std_msgs/UInt32); per stream `/device_0/sensor_<s>/<Stream>_<i>/` with
`image/data` (sensor_msgs/Image: Z16 depth as `mono16`, colour as `rgb8`, ...), `info`
(realsense_msgs/StreamInfo), `info/camera_info` (sensor_msgs/CameraInfo: K, the SDK's distortion
model by name and its coefficients) and `tf/<group>` (geometry_msgs/Transform: the extrinsics
from the group's reference stream to this one); per sensor `option/<Name>/value`
(std_msgs/Float32), among them `Depth_Units` (metres per Z16 unit).

The SDK records its sensors as they stream: depth is not aligned to colour in the file. Here it
is aligned as `rs2::align` aligns it (librealsense src/proc/align.cpp): each depth pixel's corners
are projected into the colour image and the covered colour pixels take the nearest depth.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.errors import DataError
from pipeline.io.sources.datasets.ros_messages import camera_matrix, field

FILE_VERSION = "/file_version"
COLOR_DATA = re.compile(r"^/device_\d+/sensor_\d+/Color_\d+/image/data$")
DEPTH_DATA = re.compile(r"^/device_\d+/sensor_\d+/Depth_\d+/image/data$")
# Distortion models (the SDK's names) under which x86's SSE align (what the PyPI wheel runs) uses
# the plain pinhole, whatever the coefficients: the colour and depth models of the D400 cameras.
PINHOLE_MODELS = {"depth": ("None", "Brown Conrady"), "colour": ("None", "Brown Conrady", "Inverse Brown Conrady")}


def is_realsense(topics: Iterable[str]) -> bool:
    """Whether a bag's topics are a RealSense recording's."""
    names = set(topics)
    return FILE_VERSION in names and any(DEPTH_DATA.match(name) for name in names)


def stream_topic(data_topic: str, *parts: str) -> str:
    """A topic of the stream whose frames are on `data_topic`: `stream_topic(t, "info", "camera_info")`."""
    return "/".join([data_topic.removesuffix("/image/data"), *parts])


def depth_units_topic(depth_data_topic: str) -> str:
    """The depth sensor's `Depth Units` option (metres per Z16 unit)."""
    sensor = depth_data_topic.split("/")[:3]  # "", "device_0", "sensor_0"
    return "/".join([*sensor, "option", "Depth_Units", "value"])


def extrinsics_topic(data_topic: str, topics: Iterable[str]) -> str | None:
    """The stream's `tf/<group>` topic, if the file has one."""
    prefix = stream_topic(data_topic, "tf", "")
    return next((name for name in topics if name.startswith(prefix)), None)


@dataclass(frozen=True)
class StreamIntrinsics:
    """One stream's camera as the SDK describes it (rs2_intrinsics)."""

    matrix: np.ndarray  # [3, 3] pixels
    width: int
    height: int
    model: str  # the SDK's distortion model name
    coeffs: np.ndarray  # [5] k1 k2 p1 p2 k3

    @staticmethod
    def of(info: Any) -> StreamIntrinsics:
        coeffs = np.zeros(5)
        given = np.asarray(field(info, "D"), dtype=np.float64)[:5]
        coeffs[: len(given)] = given
        return StreamIntrinsics(camera_matrix(info), int(info.width), int(info.height), info.distortion_model, coeffs)

    def pixels_per_degree(self) -> tuple[float, float]:
        """Its width and height over its field of view (rs2_fov), as the SDK's align compares them."""
        k = self.matrix.astype(np.float32)
        fov_x = np.arctan2(k[0, 2] + 0.5, k[0, 0]) + np.arctan2(self.width - (k[0, 2] + 0.5), k[0, 0])
        fov_y = np.arctan2(k[1, 2] + 0.5, k[1, 1]) + np.arctan2(self.height - (k[1, 2] + 0.5), k[1, 1])
        return self.width / float(np.degrees(fov_x)), self.height / float(np.degrees(fov_y))


@dataclass(frozen=True)
class DepthToColor:
    """What aligning a recording's depth to its colour takes."""

    depth: StreamIntrinsics
    color: StreamIntrinsics
    extrinsics: np.ndarray  # [4, 4] depth camera -> colour camera (p_color = R p_depth + t), metres

    def __post_init__(self) -> None:
        for name, stream in (("depth", self.depth), ("colour", self.color)):
            if stream.model not in PINHOLE_MODELS[name] and np.any(stream.coeffs != 0):
                raise DataError(f"the {name} stream's distortion model '{stream.model}' is not supported")

    @property
    def identity(self) -> bool:
        """Depth already is colour's: one camera (nothing to align)."""
        same = (self.depth.width, self.depth.height) == (self.color.width, self.color.height)
        return same and np.allclose(self.depth.matrix, self.color.matrix) and np.allclose(self.extrinsics, np.eye(4))

    def align(self, depth: np.ndarray) -> np.ndarray:
        """[h, w] metres in the depth camera -> [H, W] metres in the colour camera, 0 = none: as
        the SDK's SSE align does it, each depth pixel's top-left corner projected into colour
        and, where depth has fewer pixels per degree than colour, its bottom-right one too; every
        colour pixel of that rectangle keeps the nearest depth."""
        if depth.shape != (self.depth.height, self.depth.width):
            raise DataError(
                f"depth image is {depth.shape[1]}x{depth.shape[0]}, its camera_info "
                f"{self.depth.width}x{self.depth.height}"
            )
        rows, cols = np.nonzero(depth > 0)
        z = depth[rows, cols].astype(np.float32)
        x0, y0 = self._color_pixel(cols - 0.5, rows - 0.5, z)
        denser = np.less(self.depth.pixels_per_degree(), self.color.pixels_per_degree()).any()
        x1, y1 = self._color_pixel(cols + 0.5, rows + 0.5, z) if denser else (x0, y0)
        nearest = np.full((self.color.height + 2, self.color.width + 2), np.inf, dtype=np.float32)
        for dy in range(int((y1 - y0).max(initial=0)) + 1):
            for dx in range(int((x1 - x0).max(initial=0)) + 1):
                x, y = x0 + dx, y0 + dy
                covered = (x <= x1) & (y <= y1) & (x >= 0) & (y >= 0) & (x < self.color.width) & (y < self.color.height)
                np.minimum.at(nearest, (y[covered], x[covered]), z[covered])
        aligned = nearest[: self.color.height, : self.color.width]
        return np.where(np.isinf(aligned), np.float32(0), aligned)

    def _color_pixel(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth pixel corners (u, v) at depths z -> the colour pixels they fall in, in the SSE
        align's float32 arithmetic and order; rounded as (int)(coordinate + 0.5) (towards zero:
        measured against the wheel's align, which matched it pixel for pixel)."""
        f32 = np.float32
        kd, kc = self.depth.matrix.astype(f32), self.color.matrix.astype(f32)
        r, t = self.extrinsics[:3, :3].astype(f32), self.extrinsics[:3, 3].astype(f32)
        x, y = (u.astype(f32) - kd[0, 2]) / kd[0, 0], (v.astype(f32) - kd[1, 2]) / kd[1, 1]
        px, py = z * x, z * y
        moved = [r[i, 0] * px + (r[i, 1] * py + (r[i, 2] * z + t[i])) for i in range(3)]
        cx, cy = moved[0] / moved[2] * kc[0, 0] + kc[0, 2], moved[1] / moved[2] * kc[1, 1] + kc[1, 2]
        return np.trunc(cx + f32(0.5)).astype(np.int64), np.trunc(cy + f32(0.5)).astype(np.int64)
