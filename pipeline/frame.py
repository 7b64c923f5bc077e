"""The unit of data that flows through the pipeline."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


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

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])
