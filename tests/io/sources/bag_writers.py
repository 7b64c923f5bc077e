"""Bags written from a TUM folder with rosbags' writers, for the bag reader's tests: a ROS 1 bag,
a ROS 2 bag (SQLite or MCAP) and a RealSense SDK recording (the SDK's own topic layout, as its
recorder writes it: librealsense src/media/ros/ros_writer.cpp).

Every colour, depth and pose of the folder goes in at its own timestamp, so a bag pairs as the
folder does. Depth: TUM's 16-bit PNGs are 5000 units per metre; a bag's 16UC1 is millimetres
(rounded), its 32FC1 metres (exactly the reader's float32 division), a RealSense Z16 keeps the
units with Depth Units = 1/5000 m."""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from pipeline.io.files.trajectory import matrix_to_quat_xyzw, pose_from_tum_row, read_tum_poses
from pipeline.io.sources.datasets.base import read_intrinsics_file
from pipeline.io.sources.datasets.tum import DEPTH_SCALE, read_file_list

Kind = Literal["ros1", "sqlite3", "mcap"]
PoseKind = Literal["PoseStamped", "Odometry", "tf", "none"]
STREAM_INFO = "uint32 fps\nstring encoding\nbool is_recommended"  # realsense_msgs/StreamInfo
STATIC_NS = 1  # the SDK's time of the file's static information (ros TIME_MIN)


@dataclass
class TumFolder:
    """A TUM folder's content, read back."""

    color_t: np.ndarray
    colors: list[np.ndarray]  # [H, W, 3] uint8 RGB
    depth_t: np.ndarray
    depths: list[np.ndarray]  # [H, W] uint16, DEPTH_SCALE per metre
    pose_t: np.ndarray
    poses: list[np.ndarray]  # [4, 4] camera-to-world
    intrinsics: np.ndarray  # [3, 3]

    @staticmethod
    def read(folder: Path, intrinsics: np.ndarray | None = None) -> TumFolder:
        """The folder; `intrinsics` [3, 3] where it has no intrinsics.txt."""
        color_t, color_names = read_file_list(folder / "rgb.txt")
        depth_t, depth_names = read_file_list(folder / "depth.txt")
        pose_t, rows = read_tum_poses(folder / "groundtruth.txt")
        colors = [cv2.cvtColor(cv2.imread(str(folder / name)), cv2.COLOR_BGR2RGB) for name in color_names]
        depths = [cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED) for name in depth_names]
        poses = [pose_from_tum_row(row) for row in rows]
        intrinsics = read_intrinsics_file(folder) if intrinsics is None else intrinsics
        assert intrinsics is not None, "a synthetic TUM folder has intrinsics.txt"
        return TumFolder(color_t, colors, depth_t, depths, pose_t, poses, intrinsics)


