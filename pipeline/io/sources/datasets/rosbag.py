"""ROS bags as datasets: ROS 1 `.bag` files (RealSense SDK recordings among them), ROS 2 bag
folders and their `.db3` or `.mcap` files, read with rosbags (pure Python: no ROS installed).

Opening a bag reads it once: the colour, depth and pose topics' header stamps (`rosbag_topics`
chooses the topics), colour and depth paired by those stamps as the TUM reader pairs its lists
(`tum.associate`), the camera from camera_info. A frame's images are read again when it is
decoded, from the bag by the messages' place in it (random access, each decoding thread with a
reader of its own). Poses (a pose topic, or /tf between two named frames) are the frames'
ground truth or the starting guess of tracking (`dataset.pose_use`).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import sqlite3
import threading
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.rosbag1 import ReaderError as Rosbag1Error
from rosbags.rosbag2 import ReaderError as Rosbag2Error
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from pipeline.config import DatasetConfig
from pipeline.errors import DataError, UserError
from pipeline.frame import Frame
from pipeline.io.files.images import resize_rgbd
from pipeline.io.sources.datasets import realsense_bag, ros_messages
from pipeline.io.sources.datasets.base import Dataset, FrameRef, relative_poses
from pipeline.io.sources.datasets.ros_poses import TfTree, nearest_poses
from pipeline.io.sources.datasets.rosbag_topics import TF_TOPICS, BagTopics, choose_topics
from pipeline.io.sources.datasets.tum import MAX_DT, associate

log = logging.getLogger("gsplatam")

# what rosbags raises for a truncated or corrupt file (its readers assert on some inconsistencies)
READ_ERRORS = (AnyReaderError, Rosbag1Error, Rosbag2Error, SerdeError, sqlite3.Error, OSError, EOFError, KeyError, ValueError, AssertionError)  # fmt: skip


@dataclass(frozen=True)
class MessageAt:
    """Where a message is: its topic, its time in the bag (ns) and its place among the topic's
    messages of that time."""

    topic: str
    bag_ns: int
    nth: int = 0


@dataclass(frozen=True)
class BagFrame:
    color: MessageAt
    depth: MessageAt
    c2w_prior: np.ndarray | None  # [4, 4] camera-to-world, with dataset.pose_use=initial_guess


class BagReader:
    """One bag, read by any thread: each has a rosbags reader of its own (a ROS 2 bag's SQLite
    connection belongs to the thread that opened it; a ROS 1 reader's file position is shared)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._local = threading.local()

    def reader(self) -> AnyReader:
        """This thread's open reader."""
        reader: AnyReader | None = getattr(self._local, "reader", None)
        if reader is None:
            default = get_typestore(Stores.ROS1_NOETIC if self.path.suffix == ".bag" else Stores.LATEST)
            reader = AnyReader([self.path], default_typestore=default)
            with self._failures("open"):
                reader.open()
            self._local.reader = reader
        return reader

    @functools.cached_property
    def topics(self) -> dict[str, str]:
        """Topic -> message type (rosbags' names, e.g. sensor_msgs/msg/Image)."""
        return {name: info.msgtype or "" for name, info in self.reader().topics.items()}

    def messages(self, topics: Collection[str]) -> Iterator[tuple[MessageAt, Any]]:
        """Every message of `topics`, in bag order: where it is, and the message."""
        seen: dict[tuple[str, int], int] = {}
        with self._failures("read"):
            for connection, bag_ns, rawdata in self.reader().messages(self._connections(topics)):
                nth = seen[(connection.topic, bag_ns)] = seen.get((connection.topic, bag_ns), -1) + 1
                yield MessageAt(connection.topic, bag_ns, nth), self._deserialize(connection, rawdata)[0]

    def first(self, topic: str) -> Any:
        """A topic's first message."""
        for _, message in self.messages([topic]):
            return message
        raise DataError(f"{self.path}: {topic} holds no message")

    def read(self, at: MessageAt) -> tuple[str, Any, float]:
        """The message `at` -> (its type, the message, the depth units a RealSense image carries, or 0)."""
        with self._failures("read"):
            found = self.reader().messages(self._connections([at.topic]), at.bag_ns, at.bag_ns + 1)
            for nth, (connection, _, rawdata) in enumerate(found):
                if nth == at.nth:
                    message, units = self._deserialize(connection, rawdata)
                    return connection.msgtype, message, units
        raise DataError(f"{self.path}: the {at.topic} message at {at.bag_ns} ns has gone (the bag changed?)")

    def _connections(self, topics: Collection[str]) -> list[Connection]:
        return [c for c in self.reader().connections if c.topic in topics]

    def _deserialize(self, connection: Connection, rawdata: bytes) -> tuple[Any, float]:
        """-> (the message, the depth units the RealSense SDK writes after its ROS 1 images, or 0)."""
        reader = self.reader()
        try:
            return reader.deserialize(rawdata, connection.msgtype), 0.0
        except AnyReaderError:
            if reader.is2 or connection.msgtype != ros_messages.IMAGE:
                raise
        standard, units = ros_messages.without_realsense_suffix(rawdata)
        return reader.deserialize(standard, connection.msgtype), units

    @contextlib.contextmanager
    def _failures(self, doing: str) -> Iterator[None]:
        """A rosbags error (a truncated or corrupt file) as a DataError: one line naming the bag."""
        try:
            yield
        except DataError:
            raise
        except READ_ERRORS as error:
            said = " ".join(str(error).split()) or error.__class__.__name__
            raise DataError(f"cannot {doing} the bag {self.path} (truncated or corrupt?): {said}") from None


@dataclass(frozen=True)
class BagDataset(Dataset):
    """A bag's frames: `refs` as every dataset's, decoded from the bag's messages."""

    bag: BagReader = field(compare=False)
    messages: dict[float, BagFrame] = field(compare=False)  # each ref's, by its colour stamp
    depth_units: float = ros_messages.MILLIMETRE  # metres per unit of 16-bit depth (an image may carry its own)
    alignment: realsense_bag.DepthToColor | None = None  # a RealSense recording's depth -> colour

    def decode(self, ref: FrameRef) -> Frame:
        """The frame `ref` at the working size; DataError naming the message for one that cannot
        be read, of another size than the first, or (the first) without any valid depth."""
        frame = self.messages[ref.timestamp]
        color = self._read(frame.color, _color)
        depth = self._read(frame.depth, self._depth)
        width, height = self.size
        if color.shape[:2] != (height, width) or depth.shape != (height, width):
            raise DataError(
                f"{self.bag.path}: the frame at {ref.timestamp:.6f} s is {color.shape[1]}x{color.shape[0]} colour, "
                f"{depth.shape[1]}x{depth.shape[0]} depth; the sequence's frames are {width}x{height}"
            )
        if ref.index == 0 and not (depth > 0).any():
            raise DataError(f"{self.bag.path}: the first frame's depth ({ref.timestamp:.6f} s) holds no valid depth")
        intrinsics = self.intrinsics.copy()
        if self.resize is not None:
            color, depth, intrinsics = resize_rgbd(color, depth, intrinsics, self.resize)
        return Frame(ref.index, ref.timestamp, color, depth, intrinsics, ref.c2w_gt, c2w_prior=frame.c2w_prior)

    def _depth(self, message: Any, kind: str, units: float) -> np.ndarray:
        depth = ros_messages.depth_array(message, kind, units or self.depth_units)
        return self.alignment.align(depth) if self.alignment is not None else depth

    def _read(self, at: MessageAt, convert: Callable[[Any, str, float], np.ndarray]) -> np.ndarray:
        kind, message, units = self.bag.read(at)
        try:
            return convert(message, kind, units)
        except DataError as exc:
            stamp = ros_messages.stamp_seconds(message)
            raise DataError(f"{self.bag.path}: {at.topic} at {stamp:.6f} s: {exc}") from None


def _color(message: Any, kind: str, units: float) -> np.ndarray:
    return ros_messages.color_array(message, kind)


def open_bag(path: Path, intrinsics: np.ndarray | None, config: DatasetConfig) -> BagDataset:
    """The bag at `path` as a dataset (its topics chosen per `config`; `intrinsics` [3, 3], when
    given, instead of camera_info's)."""
    if not path.exists():
        raise UserError(f"bag not found: {path}")
    bag = BagReader(path)
    topics = choose_topics(str(path), bag.topics, bag.first, config)
    alignment = _alignment(bag, topics) if topics.realsense else None
    size = _checked_size(bag, topics, alignment)
    camera = intrinsics if intrinsics is not None else _camera(bag, topics)
    units = _realsense_units(bag, topics) if topics.realsense else ros_messages.MILLIMETRE
    color_t, colors = _stamps(bag, topics.color)
    depth_t, depths = _stamps(bag, topics.depth)
    pose_t, poses = _poses(bag, topics, config, color_t)
    reference = config.pose_use == "groundtruth" and pose_t is not None
    triples = associate(color_t, depth_t, pose_t if reference else None)
    if not triples:
        with_pose = " and a pose" if reference else ""
        raise DataError(f"{path}: no colour frame of {topics.color} has depth{with_pose} within {MAX_DT} s")
    prior = config.pose_use == "initial_guess"
    priors = nearest_poses(color_t, pose_t, poses, MAX_DT) if prior and pose_t is not None else None
    gt = relative_poses(np.stack([poses[k] for _, _, k in triples])) if reference else None
    refs, frames = [], {}
    for n, (i, j, _) in enumerate(triples):
        refs.append(FrameRef(n, float(color_t[i]), path, path, None if gt is None else gt[n]))
        frames[float(color_t[i])] = BagFrame(colors[i], depths[j], None if priors is None else priors[i])
    log.info("bag %s: colour %s, depth %s, %d frames", path.name, topics.color, topics.depth, len(refs))
    name = path.name if path.is_dir() else path.stem
    return BagDataset(name, "rosbag", refs, camera, 1.0 / units, None, size, bag, frames, units, alignment)


def _stamps(bag: BagReader, topic: str) -> tuple[np.ndarray, list[MessageAt]]:
    """A topic's header stamps (seconds; the bag's time where a stamp is zero) in time order,
    and where each message is; a repeated stamp keeps its first message."""
    found: dict[float, MessageAt] = {}
    for at, message in bag.messages([topic]):
        stamp = ros_messages.stamp_seconds(message) or at.bag_ns * 1e-9
        found.setdefault(stamp, at)
    order = sorted(found)
    return np.asarray(order, dtype=np.float64), [found[t] for t in order]


def _poses(
    bag: BagReader, topics: BagTopics, config: DatasetConfig, color_t: np.ndarray
) -> tuple[np.ndarray | None, list[np.ndarray]]:
    """(pose times in seconds, camera-to-world poses [4, 4]) of the pose topic, or of /tf between
    dataset.pose_frames at each colour time; (None, []) without."""
    if topics.pose is None:
        return None, []
    if topics.pose == "/tf":
        tree = TfTree()
        for at, message in bag.messages([name for name in TF_TOPICS if name in bag.topics]):
            tree.add(message, static=at.topic == "/tf_static")
        world, camera = config.pose_frames
        found = [(t, tree.lookup(world, camera, t, MAX_DT)) for t in color_t]
        known = [(t, pose) for t, pose in found if pose is not None]
        if not known:
            raise DataError(f"{bag.path}: /tf never links {world} to {camera} near a colour frame ({tree.describe()})")
        return np.array([t for t, _ in known]), [pose for _, pose in known]
    stamped = [
        (ros_messages.stamp_seconds(message), ros_messages.pose_matrix(message))
        for _, message in bag.messages([topics.pose])
    ]
    stamped.sort(key=lambda item: item[0])
    return np.array([t for t, _ in stamped]), [pose for _, pose in stamped]


def _camera(bag: BagReader, topics: BagTopics) -> np.ndarray:
    if topics.camera_info is None:
        raise UserError(f"{bag.path}: no camera_info topic: set dataset.intrinsics=fx,fy,cx,cy")
    try:
        return ros_messages.camera_matrix(bag.first(topics.camera_info))
    except DataError as exc:
        raise DataError(f"{bag.path}: {topics.camera_info}: {exc}") from None


def _checked_size(bag: BagReader, topics: BagTopics, alignment: realsense_bag.DepthToColor | None) -> tuple[int, int]:
    """The frames' (width, height): the first colour image's, which depth (once a RealSense
    recording's is aligned) and camera_info must share. DataError for an image of an encoding
    that cannot be read."""
    sizes = []
    for topic, convert in ((topics.color, ros_messages.color_array), (topics.depth, ros_messages.depth_array)):
        try:
            sizes.append(convert(bag.first(topic), bag.topics[topic]).shape[1::-1])
        except DataError as exc:
            raise DataError(f"{bag.path}: {topic}: {exc}") from None
    (width, height), depth = sizes
    if alignment is not None:
        depth = (alignment.color.width, alignment.color.height)
    if depth != (width, height):
        raise DataError(
            f"{bag.path}: depth on {topics.depth} is {depth[0]}x{depth[1]}, colour on {topics.color} is "
            f"{width}x{height}: depth must be registered to colour (e.g. a RealSense wrapper's aligned_depth_to_color)"
        )
    if topics.camera_info is not None:
        info = bag.first(topics.camera_info)
        if (info.width, info.height) not in ((width, height), (0, 0)):
            raise DataError(
                f"{bag.path}: {topics.camera_info} is for {info.width}x{info.height} images, colour is {width}x{height}"
            )
    return int(width), int(height)


def _alignment(bag: BagReader, topics: BagTopics) -> realsense_bag.DepthToColor | None:
    """A RealSense recording's depth-to-colour alignment; None where depth is colour's already."""
    streams = []
    for data in (topics.depth, topics.color):
        info = realsense_bag.StreamIntrinsics.of(bag.first(realsense_bag.stream_topic(data, "info", "camera_info")))
        tf = realsense_bag.extrinsics_topic(data, bag.topics)
        transform = None if tf is None else bag.first(tf)
        to_stream = (
            np.eye(4) if transform is None else ros_messages.transform_matrix(transform.translation, transform.rotation)
        )
        streams.append((info, to_stream))
    (depth, reference_to_depth), (color, reference_to_color) = streams
    alignment = realsense_bag.DepthToColor(depth, color, reference_to_color @ np.linalg.inv(reference_to_depth))
    return None if alignment.identity else alignment


def _realsense_units(bag: BagReader, topics: BagTopics) -> float:
    """Metres per Z16 unit: the depth sensor's `Depth Units` option (the SDK's default, 1 mm, without)."""
    option = realsense_bag.depth_units_topic(topics.depth)
    if option not in bag.topics:
        return ros_messages.MILLIMETRE
    units = float(bag.first(option).data)
    if not units > 0:
        raise DataError(f"{bag.path}: {option} is {units:g}: depth units must be positive")
    return units
