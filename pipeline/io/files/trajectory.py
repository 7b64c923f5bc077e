"""Trajectories in the TUM format (`timestamp tx ty tz qx qy qz qw`, camera-to-world)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from pipeline.errors import DataError
from pipeline.geometry import quat_to_rotmat, rotmats_to_quats
from pipeline.io.files.atomic import atomic_write_text


def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """[..., 4] quaternions (x, y, z, w), any norm -> [..., 3, 3] rotation matrices (float64)."""
    wxyz = torch.from_numpy(np.asarray(q, dtype=np.float64)[..., [3, 0, 1, 2]])
    return quat_to_rotmat(wxyz).numpy()


def matrix_to_quat_xyzw(rotation: np.ndarray) -> np.ndarray:
    """[..., 3, 3] rotation matrices -> unit quaternions [..., 4] (x, y, z, w) with w >= 0
    (geometry's conversion, float64)."""
    wxyz = rotmats_to_quats(torch.from_numpy(np.asarray(rotation, dtype=np.float64))).numpy()
    return wxyz[..., [1, 2, 3, 0]]


def pose_from_tum_row(row: np.ndarray) -> np.ndarray:
    """(tx, ty, tz, qx, qy, qz, qw) -> [4, 4] camera-to-world."""
    pose = np.eye(4)
    pose[:3, :3] = quat_xyzw_to_matrix(row[3:7])
    pose[:3, 3] = row[:3]
    return pose


def read_numeric_table(path: Path, columns: int) -> np.ndarray:
    """Rows of `columns` finite numbers; '#' comments and blank lines skipped."""
    return read_numeric_lines(path, columns)[0]


def read_numeric_lines(path: Path, columns: int) -> tuple[np.ndarray, list[int]]:
    """-> (rows of `columns` finite numbers [N, columns], the line number of each row)."""
    rows, numbers = [], []
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DataError(f"missing file: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot read {path}: {exc}") from None
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < columns:
            raise DataError(f"{path}:{number}: expected {columns} numbers, found {len(parts)}")
        try:
            row = [float(p) for p in parts[:columns]]
        except ValueError:
            raise DataError(f"{path}:{number}: not a number in '{line}'") from None
        if not all(math.isfinite(v) for v in row):
            raise DataError(f"{path}:{number}: NaN or infinite value in '{line}'")
        rows.append(row)
        numbers.append(number)
    return np.asarray(rows, dtype=np.float64).reshape(-1, columns), numbers


def read_tum_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory file's rows -> (timestamps [N] seconds, rows [N, 7] tx ty tz qx qy qz qw),
    in timestamp order. Raises DataError naming the line of a quaternion that is not a rotation."""
    table, numbers = read_numeric_lines(path, 8)
    norms = np.linalg.norm(table[:, 4:8], axis=1)
    for number, norm in zip(numbers, norms):
        if norm < 1e-6:
            raise DataError(f"{path}:{number}: the quaternion qx qy qz qw is zero, not a rotation")
    order = np.argsort(table[:, 0], kind="stable")
    return table[order, 0], table[order, 1:]


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """-> (timestamps [N] seconds, camera-to-world poses [N, 4, 4])."""
    timestamps, rows = read_tum_poses(path)
    poses = np.stack([pose_from_tum_row(row) for row in rows]) if len(rows) else np.zeros((0, 4, 4))
    return timestamps, poses


def write_tum_trajectory(path: Path, timestamps: np.ndarray, c2w: np.ndarray) -> None:
    """Write camera-to-world poses [N, 4, 4] with their timestamps [N] in the TUM format."""
    atomic_write_text(path, tum_trajectory_text(timestamps, c2w))


def tum_trajectory_text(timestamps: np.ndarray, c2w: np.ndarray) -> str:
    """Camera-to-world poses [N, 4, 4] with their timestamps [N] seconds as a TUM trajectory file."""
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    quats = matrix_to_quat_xyzw(np.asarray(c2w)[:, :3, :3]) if len(c2w) else np.zeros((0, 4))
    for t, pose, q in zip(timestamps, c2w, quats):
        x, y, z = pose[:3, 3]
        lines.append(f"{t:.6f} {x:.9f} {y:.9f} {z:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    return "\n".join(lines) + "\n"
