"""A triangle mesh of the map: TSDF fusion of rendered RGB-D views (Open3D, the `mesh` extra).

Colour and depth are rendered from the Gaussian map at the keyframe poses (where the export
runs, which need not be where the run did); each view is integrated into a sparse (voxel-block)
truncated signed-distance volume, and marching cubes extracts the zero crossing with per-vertex
colours and normals.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from pipeline.config import Config, RenderConfig
from pipeline.errors import DataError
from pipeline.geometry import invert_pose
from pipeline.io.files.atomic import atomic_write_bytes
from pipeline.io.outputs.exports.job import ExportJob, RunRecords
from pipeline.io.outputs.intrinsics import CameraIntrinsics
from pipeline.io.outputs.ply import ply_bytes
from pipeline.render import Camera, make_renderer, resolve_backend
from pipeline.slam.gaussian_map import copied
from pipeline.slam.state import Checkpoint

DEFAULT_NAME = "mesh.ply"  # in the run folder
FOR = "a triangle mesh with vertex colours, fused from renders at the keyframes"
NEEDS: str | None = "open3d"


@dataclass
class RGBDView:
    color: np.ndarray  # [H, W, 3] uint8 RGB
    depth: np.ndarray  # [H, W] float32 metres, 0 = no depth
    c2w: np.ndarray  # [4, 4] camera-to-world, OpenCV camera axes


@dataclass
class TriangleMesh:
    vertices: np.ndarray  # [V, 3] float32 metres, world frame
    colors: np.ndarray  # [V, 3] uint8 RGB
    normals: np.ndarray  # [V, 3] float32 unit
    triangles: np.ndarray  # [F, 3] int32 vertex indices


TRUNCATION_VOXELS = 4.0  # the signed distance is truncated at this many voxels from the surface
BLOCK_RESOLUTION = 8  # voxels per side of a block of the sparse volume (blocks are added as needed)
INITIAL_BLOCKS = 10_000
MIN_SILHOUETTE = 0.9  # rendered depth is fused only where the map covers the pixel at least this much
DEPTH_MARGIN = 1.2  # depths beyond this x the deepest keyframe depth are left out of the fusion


def export(job: ExportJob) -> str:
    """The mesh of the map rendered at every keyframe pose on `job.device` (None: the CPU);
    DataError when the fusion gives no triangle."""
    views = _rendered_views(job.run, job.checkpoint, job.device or torch.device("cpu"))
    mesh = fuse_tsdf(views, job.run.read_intrinsics(), job.voxel_m, _max_depth(job.checkpoint))
    if len(mesh.triangles) == 0:
        raise DataError(f"the map of {job.run.path} gives an empty mesh at {job.voxel_m} m voxels")
    write_mesh_ply(job.target, mesh)
    return f"{len(mesh.vertices):,} vertices, {len(mesh.triangles):,} triangles ({job.voxel_m} m voxels)"


def _rendered_views(run: RunRecords, checkpoint: Checkpoint, device: torch.device) -> Iterator[RGBDView]:
    """Colour and depth rendered from the map at every keyframe pose, one at a time (the fusion
    asks for the next when it has integrated the last); depth kept where the map covers the
    pixel (silhouette >= MIN_SILHOUETTE)."""
    config = run.read_config()
    renderer = make_renderer(_rendering_on(config, device), config.gaussians, device)
    camera = run.read_intrinsics()
    k = torch.tensor(camera.matrix(), dtype=torch.float32, device=device)
    gaussians = copied(checkpoint.gaussians, device)
    for keyframe in checkpoint.keyframes:
        with torch.no_grad():
            c2w = keyframe.c2w.to(device).float()
            view = Camera(invert_pose(c2w), k, camera.width, camera.height, config.render.near, config.render.far)
            out = renderer(gaussians, view)
            depth = torch.where(out.silhouette >= MIN_SILHOUETTE, out.depth, torch.zeros_like(out.depth))
            color = (out.color.clamp(0, 1) * 255).round().to(torch.uint8)
        yield RGBDView(color.cpu().numpy(), depth.cpu().numpy(), c2w.double().cpu().numpy())


def _rendering_on(config: Config, device: torch.device) -> RenderConfig:
    """A finished run's render settings with the backend that suits `device`."""
    return replace(config.render, backend=resolve_backend(replace(config.render, backend="auto"), device))


def _max_depth(checkpoint: Checkpoint) -> float:
    return DEPTH_MARGIN * max(float(k.depth.max()) for k in checkpoint.keyframes)


def fuse_tsdf(views: Iterable[RGBDView], camera: CameraIntrinsics, voxel_m: float, max_depth_m: float) -> TriangleMesh:
    """Integrate `views` into a TSDF of `voxel_m` voxels, depths beyond `max_depth_m` left out,
    and extract its surface where at least one view saw it.

    Open3D's voxel-block grid (its tensor TSDF; the legacy ScalableTSDFVolume of open3d 0.20
    extracts nothing on the CPU build)."""
    import open3d as o3d

    cpu = o3d.core.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3d.core.float32, o3d.core.float32, o3d.core.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=voxel_m,
        block_resolution=BLOCK_RESOLUTION,
        block_count=INITIAL_BLOCKS,
        device=cpu,
    )
    # Open3D puts pixel (u, v) at (u, v) exactly; here its centre is at (u + 0.5, v + 0.5).
    k = camera.matrix()
    k[:2, 2] -= 0.5
    intrinsic = o3d.core.Tensor(k, o3d.core.float64)
    for view in views:
        depth = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(view.depth, dtype=np.float32)))
        color = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(view.color, dtype=np.float32) / 255.0))
        extrinsic = o3d.core.Tensor(np.linalg.inv(view.c2w), o3d.core.float64)  # world-to-camera
        blocks = grid.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1.0, max_depth_m, TRUNCATION_VOXELS)
        grid.integrate(blocks, depth, color, intrinsic, extrinsic, 1.0, max_depth_m, TRUNCATION_VOXELS)
    mesh = grid.extract_triangle_mesh(weight_threshold=0.5).to_legacy()
    mesh.compute_vertex_normals()
    return TriangleMesh(
        vertices=np.asarray(mesh.vertices, dtype=np.float32),
        colors=(np.asarray(mesh.vertex_colors) * 255).round().clip(0, 255).astype(np.uint8),
        normals=np.asarray(mesh.vertex_normals, dtype=np.float32),
        triangles=np.asarray(mesh.triangles, dtype=np.int32),
    )


def write_mesh_ply(path: Path, mesh: TriangleMesh) -> None:
    """Binary PLY: vertices with normals and colours, triangles."""
    v, n, c = mesh.vertices, mesh.normals, mesh.colors
    columns = {"x": v[:, 0], "y": v[:, 1], "z": v[:, 2], "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]}
    columns.update({"red": c[:, 0], "green": c[:, 1], "blue": c[:, 2]})
    atomic_write_bytes(path, ply_bytes(columns, mesh.triangles))
