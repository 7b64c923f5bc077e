"""Plain tensor geometry: rotations, poses, back-projection and projection.

Naming: `c2w` camera-to-world, `w2c` world-to-camera, both [4, 4] (OpenCV camera axes).
Quaternions are (w, x, y, z). Pixel (u, v) has its centre at (u + 0.5, v + 0.5), as in gsplat.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F


def rotmat_to_quat(rot: torch.Tensor) -> torch.Tensor:
    """[3, 3] rotation -> unit quaternion [4] (w, x, y, z) with w >= 0."""
    return rotmats_to_quats(rot[None])[0]


def rotmats_to_quats(rot: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotations -> unit quaternions [..., 4] (w, x, y, z) with w >= 0 (Shepperd's
    method, in float64, the result in the input's dtype)."""
    m = rot.double()
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    candidates = torch.stack(
        [
            torch.stack([1 + trace, m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m01 + m10, 1 + m11 - m00 - m22, m12 + m21], dim=-1),
            torch.stack([m10 - m01, m02 + m20, m12 + m21, 1 + m22 - m00 - m11], dim=-1),
        ],
        dim=-2,
    )  # [..., 4, 4]: each row is 4 q_k q (up to scale), best conditioned where its k-th entry is largest
    best = torch.argmax(torch.diagonal(candidates, dim1=-2, dim2=-1), dim=-1)
    rows = best[..., None, None].expand(*best.shape, 1, 4)
    q = F.normalize(torch.take_along_dim(candidates, rows, dim=-2)[..., 0, :], dim=-1)  # no read-back of `best`
    q = torch.where(q[..., :1] < 0, -q, q)
    return q.to(rot.dtype)


# Row-major rotation entries as sums of the products q_i q_j of a unit quaternion (w, x, y, z):
# each entry lists (sign, i, j) terms; e.g. R00 = w^2 + x^2 - y^2 - z^2, R01 = 2 (xy - wz).
_ROTATION_TERMS = (
    ((1, 0, 0), (1, 1, 1), (-1, 2, 2), (-1, 3, 3)),
    ((1, 1, 2), (1, 2, 1), (-1, 0, 3), (-1, 3, 0)),
    ((1, 1, 3), (1, 3, 1), (1, 0, 2), (1, 2, 0)),
    ((1, 1, 2), (1, 2, 1), (1, 0, 3), (1, 3, 0)),
    ((1, 0, 0), (-1, 1, 1), (1, 2, 2), (-1, 3, 3)),
    ((1, 2, 3), (1, 3, 2), (-1, 0, 1), (-1, 1, 0)),
    ((1, 1, 3), (1, 3, 1), (-1, 0, 2), (-1, 2, 0)),
    ((1, 2, 3), (1, 3, 2), (1, 0, 1), (1, 1, 0)),
    ((1, 0, 0), (-1, 1, 1), (-1, 2, 2), (1, 3, 3)),
)


