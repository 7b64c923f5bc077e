"""The 3D Gaussian-splatting PLY with every property training code writes: normals and the 45
higher-order SH coefficients `f_rest_*` (zeros: the map is view-independent), for viewers that
refuse or misdraw files without them. `map.ply` of a run is the compact form without f_rest_*.
"""

from __future__ import annotations

from pathlib import Path

import torch

from pipeline.config import GaussianKind
from pipeline.geometry import quat_to_rotmat
from pipeline.io.files.atomic import atomic_write_bytes
from pipeline.io.outputs.exports.job import ExportJob
from pipeline.io.outputs.ply import gaussian_columns, ply_bytes
from pipeline.render.types import Gaussians

DEFAULT_NAME = "map_3dgs.ply"  # in the run folder
FOR = "the 3DGS PLY with every property (normals, f_rest_* as zeros) for viewers that want them all"
NEEDS: str | None = None

SH_REST = 45  # SH degree 3: 15 coefficients per colour channel beyond the DC term


def surface_normals(gaussians: Gaussians, kind: GaussianKind) -> torch.Tensor:
    """[N, 3] unit normals: a 2D Gaussian's third axis; a 3D Gaussian's shortest axis when its
    scales differ; zeros for isotropic 3D Gaussians, which have no preferred direction."""
    n = len(gaussians)
    if kind == "3d" and gaussians.log_scales.shape[1] == 1:
        return torch.zeros(n, 3)
    with torch.no_grad():
        rotation = quat_to_rotmat(gaussians.quats.float())
        axis = torch.full((n,), 2) if kind == "2d" else gaussians.log_scales.argmin(dim=1)
        return rotation[torch.arange(n), :, axis]


def write_full_ply(path: Path, gaussians: Gaussians, kind: GaussianKind) -> None:
    columns = gaussian_columns(gaussians, sh_rest=SH_REST, normals=surface_normals(gaussians, kind))
    atomic_write_bytes(path, ply_bytes(columns))


def export(job: ExportJob) -> str:
    write_full_ply(job.target, job.checkpoint.gaussians, job.run.read_config().gaussians.kind)
    return f"{len(job.checkpoint.gaussians):,} Gaussians with normals and f_rest_* (zeros)"
