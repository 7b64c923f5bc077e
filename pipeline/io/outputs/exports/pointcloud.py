"""The map as a coloured point cloud: one point per Gaussian centre (PLY: x y z, red green blue).

Any point-cloud tool reads it (Open3D, CloudCompare, MeshLab), and nerfstudio's splatfacto
starts from it when transforms.json names it (`ply_file_path`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.io.files.atomic import atomic_write_bytes
from pipeline.io.outputs.exports.job import ExportJob
from pipeline.io.outputs.ply import ply_bytes
from pipeline.render.types import Gaussians

DEFAULT_NAME = "pointcloud.ply"  # in the run folder
FOR = "the Gaussian centres with their colours, for any point-cloud tool"
NEEDS: str | None = None


def pointcloud_bytes(gaussians: Gaussians) -> bytes:
    xyz = gaussians.means.detach().float().cpu().numpy()
    rgb = (gaussians.colors.detach().float().clamp(0, 1) * 255).round().cpu().numpy().astype(np.uint8)
    columns = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]}
    return ply_bytes(columns)


def write_pointcloud(path: Path, gaussians: Gaussians) -> None:
    atomic_write_bytes(path, pointcloud_bytes(gaussians))


def export(job: ExportJob) -> str:
    write_pointcloud(job.target, job.checkpoint.gaussians)
    return f"{len(job.checkpoint.gaussians):,} coloured points (Gaussian centres)"
