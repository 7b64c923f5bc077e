"""The unit of data that flows through the pipeline."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class ImageFeatures:
    """A frame's image features (ORB) and where their pixels lie in its camera."""

    pixels: np.ndarray  # [N, 2] float32 keypoint positions (x, y), pixels
    descriptors: np.ndarray  # [N, 32] uint8 ORB descriptors
    points: np.ndarray  # [N, 3] float32 each keypoint lifted by its depth, camera frame, metres; z = 0: no depth


@dataclass(frozen=True)
class FrameMotion:
    """Visual odometry's estimate of how the camera moved since an earlier frame."""

    since: int  # the index of the earlier frame
    c2c: np.ndarray  # [4, 4] float64 this camera's pose in the earlier camera's frame (camera-to-camera), metres
    inliers: int  # feature matches that agree with it


@dataclass
class Frame:
    """One decoded RGB-D frame on the host.

    Poses are camera-to-world (OpenCV camera axes: x right, y down, z forward), relative to
    the sequence's first frame.
    """

    index: int
    timestamp: float  # seconds
    color: np.ndarray  # [H, W, 3] uint8 RGB
    depth: np.ndarray  # [H, W] float32 metres, 0 = invalid
    intrinsics: np.ndarray  # [3, 3] float64 pixels
    c2w_gt: np.ndarray | None  # [4, 4] float64 ground-truth camera-to-world, if known
    c2w_prior: np.ndarray | None = None  # [4, 4] float64 a device's own pose estimate (e.g. ARKit), if used
    received_at: float | None = None  # host clock (time.perf_counter, s) when a live source received it
    features: ImageFeatures | None = None  # set in the decode stage when visual odometry is on
    motion: FrameMotion | None = None  # visual odometry since the frame before it (the odometry step)

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])


@dataclass
class DeviceFrame:
    """A frame's tensors on the compute device, ready for tracking and mapping."""

    index: int
    timestamp: float
    color: torch.Tensor  # [H, W, 3] float32 in [0, 1]
    depth: torch.Tensor  # [H, W] float32 metres, 0 = invalid
    intrinsics: torch.Tensor  # [3, 3] float32
    c2w_gt: torch.Tensor | None  # [4, 4] float32
    c2w_prior: torch.Tensor | None = None  # [4, 4] float32 a device's pose estimate: tracking starts from its motion
    received_at: float | None = None  # host clock (time.perf_counter, s) when a live source received it
    motion: FrameMotion | None = None  # visual odometry since an earlier frame (on the host)

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])
