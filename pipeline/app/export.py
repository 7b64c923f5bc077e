"""The `export` command: a run folder -> a nerfstudio dataset, `.splat`, a full 3DGS PLY, a mesh
or a point cloud, from its checkpoint (map and keyframes) and `intrinsics.json`.

Where an export may write is checked before anything is written: never onto a run's own files
(`run_owning`); a file where a file is asked for, a folder for nerfstudio (absent, or an earlier
nerfstudio export, which it replaces as a whole). The checkpoint is validated on reading. A
nerfstudio export is written into a temporary folder beside its place and renamed into it, so it
appears complete or not at all; an OS error (a full disk, no permission) is one line naming the
path, exit code 2."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch

from pipeline.app.setup import rendering_on
from pipeline.errors import DataError, OutputError, UserError
from pipeline.geometry import invert_pose
from pipeline.io.files.folders import atomic_folder, make_folder
from pipeline.io.outputs.exports.compressed_ply import write_compressed_ply
from pipeline.io.outputs.exports.full_ply import write_full_ply
from pipeline.io.outputs.exports.mesh import RGBDView, fuse_tsdf, write_mesh_ply
from pipeline.io.outputs.exports.nerfstudio import WRITTEN as NERFSTUDIO_FILES
from pipeline.io.outputs.exports.nerfstudio import Frames, Size, views_of, write_nerfstudio
from pipeline.io.outputs.exports.pointcloud import write_pointcloud
from pipeline.io.outputs.exports.splat import write_splat
from pipeline.io.outputs.exports.spz import write_spz
from pipeline.io.outputs.run_folder import RunFolder, run_owning
from pipeline.render import Camera, make_renderer
from pipeline.slam.gaussian_map import copied
from pipeline.slam.state import Checkpoint

MESH_MIN_SILHOUETTE = 0.9  # rendered depth is fused only where the map covers the pixel at least this much
MESH_DEPTH_MARGIN = 1.2  # depths beyond this x the deepest keyframe depth are left out of the fusion


@dataclass
class Exported:
    path: Path  # the file or folder written
    summary: str  # what it holds, one line


@dataclass(frozen=True)
class NerfstudioOptions:
    frames: Frames = "keyframes"  # keyframes, or every frame tracked well
    size: Size = "working"  # SLAM's working size, or the dataset's own


def export_run(
    run_dir: Path,
    fmt: str,
    output: Path | None = None,
    voxel_m: float = 0.02,
    device: torch.device | None = None,
    nerfstudio: NerfstudioOptions = NerfstudioOptions(),
) -> Exported:
    """Write `fmt` (a key of FORMATS) of the run in `run_dir` to `output` (default: where the
    run folder keeps that export); a mesh is rendered on `device` (None: the CPU)."""
    if voxel_m <= 0:
        raise UserError(f"--voxel must be positive (metres), not {voxel_m}")
    folder = RunFolder.existing(run_dir)
    checkpoint, _ = folder.read_checkpoint()
    target = _checked_target(output or folder.export(fmt), fmt)
    try:
        exported = _write(fmt, folder, checkpoint, target, voxel_m, device, nerfstudio)
        folder.record_export(fmt, exported.path, checkpoint)
    except OSError as exc:
        raise OutputError(f"cannot write {target}: {exc.strerror or exc}") from None
    return exported


def _checked_target(target: Path, fmt: str) -> Path:
    """`target` (its folder resolved, and created) once the export may write there; UserError
    naming it otherwise."""
    target = target.parent.resolve() / target.name
    owner = run_owning(target)
    if owner is not None:
        raise UserError(
            f"{target} is one of the run folder {owner.path}'s own files: an export never writes onto a run; "
            "choose another --output"
        )
    if fmt == "nerfstudio":
        _check_nerfstudio_folder(target)
    elif target.is_dir():
        raise UserError(f"{target} is a folder: --output names the file to write")
    make_folder(target.parent, "the export's folder")
    return target


def _check_nerfstudio_folder(target: Path) -> None:
    """A nerfstudio export replaces only an earlier nerfstudio export (or an empty folder)."""
    if target.exists() and not target.is_dir():
        raise UserError(f"{target} is a file: a nerfstudio export is a folder, choose another --output")
    if target.is_dir():
        written = {path for pattern in NERFSTUDIO_FILES for path in target.glob(pattern)}
        others = sorted(p for p in target.rglob("*") if not p.is_dir() and p not in written)
        if others:
            raise UserError(
                f"{target} holds files that are not a nerfstudio export (e.g. {others[0]}): "
                "an export replaces only an earlier export; choose another --output"
            )


def _write(
    fmt: str,
    folder: RunFolder,
    checkpoint: Checkpoint,
    target: Path,
    voxel_m: float,
    device: torch.device | None,
    nerfstudio: NerfstudioOptions,
) -> Exported:
    """Write `fmt` of `checkpoint` (of the run in `folder`) to `target`."""
    gaussians = checkpoint.gaussians
    if fmt == "nerfstudio":
        working = folder.read_intrinsics()
        config, stamps = folder.read_config(), folder.frame_timestamps()
        views, camera = views_of(checkpoint, config, working, nerfstudio.frames, nerfstudio.size, stamps)
        counts: list[int] = []
        atomic_folder(target, lambda staged: counts.append(write_nerfstudio(staged, views, camera, gaussians)))
        what = "keyframes" if nerfstudio.frames == "keyframes" else "frames"
        return Exported(target, f"{counts[0]} {what} at {camera.width}x{camera.height} with depth, transforms.json")
    if fmt == "splat":
        write_splat(target, gaussians)
        return Exported(target, f"{len(gaussians):,} Gaussians, 32 bytes each")
    if fmt == "ply":
        write_full_ply(target, gaussians, folder.read_config().gaussians.kind)
        return Exported(target, f"{len(gaussians):,} Gaussians with normals and f_rest_* (zeros)")
    if fmt == "compressed-ply":
        write_compressed_ply(target, gaussians)
        return Exported(
            target, f"{len(gaussians):,} Gaussians (those over 1/255 opacity), 16 bytes each, chunks of 256"
        )
    if fmt == "spz":
        write_spz(target, gaussians)
        return Exported(target, f"{len(gaussians):,} Gaussians, SPZ version 3 (gzip)")
    if fmt == "pointcloud":
        write_pointcloud(target, gaussians)
        return Exported(target, f"{len(gaussians):,} coloured points (Gaussian centres)")
    mesh = fuse_tsdf(
        _rendered_views(folder, checkpoint, device or torch.device("cpu")),
        folder.read_intrinsics(),
        voxel_m,
        _max_depth(checkpoint),
    )
    if len(mesh.triangles) == 0:
        raise DataError(f"the map of {folder.path} gives an empty mesh at {voxel_m} m voxels")
    write_mesh_ply(target, mesh)
    return Exported(target, f"{len(mesh.vertices):,} vertices, {len(mesh.triangles):,} triangles ({voxel_m} m voxels)")


def _rendered_views(folder: RunFolder, checkpoint: Checkpoint, device: torch.device) -> Iterator[RGBDView]:
    """Colour and depth rendered from the map at every keyframe pose, one at a time (the fusion
    asks for the next when it has integrated the last); depth kept where the map covers the
    pixel (silhouette >= MESH_MIN_SILHOUETTE)."""
    config = folder.read_config()
    renderer = make_renderer(rendering_on(config, device), config.gaussians, device)
    camera = folder.read_intrinsics()
    k = torch.tensor(camera.matrix(), dtype=torch.float32, device=device)
    gaussians = copied(checkpoint.gaussians, device)
    for keyframe in checkpoint.keyframes:
        with torch.no_grad():
            c2w = keyframe.c2w.to(device).float()
            view = Camera(invert_pose(c2w), k, camera.width, camera.height, config.render.near, config.render.far)
            out = renderer(gaussians, view)
            depth = torch.where(out.silhouette >= MESH_MIN_SILHOUETTE, out.depth, torch.zeros_like(out.depth))
            color = (out.color.clamp(0, 1) * 255).round().to(torch.uint8)
        yield RGBDView(color.cpu().numpy(), depth.cpu().numpy(), c2w.double().cpu().numpy())


def _max_depth(checkpoint: Checkpoint) -> float:
    return MESH_DEPTH_MARGIN * max(float(k.depth.max()) for k in checkpoint.keyframes)
