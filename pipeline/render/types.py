"""What every renderer takes and returns."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Gaussians:
    """Gaussian parameters in the world frame (metres), before activation.

    The colour is used as is (no activation), as in SplaTAM.
    """

    means: torch.Tensor  # [N, 3] world metres
    quats: torch.Tensor  # [N, 4] (w, x, y, z), unnormalised
    log_scales: torch.Tensor  # [N, 1] isotropic or [N, 3] anisotropic, log metres
    opacity_logits: torch.Tensor  # [N]
    colors: torch.Tensor  # [N, 3] RGB in [0, 1]

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def scales(self) -> torch.Tensor:
        """[N, 3] metres (an isotropic scale repeated on all axes)."""
        return torch.exp(self.log_scales).expand(-1, 3)


@dataclass
class Camera:
    w2c: torch.Tensor  # [4, 4] world-to-camera (OpenCV axes); may require grad
    intrinsics: torch.Tensor  # [3, 3] pixels, pixel (u, v) centred at (u + 0.5, v + 0.5)
    width: int
    height: int
    near: float = 0.01
    far: float = 100.0


@dataclass
class RenderOutput:
    color: torch.Tensor  # [H, W, 3]
    depth: torch.Tensor  # [H, W] expected camera-z depth, metres; 0 where nothing is hit
    silhouette: torch.Tensor  # [H, W] accumulated alpha in [0, 1]
    radii: torch.Tensor  # [N] largest 2D radius in pixels (int32), 0 when culled
    visible: torch.Tensor  # [N] bool: projected inside the image and not culled
