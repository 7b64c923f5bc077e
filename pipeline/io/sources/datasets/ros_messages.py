"""ROS messages as arrays: images (raw and compressed), camera info and poses, as the bag
reader (`rosbag.py`) deserialises them with rosbags (ROS 1 and ROS 2 types alike: ROS 1 names
some fields in capitals, `K`, ROS 2 in lower case, `k`).

Depth follows REP 118: 16UC1 in millimetres, 32FC1 in metres; a RealSense recording's `mono16`
(the SDK's Z16) is in the file's own depth units."""

from __future__ import annotations

import struct
from typing import Any

import cv2
import numpy as np

from pipeline.errors import DataError
from pipeline.io.files.trajectory import pose_from_tum_row

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
)
TF = "tf2_msgs/msg/TFMessage"

COLOR_ENCODINGS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8UC1": 1, "8UC3": 3}
DEPTH_ENCODINGS: dict[str, np.dtype[Any]] = {
    "16UC1": np.dtype(np.uint16),
    "mono16": np.dtype(np.uint16),
    "32FC1": np.dtype(np.float32),
}
MILLIMETRE = 0.001  # metres per unit of 16-bit depth (REP 118)
COMPRESSED_DEPTH_HEADER = 12  # compressed_depth_image_transport's header before the PNG: format, two floats


def field(message: Any, name: str) -> Any:
    """A field that ROS 1 spells in capitals and ROS 2 in lower case (CameraInfo's K, D)."""
    return getattr(message, name) if hasattr(message, name) else getattr(message, name.lower())


def stamp_seconds(message: Any) -> float:
    """A stamped message's header time, seconds (ROS 1 `secs`/`nsecs` are `sec`/`nanosec` in rosbags)."""
    stamp = message.header.stamp
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def is_depth_encoding(message: Any, mimetype: str) -> bool:
    """Whether an image message holds depth (by its encoding or compressed format)."""
    if mimetype == COMPRESSED:
        return "compresseddepth" in message.format.lower()
    return bool(message.encoding in DEPTH_ENCODINGS)


def _pixels(message: Any, dtype: np.dtype[Any], channels: int) -> np.ndarray:
    """A raw image's pixels [H, W, C] of `dtype`, row padding (`step`) dropped, in host byte order."""
    height, width, step = int(message.height), int(message.width), int(message.step)
    row = width * channels * dtype.itemsize
    data = np.asarray(message.data, dtype=np.uint8)
    if width == 0 or height == 0 or step < row or len(data) < step * height:
        raise DataError(f"{width}x{height} {message.encoding} image of {len(data)} bytes (row step {step})")
    rows = data[: step * height].reshape(height, step)[:, :row]
    stored = dtype.newbyteorder(">" if message.is_bigendian else "<")
    return np.ascontiguousarray(rows).view(stored).astype(dtype).reshape(height, width, channels)


def color_array(message: Any, mimetype: str) -> np.ndarray:
    """An Image or CompressedImage -> [H, W, 3] uint8 RGB (grey repeated)."""
    if mimetype == COMPRESSED:
        image = cv2.imdecode(np.asarray(message.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise DataError(f"undecodable compressed colour image (format '{message.format}')")
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    channels = COLOR_ENCODINGS.get(message.encoding)
    if channels is None:
        raise DataError(f"unknown colour encoding '{message.encoding}' (read: {', '.join(COLOR_ENCODINGS)})")
    pixels = _pixels(message, np.dtype(np.uint8), channels)
    if channels == 1:
        return np.repeat(pixels, 3, axis=2)
    rgb = pixels[..., :3]
    return np.ascontiguousarray(rgb[..., ::-1] if message.encoding.startswith("bgr") else rgb)


def depth_array(message: Any, mimetype: str, units: float = MILLIMETRE) -> np.ndarray:
    """An Image (16UC1, mono16: `units` metres each; 32FC1 metres) or a CompressedImage of
    compressed_depth_image_transport's 16UC1 PNG -> [H, W] float32 metres, 0 = invalid (NaN,
    infinite and negative values too)."""
    if mimetype == COMPRESSED:
        if not message.format.lower().startswith("16uc1; compresseddepth"):
            raise DataError(f"unknown compressed depth format '{message.format}' (read: 16UC1; compressedDepth png)")
        png = np.asarray(message.data, dtype=np.uint8)[COMPRESSED_DEPTH_HEADER:]
        raw = cv2.imdecode(png, cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise DataError("undecodable compressed depth image (expected a 16-bit PNG)")
        return (raw.astype(np.float32) * np.float32(units)).astype(np.float32)
    dtype = DEPTH_ENCODINGS.get(message.encoding)
    if dtype is None:
        raise DataError(
            f"unknown depth encoding '{message.encoding}' (depth is read as 16UC1 millimetres or 32FC1 metres)"
        )
    raw = _pixels(message, dtype, 1)[..., 0]
    if dtype == np.uint16:
        return (raw.astype(np.float32) * np.float32(units)).astype(np.float32)
    return np.where(np.isfinite(raw) & (raw > 0), raw, 0.0).astype(np.float32)


def camera_matrix(info: Any) -> np.ndarray:
    """CameraInfo's K -> [3, 3] float64 pixels; DataError for a camera that is not calibrated."""
    k = np.asarray(field(info, "K"), dtype=np.float64).reshape(3, 3)
    if not (np.isfinite(k).all() and k[0, 0] > 0 and k[1, 1] > 0):
        raise DataError("its K holds no calibration (fx, fy must be positive)")
    return np.array([[k[0, 0], 0.0, k[0, 2]], [0.0, k[1, 1], k[1, 2]], [0.0, 0.0, 1.0]])


def transform_matrix(translation: Any, rotation: Any) -> np.ndarray:
    """A translation (x, y, z) and a quaternion (x, y, z, w) -> [4, 4] float64."""
    row = np.array(
        [translation.x, translation.y, translation.z, rotation.x, rotation.y, rotation.z, rotation.w], dtype=np.float64
    )
    if not (np.isfinite(row).all() and np.linalg.norm(row[3:]) > 0):
        raise DataError(f"pose {row.tolist()} (x y z qx qy qz qw) is not finite with a non-zero quaternion")
    return pose_from_tum_row(row)


def pose_matrix(message: Any) -> np.ndarray:
    """PoseStamped, PoseWithCovarianceStamped or Odometry -> [4, 4] float64 (its frame's pose)."""
    pose = message.pose.pose if hasattr(message.pose, "pose") else message.pose
    return transform_matrix(pose.position, pose.orientation)


def without_realsense_suffix(rawdata: bytes) -> tuple[bytes, float]:
    """The RealSense SDK writes its ROS 1 Image messages with the frame's depth units (float32)
    after the standard fields (header.frame_id "1" says so): -> (the standard message, those
    units). Only for a message that standard deserialisation found too long."""
    if len(rawdata) < 4:
        raise DataError("an image message shorter than its depth units")
    (units,) = struct.unpack("<f", rawdata[-4:])
    return rawdata[:-4], float(units)
