"""What a viewer shows and the contract the SLAM-side feed drives: the web viewer (viser) and
the desktop one (Open3D) both implement `MapDisplay`; their feed (`ViewerFeed`) and the rerun
sink (`RerunFeed`) both implement `LiveFeed`, what a session holds of its viewer."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from pipeline.frame import DeviceFrame
    from pipeline.slam.handoff import FrameResult
    from pipeline.slam.view import SlamView


@dataclass
class MapView:
    """A map ready for display, on the host."""

    centers: np.ndarray  # [N, 3] float32 world metres
    covariances: np.ndarray  # [N, 3, 3] float32 metres^2
    rgbs: np.ndarray  # [N, 3] float32 in [0, 1]
    opacities: np.ndarray  # [N, 1] float32 in [0, 1]


@dataclass
class FrameView:
    """What a viewer shows of the latest processed frame (host arrays)."""

    index: int
    poses: np.ndarray  # [F, 4, 4] estimated camera-to-world of every frame so far
    intrinsics: np.ndarray  # [3, 3] pixels
    color: np.ndarray  # [H, W, 3] uint8 input colour
    depth: np.ndarray  # [H, W, 3] uint8 input depth, colour-mapped
    rendered_depth: np.ndarray  # [H, W, 3] uint8 colour-mapped, at the latest estimated pose
    silhouette: np.ndarray  # [H, W, 3] uint8
    stats: str  # markdown


class MapDisplay(Protocol):
    """A viewer of a running SLAM. Every method may be called from any thread."""

    running: threading.Event  # cleared while the user pauses SLAM
    save_requested: threading.Event  # set by the user's Save
    stopped: threading.Event  # set by the user's Stop, or when the window is closed

    def clients(self) -> int:
        """How many people are watching (browsers connected; 1 while a window is open)."""
        ...

    def show_map(self, view: MapView) -> None: ...

    def show_frame(self, view: FrameView) -> None: ...

    def show_saved(self, message: str) -> None:
        """Confirm a save where the user pressed Save."""
        ...

    def show_summary(self, markdown: str) -> None:
        """The run is over: its summary, and Stop now just closes."""
        ...

    def close(self) -> None: ...


class LiveFeed(Protocol):
    """A viewer of any kind as a SLAM-stage observer, with its life after SLAM."""

    released: threading.Event  # set once the run is asked to stop: a viewer that paused SLAM lets it go

    def __call__(self, slam: SlamView, frame: DeviceFrame, result: FrameResult) -> None: ...

    def finish(self) -> None:
        """SLAM has stopped: show its final state."""
        ...

    def linger(self, summary: str) -> None:
        """After the run: keep the final state up with `summary` (markdown) while someone watches."""
        ...

    def close(self) -> None:
        """Safe twice."""
        ...


def colorize_depth(depth: np.ndarray, far: float) -> np.ndarray:
    """Depth [H, W] metres -> [H, W, 3] uint8 (turbo colour map, black where 0)."""
    import cv2

    scaled = np.clip(depth / max(far, 1e-6) * 255.0, 0, 255).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[depth <= 0] = 0
    return rgb


def follow_pose(c2w: np.ndarray, back_m: float, up_m: float) -> np.ndarray:
    """A viewpoint behind and above the camera `c2w` [4, 4] (OpenCV axes), looking the same way:
    the frustum stays in view instead of around the eye."""
    pose = c2w.copy()
    pose[:3, 3] = c2w[:3, 3] - back_m * c2w[:3, 2] - up_m * c2w[:3, 1]  # z forward, y down
    return pose