@functools.cache
def _rotation_from_products(device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """[9, 16] matrix taking the flattened outer product q q^T to the flattened rotation."""
    matrix = torch.zeros(9, 16, dtype=dtype)
    for row, terms in enumerate(_ROTATION_TERMS):
        for sign, i, j in terms:
            matrix[row, 4 * i + j] = sign
    return matrix.to(device)


@functools.cache
def _last_row(device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    return torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=dtype).to(device)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[..., 4] (w, x, y, z), any norm -> [..., 3, 3].

    One matrix product with the quaternion's outer product: a few kernels forward and backward,
    where the entry-by-entry form takes ~40 each way. Tracking builds a pose from a quaternion
    every iteration, and there the host's time to launch kernels sets the pace.
    """
    q = F.normalize(quats, dim=-1)
    products = (q[..., :, None] * q[..., None, :]).flatten(-2)  # [..., 16]
    rotation = products @ _rotation_from_products(q.device, q.dtype).T
    return rotation.unflatten(-1, (3, 3))


def pose_matrix(quat: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Quaternion [4] (normalised here) and translation [3] -> [4, 4]."""
    top = torch.cat([quat_to_rotmat(quat), trans[:, None]], dim=1)
    return torch.cat([top, _last_row(top.device, top.dtype)], dim=0)


def invert_pose(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of a rigid [..., 4, 4] transform."""
    rot_t = pose[..., :3, :3].transpose(-1, -2)
    top = torch.cat([rot_t, -(rot_t @ pose[..., :3, 3:4])], dim=-1)
    return torch.cat([top, pose[..., 3:, :]], dim=-2)  # a rigid transform's last row is (0, 0, 0, 1)


def constant_velocity(c2w_prev2: torch.Tensor, c2w_prev: torch.Tensor, fraction: float = 1.0) -> torch.Tensor:
    """Predict the next camera-to-world [4, 4] by repeating the last relative motion, or
    `fraction` of it when the next frame is that much nearer in time (or, above 1, further)."""
    motion = invert_pose(c2w_prev2) @ c2w_prev
    if fraction != 1.0:
        motion = motion_fraction(motion, fraction)
    return c2w_prev @ motion


def motion_extent(motion: torch.Tensor) -> torch.Tensor:
    """Of a rigid motion [4, 4]: [2] (the translation's length in its units, the rotation angle in
    degrees), on its device: nothing is read back."""
    cosine = ((torch.diagonal(motion[:3, :3]).sum() - 1) / 2).clamp(-1.0, 1.0)
    return torch.stack([motion[:3, 3].norm(), torch.rad2deg(torch.arccos(cosine))])


def motion_fraction(motion: torch.Tensor, fraction: float) -> torch.Tensor:
    """`fraction` of a rigid motion [4, 4]: its rotation angle about the same axis and its
    translation, each scaled (0: the identity, 1: the motion itself)."""
    quat = rotmat_to_quat(motion[:3, :3])  # w >= 0: the angle is at most pi
    sine = quat[1:].norm()
    half_angle = torch.atan2(sine, quat[0]) * fraction
    axis = quat[1:] / sine.clamp(min=1e-12)
    scaled = torch.cat([torch.cos(half_angle)[None], torch.sin(half_angle) * axis]).to(motion.dtype)
    return pose_matrix(scaled, motion[:3, 3] * fraction)


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


def skew(vector: torch.Tensor) -> torch.Tensor:
    """[..., 3] -> the cross-product matrix [..., 3, 3]: skew(a) @ b = a x b."""
    x, y, z = vector.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).unflatten(-1, (3, 3))


def se3_exp(twist: torch.Tensor) -> torch.Tensor:
    """Twist [6] (rotation vector in radians, then translation in metres) -> rigid [4, 4].

    The exponential map of se(3): R = I + a W + b W^2, t = (I + b W + c W^2) v with W = skew(w),
    a = sin(th) / th, b = (1 - cos(th)) / th^2, c = (th - sin(th)) / th^3, th = |w|; their
    Taylor series near th = 0, chosen on the device. Call it in float64: b and c cancel badly
    in float32 for small angles.
    """
    omega, v = twist[:3], twist[3:]
    theta_sq = (omega * omega).sum()
    small = theta_sq < 1e-6
    theta = torch.where(small, torch.ones_like(theta_sq), theta_sq).sqrt()
    sin, cos = torch.sin(theta), torch.cos(theta)
    a = torch.where(small, 1 - theta_sq / 6, sin / theta)
    b = torch.where(small, 0.5 - theta_sq / 24, (1 - cos) / theta**2)
    c = torch.where(small, 1 / 6 - theta_sq / 120, (theta - sin) / theta**3)
    w = skew(omega)
    w_sq = w @ w
    eye = torch.eye(4, dtype=twist.dtype, device=twist.device)
    rotation = eye[:3, :3] + a * w + b * w_sq
    translation = (eye[:3, :3] + b * w + c * w_sq) @ v
    top = torch.cat([rotation, translation[:, None]], dim=1)
    return torch.cat([top, eye[3:]], dim=0)


def grid_around(relative: torch.Tensor, step_m: float) -> torch.Tensor:
    """[9, 4, 4] float64 on `relative`'s device: the camera of `relative` [4, 4] (a camera in
    another's frame) and that camera moved `step_m` metres sideways and along its axis around it
    (a 3 x 3 grid in its own x and z, `relative` itself first): where an alignment may start
    when the motion is too large for one basin."""
    offsets = sorted(
        ((x, z) for x in (-step_m, 0.0, step_m) for z in (-step_m, 0.0, step_m)), key=lambda o: o != (0, 0)
    )
    moves = torch.eye(4, dtype=torch.float64).repeat(len(offsets), 1, 1)
    moves[:, 0, 3] = torch.tensor([x for x, _ in offsets], dtype=torch.float64)
    moves[:, 2, 3] = torch.tensor([z for _, z in offsets], dtype=torch.float64)
    return relative.double() @ moves.to(relative.device)
