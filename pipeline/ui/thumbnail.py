"""A frame at the size viewers show it: images at most `DISPLAY_WIDTH` pixels wide, and the
camera that sees them."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from pipeline.frame import DeviceFrame

DISPLAY_WIDTH = 320  # pixels: the images viewers show (panels, frustums, rerun) are this wide at most


@dataclass
class Thumbnail:
    """A frame's images and camera at the display size, new tensors where the frame's are."""

    color: torch.Tensor  # [h, w, 3] uint8
    depth: torch.Tensor  # [h, w] float32 metres, 0 = invalid
    intrinsics: torch.Tensor  # [3, 3] pixels, for the size [h, w]

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])


def as_u8(values: torch.Tensor) -> torch.Tensor:
    """Values in [0, 1] (clamped) -> uint8, on their device."""
    return (values.clamp(0, 1) * 255).to(torch.uint8)


def thumbnail(frame: DeviceFrame, max_width: int = DISPLAY_WIDTH) -> Thumbnail:
    """Colour by area averaging, depth by nearest pixel (no depth invented between surfaces)."""
    scale = min(1.0, max_width / frame.width)
    width, height = max(1, round(frame.width * scale)), max(1, round(frame.height * scale))
    intrinsics = frame.intrinsics.clone()
    intrinsics[0] *= width / frame.width  # Python numbers: no copy to the device (a host wait) at a frame boundary
    intrinsics[1] *= height / frame.height
    color = F.interpolate(frame.color.permute(2, 0, 1)[None], size=(height, width), mode="area")[0].permute(1, 2, 0)
    depth = F.interpolate(frame.depth[None, None], size=(height, width), mode="nearest")[0, 0]
    return Thumbnail(as_u8(color), depth, intrinsics)
