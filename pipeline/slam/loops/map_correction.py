"""Moving the map with corrected keyframe poses: every Gaussian moves rigidly with the keyframe
that created it, by that keyframe's correction corrected @ inv(old)."""

from __future__ import annotations

from dataclasses import replace

import torch

from pipeline.geometry import invert_pose, rotmat_to_quat
from pipeline.render.types import Gaussians


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton products a b of quaternions [..., 4] (w, x, y, z): the rotation of b, then a's."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def corrections(old_c2w: torch.Tensor, new_c2w: torch.Tensor) -> torch.Tensor:
    """Per keyframe, the world motion [K, 4, 4] that takes its old pose [K, 4, 4] to the new one."""
    return new_c2w @ invert_pose(old_c2w)


def move_map(gaussians: Gaussians, creator: torch.Tensor, old_c2w: torch.Tensor, new_c2w: torch.Tensor) -> Gaussians:
    """The map with each Gaussian moved by its creating keyframe's correction: `creator` [N]
    long, the keyframe's position in the pose graph (-1: none), poses [K, 4, 4] camera-to-world
    (metres). Means are rotated and translated, rotations (w, x, y, z, any norm: the norm is
    kept) turned by the correction's rotation; Gaussians of keyframes whose pose is unchanged
    keep their values exactly, and scales, opacities and colours are the same tensors. A new
    Gaussians; the input is not changed."""
    device = gaussians.means.device
    motion = corrections(old_c2w.double(), new_c2w.double()).to(gaussians.means)  # [K, 4, 4]
    changed = (old_c2w != new_c2w).flatten(1).any(-1).to(device)  # [K]
    creator = creator.to(device)
    pick = creator.clamp(min=0)
    moved = (creator >= 0) & changed[pick]
    rotation, translation = motion[pick, :3, :3], motion[pick, :3, 3]  # [N, 3, 3], [N, 3]
    means = (rotation @ gaussians.means[..., None])[..., 0] + translation
    turn = torch.stack([rotmat_to_quat(r) for r in motion[:, :3, :3]])[pick]  # [N, 4]
    quats = quat_multiply(turn.to(gaussians.quats), gaussians.quats)
    keep = ~moved[:, None]
    return replace(
        gaussians,
        means=torch.where(keep, gaussians.means, means),
        quats=torch.where(keep, gaussians.quats, quats),
    )
