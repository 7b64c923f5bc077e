"""The frame at the size viewers show it."""

from __future__ import annotations

import torch

from pipeline.frame import DeviceFrame
from pipeline.geometry import project
from pipeline.ui.thumbnail import thumbnail


def test_a_wide_frame_shrinks_to_320_pixels_with_its_camera_and_no_depth_invented() -> None:
    k = torch.tensor([[500.0, 0, 319.5], [0, 480.0, 241.0], [0, 0, 1]])
    depth = torch.where(torch.arange(640)[None, :].expand(480, 640) < 320, 1.0, 3.0)  # two walls
    color = torch.rand(480, 640, 3)
    small = thumbnail(DeviceFrame(0, 0.0, color, depth, k, None))
    assert (small.width, small.height) == (320, 240) and small.color.dtype == torch.uint8
    assert set(small.depth.unique().tolist()) == {1.0, 3.0}  # nearest: nothing between the walls
    point = torch.tensor([[0.3, -0.2, 2.0]])  # a point lands on the same place of both images
    assert torch.allclose(project(point, torch.eye(4), small.intrinsics)[0], project(point, torch.eye(4), k)[0] / 2)
    mean = color[:2, :2].mean(dim=(0, 1)) * 255  # area averaging of each 2x2 block
    assert torch.allclose(small.color[0, 0].float(), mean.floor(), atol=1.0)
    unchanged = thumbnail(DeviceFrame(0, 0.0, color[:96, :128], depth[:96, :128], k, None))
    assert (unchanged.width, unchanged.height) == (128, 96) and torch.equal(unchanged.intrinsics, k)
