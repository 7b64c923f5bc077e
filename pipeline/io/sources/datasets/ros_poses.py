"""Poses from a bag: /tf (and /tf_static) between two named frames, and the pose nearest a time."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.io.sources.datasets.ros_messages import stamp_seconds, transform_matrix


def _frame(name: str) -> str:
    return name.lstrip("/")  # ROS 1 names frames "/world" as often as "world"


class TfTree:
    """The transforms /tf and /tf_static carried: for each child frame its parent and the
    transform parent <- child (the child's pose in its parent) over time."""

    def __init__(self) -> None:
        self._parent: dict[str, str] = {}
        self._times: dict[str, list[float]] = {}
        self._poses: dict[str, list[np.ndarray]] = {}
        self._static: set[str] = set()

    def add(self, message: Any, static: bool) -> None:
        """The transforms of one tf2_msgs/TFMessage."""
        for stamped in message.transforms:
            child = _frame(stamped.child_frame_id)
            self._parent[child] = _frame(stamped.header.frame_id)
            self._times.setdefault(child, []).append(stamp_seconds(stamped))
            self._poses.setdefault(child, []).append(
                transform_matrix(stamped.transform.translation, stamped.transform.rotation)
            )
            if static:
                self._static.add(child)

    def lookup(self, world: str, camera: str, t: float, max_dt: float) -> np.ndarray | None:
        """`camera`'s pose in `world` [4, 4] at time `t` (seconds): every transform on the way
        from its nearest sample within `max_dt` (a static one whatever its time); None where
        the frames are not linked, or a transform has no sample near `t`."""
        to_camera, to_world = self._to_root(_frame(camera), t, max_dt), self._to_root(_frame(world), t, max_dt)
        if to_camera is None or to_world is None or to_camera[0] != to_world[0]:
            return None
        return np.linalg.inv(to_world[1]) @ to_camera[1]

    def _to_root(self, frame: str, t: float, max_dt: float) -> tuple[str, np.ndarray] | None:
        """(the root of `frame`'s tree, the root <- frame transform at `t`), or None."""
        pose, seen = np.eye(4), {frame}
        while frame in self._parent:
            times = np.asarray(self._times[frame])
            k = int(np.argmin(np.abs(times - t)))
            if frame not in self._static and abs(times[k] - t) >= max_dt:
                return None
            pose = self._poses[frame][k] @ pose
            frame = self._parent[frame]
            if frame in seen:  # a loop of transforms: no tree
                return None
            seen.add(frame)
        return frame, pose

    def describe(self) -> str:
        """The links it has, `parent -> child`, for an error message."""
        links = sorted(f"{parent} -> {child}" for child, parent in self._parent.items())
        return "its links: " + (", ".join(links[:12]) if links else "none")


def nearest_poses(
    times: np.ndarray, pose_t: np.ndarray, poses: Sequence[np.ndarray], max_dt: float
) -> list[np.ndarray | None]:
    """For each of `times` the pose whose time is nearest, when within `max_dt` (else None)."""
    found: list[np.ndarray | None] = []
    for t in times:
        k = int(np.argmin(np.abs(pose_t - t)))
        found.append(poses[k] if abs(pose_t[k] - t) < max_dt else None)
    return found