class BagWriter:
    """One bag being written, ROS 1 or ROS 2 (SQLite or MCAP): a connection per topic."""

    def __init__(self, path: Path, kind: Kind) -> None:
        self.ros1 = kind == "ros1"
        self.store: Typestore = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.LATEST)
        self.store.register(get_types_from_msg(STREAM_INFO, "realsense_msgs/msg/StreamInfo"))
        if self.ros1:
            self.writer: Any = Rosbag1Writer(path)
        else:
            plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
            self.writer = Rosbag2Writer(path, version=9, storage_plugin=plugin)
        self.writer.open()
        self.connections: dict[str, Any] = {}

    def type(self, name: str) -> Any:
        return self.store.types[name]

    def put(self, topic: str, message: Any, t_ns: int, suffix: bytes = b"") -> None:
        msgtype = message.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        serialize = self.store.serialize_ros1 if self.ros1 else self.store.serialize_cdr
        self.writer.write(self.connections[topic], t_ns, bytes(serialize(message, msgtype)) + suffix)

    def close(self) -> None:
        self.writer.close()

    # messages
    def header(self, seconds: float, frame_id: str = "camera_color_optical_frame") -> Any:
        stamp = self.type("builtin_interfaces/msg/Time")(int(seconds), int(round((seconds % 1) * 1e9)) % 10**9)
        Header = self.type("std_msgs/msg/Header")
        return Header(0, stamp, frame_id) if self.ros1 else Header(stamp, frame_id)

    def image(
        self, seconds: float, pixels: np.ndarray, encoding: str, frame_id: str = "camera_color_optical_frame"
    ) -> Any:
        height, width = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        step = data.size // height
        return self.type("sensor_msgs/msg/Image")(
            self.header(seconds, frame_id), height, width, encoding, 0, step, data
        )

    def compressed(self, seconds: float, pixels_rgb: np.ndarray) -> Any:
        png = cv2.imencode(".png", cv2.cvtColor(pixels_rgb, cv2.COLOR_RGB2BGR))[1].reshape(-1)
        return self.type("sensor_msgs/msg/CompressedImage")(self.header(seconds), "png", png)

    def camera_info(
        self, k: np.ndarray, width: int, height: int, model: str = "plumb_bob", d: np.ndarray | None = None
    ) -> Any:
        Roi = self.type("sensor_msgs/msg/RegionOfInterest")
        coeffs = np.zeros(5) if d is None else np.asarray(d, dtype=np.float64)
        projection = np.hstack([k, np.zeros((3, 1))]).reshape(-1)
        return self.type("sensor_msgs/msg/CameraInfo")(
            self.header(0.0), height, width, model, coeffs, k.reshape(-1).astype(np.float64), np.eye(3).reshape(-1),
            projection, 0, 0, Roi(0, 0, 0, 0, False),
        )  # fmt: skip

    def pose(self, c2w: np.ndarray) -> Any:
        q = matrix_to_quat_xyzw(c2w[:3, :3])
        Point, Quaternion = self.type("geometry_msgs/msg/Point"), self.type("geometry_msgs/msg/Quaternion")
        return self.type("geometry_msgs/msg/Pose")(Point(*c2w[:3, 3]), Quaternion(*q))

    def transform(self, matrix: np.ndarray) -> Any:
        q = matrix_to_quat_xyzw(matrix[:3, :3])
        Vector3, Quaternion = self.type("geometry_msgs/msg/Vector3"), self.type("geometry_msgs/msg/Quaternion")
        return self.type("geometry_msgs/msg/Transform")(Vector3(*matrix[:3, 3]), Quaternion(*q))

    def transforms(self, seconds: float, links: list[tuple[str, str, np.ndarray]]) -> Any:
        stamped = self.type("geometry_msgs/msg/TransformStamped")
        return self.type("tf2_msgs/msg/TFMessage")(
            [stamped(self.header(seconds, parent), child, self.transform(matrix)) for parent, child, matrix in links]
        )


def _ns(seconds: float) -> int:
    return int(round(seconds * 1e9))


DepthEncoding = Literal["16UC1", "32FC1"]


def depth_pixels(raw: np.ndarray, encoding: str) -> np.ndarray:
    """TUM's 16-bit depth (DEPTH_SCALE per metre) as a bag's depth image of `encoding`."""
    if encoding == "32FC1":
        return raw.astype(np.float32) / np.float32(DEPTH_SCALE)
    return np.round(raw.astype(np.float64) * (1000.0 / DEPTH_SCALE)).astype(np.uint16)


def write_tum_bag(
    path: Path,
    folder: TumFolder,
    kind: Kind,
    depth: str = "16UC1",
    color: Literal["rgb8", "bgr8", "png"] = "rgb8",
    pose: PoseKind = "PoseStamped",
    edit: Callable[[BagWriter], None] | None = None,
) -> Path:
    """The folder as a ROS bag: /camera/color/image_raw, /camera/color/camera_info,
    /camera/aligned_depth_to_color/image_raw and the poses (a PoseStamped or Odometry topic, or
    /tf world -> camera_link -> camera_color_optical_frame with the last link on /tf_static);
    `edit` adds to it before it is closed."""
    bag = BagWriter(path, kind)
    height, width = folder.colors[0].shape[:2]
    bag.put("/camera/color/camera_info", bag.camera_info(folder.intrinsics, width, height), _ns(folder.color_t[0]))
    for t, pixels in zip(folder.color_t, folder.colors):
        if color == "png":
            message = bag.compressed(t, pixels)
            bag.put("/camera/color/image_raw/compressed", message, _ns(t))
        else:
            message = bag.image(t, pixels[..., ::-1] if color == "bgr8" else pixels, color)
            bag.put("/camera/color/image_raw", message, _ns(t))
    for t, raw in zip(folder.depth_t, folder.depths):
        bag.put("/camera/aligned_depth_to_color/image_raw", bag.image(t, depth_pixels(raw, depth), depth), _ns(t))
    body_to_optical = np.array([[0.0, 0, 1, 0.02], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]])  # REP 103 -> optical
    if pose == "tf":
        link = [("camera_link", "camera_color_optical_frame", body_to_optical)]
        bag.put("/tf_static", bag.transforms(folder.pose_t[0], link), _ns(folder.pose_t[0]))
    for t, c2w in zip(folder.pose_t, folder.poses):
        if pose == "PoseStamped":
            bag.put(
                "/camera/pose", bag.type("geometry_msgs/msg/PoseStamped")(bag.header(t, "world"), bag.pose(c2w)), _ns(t)
            )
        elif pose == "Odometry":
            covariant = bag.type("geometry_msgs/msg/PoseWithCovariance")(bag.pose(c2w), np.zeros(36))
            twist = bag.type("geometry_msgs/msg/TwistWithCovariance")(
                bag.type("geometry_msgs/msg/Twist")(bag.type("geometry_msgs/msg/Vector3")(0, 0, 0), bag.type("geometry_msgs/msg/Vector3")(0, 0, 0)),
                np.zeros(36),
            )  # fmt: skip
            odometry = bag.type("nav_msgs/msg/Odometry")(bag.header(t, "odom"), "camera", covariant, twist)
            bag.put("/odom", odometry, _ns(t))
        elif pose == "tf":
            link = [("world", "camera_link", c2w @ np.linalg.inv(body_to_optical))]
            bag.put("/tf", bag.transforms(t, link), _ns(t))
    if edit is not None:
        edit(bag)
    bag.close()
    return path


