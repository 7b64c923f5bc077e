"""Which topics of a bag hold the colour, the depth, the camera and the poses: the ones the
settings name (`dataset.color_topic`, ...), else the only candidate of each kind. A kind with
no candidate, or several, is one line that lists what the bag has and names the setting."""

from __future__ import annotations

import posixpath
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from pipeline.config import DatasetConfig
from pipeline.errors import DataError, UserError
from pipeline.io.sources.datasets import realsense_bag
from pipeline.io.sources.datasets.ros_messages import (
    CAMERA_INFO,
    COLOR_ENCODINGS,
    COMPRESSED,
    IMAGE,
    POSE_TYPES,
    TF,
    is_depth_encoding,
)

TF_TOPICS = ("/tf", "/tf_static")
LISTED = 12  # topics named in a message at most


@dataclass(frozen=True)
class BagTopics:
    color: str
    depth: str
    camera_info: str | None  # None: intrinsics from dataset.intrinsics
    pose: str | None  # a pose topic, "/tf" (with dataset.pose_frames), or None
    realsense: bool  # the RealSense SDK's layout


def listing(topics: Mapping[str, str]) -> str:
    """`/a (sensor_msgs/Image), /b (...)`, the first LISTED."""
    named = [f"{name} ({msgtype.replace('/msg/', '/')})" for name, msgtype in sorted(topics.items())]
    more = f" and {len(named) - LISTED} more" if len(named) > LISTED else ""
    return ", ".join(named[:LISTED]) + more if named else "none"


def choose_topics(
    where: str, topics: Mapping[str, str], first: Callable[[str], Any], config: DatasetConfig
) -> BagTopics:
    """The topics of the bag at `where` (its topics: name -> message type; `first(topic)`: the
    topic's first message, deserialised) that `config` names or that are unambiguous."""
    if realsense_bag.is_realsense(topics):
        return _realsense(where, topics, config)
    images = {name: kind for name, kind in topics.items() if kind in (IMAGE, COMPRESSED)}
    depths = {name for name in images if _holds_depth(name, images[name], first(name))}
    color = _one(where, topics, "colour image", "color_topic", config.color_topic, set(images) - depths, images)
    depth = _one(where, topics, "depth image", "depth_topic", config.depth_topic, depths, images)
    return BagTopics(color, depth, _camera_info(where, topics, color, config), _pose(where, topics, config), False)


def _holds_depth(name: str, kind: str, message: Any) -> bool:
    """Depth by its encoding; an image of an encoding that is no colour's, by its name."""
    if is_depth_encoding(message, kind):
        return True
    colour = kind == COMPRESSED or message.encoding in COLOR_ENCODINGS
    return not colour and "depth" in name.lower()


def _one(
    where: str, topics: Mapping[str, str], what: str, key: str, named: str, candidates: set[str], of: Mapping[str, str]
) -> str:
    """The topic named (checked against `of`, the topics of the right types), else the only candidate."""
    if named:
        if named not in topics:
            raise UserError(f"{where} has no topic {named} (dataset.{key}); its topics: {listing(topics)}")
        if named not in of:
            raise UserError(f"{where}: {named} is a {topics[named]}, not a {what} (dataset.{key})")
        return named
    if len(candidates) == 1:
        return next(iter(candidates))
    if not candidates:
        raise DataError(f"{where} has no {what} topic; its topics: {listing(topics)}")
    raise UserError(
        f"{where} has {len(candidates)} {what} topics ({', '.join(sorted(candidates))}): "
        f"name one with --set dataset.{key}=TOPIC"
    )


def _camera_info(where: str, topics: Mapping[str, str], color: str, config: DatasetConfig) -> str | None:
    """The camera_info named, else the colour topic's (a sibling), else the only one; None with
    dataset.intrinsics set."""
    infos = {name for name, kind in topics.items() if kind == CAMERA_INFO}
    if not config.camera_info_topic and config.intrinsics:
        return None
    sibling = posixpath.join(posixpath.dirname(color), "camera_info")
    candidates = {sibling} if sibling in infos else infos
    try:
        return _one(
            where,
            topics,
            "camera info",
            "camera_info_topic",
            config.camera_info_topic,
            candidates,
            dict.fromkeys(infos, CAMERA_INFO),
        )
    except DataError:
        raise DataError(
            f"{where} has no sensor_msgs/CameraInfo topic: set dataset.intrinsics=fx,fy,cx,cy; its topics: {listing(topics)}"
        ) from None


def _pose(where: str, topics: Mapping[str, str], config: DatasetConfig) -> str | None:
    """The pose topic: /tf with dataset.pose_frames, the one named, else the only one (None without)."""
    if config.pose_use == "ignore":
        return None
    if config.pose_frames:
        if len(config.pose_frames) != 2:
            raise UserError("dataset.pose_frames takes two frames: the world's and the camera's, e.g. map,camera")
        if not any(topics.get(name) == TF for name in TF_TOPICS):
            raise UserError(f"{where} has no /tf topic for dataset.pose_frames; its topics: {listing(topics)}")
        return "/tf"
    poses = {name: kind for name, kind in topics.items() if kind in POSE_TYPES}
    if config.pose_topic in TF_TOPICS:
        raise UserError("a pose from /tf is between two frames: set dataset.pose_frames=WORLD,CAMERA instead")
    if not config.pose_topic and not poses:
        return None
    return _one(where, topics, "pose", "pose_topic", config.pose_topic, set(poses), poses)


def _realsense(where: str, topics: Mapping[str, str], config: DatasetConfig) -> BagTopics:
    """A RealSense recording: its colour and depth streams (the first of each, or those named)."""
    colors = {name for name in topics if realsense_bag.COLOR_DATA.match(name)}
    depths = {name for name in topics if realsense_bag.DEPTH_DATA.match(name)}
    images = dict.fromkeys(colors | depths, IMAGE)
    color = _one(where, topics, "colour stream", "color_topic", config.color_topic, set(sorted(colors)[:1]), images)
    depth = _one(where, topics, "depth stream", "depth_topic", config.depth_topic, set(sorted(depths)[:1]), images)
    for stream in (color, depth):
        info = realsense_bag.stream_topic(stream, "info", "camera_info")
        if info not in topics:
            raise DataError(f"{where}: a RealSense recording without {info}")
    camera_info = realsense_bag.stream_topic(color, "info", "camera_info")
    return BagTopics(color, depth, camera_info, None, True)
