"""Plain tensor geometry: rotations, poses, back-projection and projection.

Naming: `c2w` camera-to-world, `w2c` world-to-camera, both [4, 4] (OpenCV camera axes).
Quaternions are (w, x, y, z). Pixel (u, v) has its centre at (u + 0.5, v + 0.5), as in gsplat.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[..., 4] (w, x, y, z), any norm -> [..., 3, 3]."""
    w, x, y, z = F.normalize(quats, dim=-1).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def rotmat_to_quat(rot: torch.Tensor) -> torch.Tensor:
    """[3, 3] rotation -> unit quaternion [4] (w, x, y, z) with w >= 0."""
    m = rot.double()
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = torch.stack(
        [
            torch.stack([1 + trace, m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]),
            torch.stack([m[2, 1] - m[1, 2], 1 + m[0, 0] - m[1, 1] - m[2, 2], m[0, 1] + m[1, 0], m[0, 2] + m[2, 0]]),
            torch.stack([m[0, 2] - m[2, 0], m[0, 1] + m[1, 0], 1 + m[1, 1] - m[0, 0] - m[2, 2], m[1, 2] + m[2, 1]]),
            torch.stack([m[1, 0] - m[0, 1], m[0, 2] + m[2, 0], m[1, 2] + m[2, 1], 1 + m[2, 2] - m[0, 0] - m[1, 1]]),
        ]
    )  # each row is 4 q_k q (up to scale), best conditioned where its k-th entry is largest
    best = torch.argmax(torch.stack([candidates[k, k] for k in range(4)]))
    q = F.normalize(candidates.index_select(0, best[None])[0], dim=0)  # no read-back of `best`
    q = torch.where(q[0] < 0, -q, q)
    return q.to(rot.dtype)


def pose_matrix(quat: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Quaternion [4] (normalised here) and translation [3] -> [4, 4]."""
    top = torch.cat([quat_to_rotmat(quat), trans[:, None]], dim=1)
    bottom = torch.eye(4, dtype=top.dtype, device=top.device)[3:]  # made on the device: no host copy
    return torch.cat([top, bottom], dim=0)


def invert_pose(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of a rigid [..., 4, 4] transform."""
    rot_t = pose[..., :3, :3].transpose(-1, -2)
    top = torch.cat([rot_t, -(rot_t @ pose[..., :3, 3:4])], dim=-1)
    return torch.cat([top, pose[..., 3:, :]], dim=-2)  # a rigid transform's last row is (0, 0, 0, 1)


def constant_velocity(c2w_prev2: torch.Tensor, c2w_prev: torch.Tensor) -> torch.Tensor:
    """Predict the next camera-to-world by repeating the last relative motion."""
    motion = invert_pose(c2w_prev2) @ c2w_prev
    return c2w_prev @ motion


def pixel_grid(height: int, width: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates (u + 0.5, v + 0.5), each [H, W]."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=torch.float32) + 0.5,
        torch.arange(width, device=device, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    return u, v


def backproject(
    u: torch.Tensor, v: torch.Tensor, depth: torch.Tensor, intrinsics: torch.Tensor, c2w: torch.Tensor
) -> torch.Tensor:
    """Pixel centres [M] with depth [M] metres -> world points [M, 3]."""
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    cam = torch.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], dim=-1)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def project(points: torch.Tensor, w2c: torch.Tensor, intrinsics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World points [..., M, 3] through world-to-camera [..., 4, 4] -> (pixel coords [..., M, 2], depth [..., M])."""
    cam = points @ w2c[..., :3, :3].transpose(-1, -2) + w2c[..., None, :3, 3]
    z = cam[..., 2]
    safe = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
    uv = torch.stack(
        [
            intrinsics[0, 0] * cam[..., 0] / safe + intrinsics[0, 2],
            intrinsics[1, 1] * cam[..., 1] / safe + intrinsics[1, 2],
        ],
        dim=-1,
    )
    return uv, z