@dataclass(frozen=True)
class DepthCamera:
    """A RealSense depth stream that is not the colour camera (for alignment)."""

    intrinsics: np.ndarray  # [3, 3]
    width: int
    height: int
    depth_to_color: np.ndarray  # [4, 4]


def write_realsense_bag(
    path: Path, folder: TumFolder, depth_camera: DepthCamera | None = None, depths: list[np.ndarray] | None = None
) -> Path:
    """The folder as a RealSense SDK recording (file version 4: device and sensor info, stream
    info, camera_info, the Depth Units option, extrinsics on tf/0 from the depth stream, Z16
    depth and RGB8 colour with the SDK's trailing depth units). `depth_camera` and `depths`
    (Z16 at its size): a depth stream of its own instead of the colour camera's."""
    bag = BagWriter(path, "ros1")
    height, width = folder.colors[0].shape[:2]
    units = 1.0 / DEPTH_SCALE
    keyvalue, float32, text = (
        bag.type("diagnostic_msgs/msg/KeyValue"),
        bag.type("std_msgs/msg/Float32"),
        bag.type("std_msgs/msg/String"),
    )
    stream_info = bag.type("realsense_msgs/msg/StreamInfo")
    bag.put("/file_version", bag.type("std_msgs/msg/UInt32")(4), STATIC_NS)
    for key, value in (("Name", "Intel RealSense D435"), ("Serial Number", "123456789012"), ("Product Id", "0B07")):
        bag.put("/device_0/info", keyvalue(key, value), STATIC_NS)
    bag.put("/device_0/sensor_0/info", keyvalue("Name", "Stereo Module"), STATIC_NS)
    bag.put("/device_0/sensor_1/info", keyvalue("Name", "RGB Camera"), STATIC_NS)
    depth_k, depth_w, depth_h = (folder.intrinsics, width, height) if depth_camera is None else (
        depth_camera.intrinsics, depth_camera.width, depth_camera.height
    )  # fmt: skip
    streams = (
        ("/device_0/sensor_0/Depth_0", "mono16", depth_k, depth_w, depth_h, np.eye(4)),
        ("/device_0/sensor_1/Color_0", "rgb8", folder.intrinsics, width, height,
         np.eye(4) if depth_camera is None else depth_camera.depth_to_color),
    )  # fmt: skip
    for prefix, encoding, k, w, h, extrinsics in streams:
        bag.put(f"{prefix}/info", stream_info(30, encoding, True), STATIC_NS)
        bag.put(f"{prefix}/info/camera_info", bag.camera_info(k, w, h, "Brown Conrady"), STATIC_NS)
        bag.put(f"{prefix}/tf/0", bag.transform(extrinsics), STATIC_NS)
    bag.put("/device_0/sensor_0/option/Depth_Units/value", float32(units), STATIC_NS)
    bag.put(
        "/device_0/sensor_0/option/Depth_Units/description",
        text("Number of meters represented by a single depth unit"),
        STATIC_NS,
    )
    suffix = struct.pack("<f", units)
    z16 = folder.depths if depths is None else depths
    frames = sorted(
        [(t, "depth", i) for i, t in enumerate(folder.depth_t)]
        + [(t, "color", i) for i, t in enumerate(folder.color_t)]
    )
    for t, stream, i in frames:
        if stream == "depth":
            image = bag.image(t, z16[i], "mono16", frame_id="1")
            bag.put("/device_0/sensor_0/Depth_0/image/data", image, _ns(t), suffix)
        else:
            image = bag.image(t, folder.colors[i], "rgb8", frame_id="1")
            bag.put("/device_0/sensor_1/Color_0/image/data", image, _ns(t), struct.pack("<f", 0.0))
    bag.close()
    return path
