"""The `export` command: a run folder -> one of the formats of EXPORTERS (a nerfstudio dataset,
`.splat`, PLYs, SPZ, a mesh, a point cloud), from its checkpoint (map and keyframes) and `intrinsics.json`.

Where an export may write is checked before anything is written: never onto a run's own files
(`run_owning`); a file where a file is asked for, a folder for nerfstudio (absent, or an earlier
nerfstudio export, which it replaces as a whole). The checkpoint is validated on reading. A
nerfstudio export is written into a temporary folder beside its place and renamed into it, so it
appears complete or not at all; an OS error (a full disk, no permission) is one line naming the
path, exit code 2."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from pipeline.errors import OutputError, UserError
from pipeline.io.files.folders import make_folder
from pipeline.io.outputs.exports import EXPORTERS
from pipeline.io.outputs.exports.job import NERFSTUDIO_DEFAULTS, ExportJob, NerfstudioOptions
from pipeline.io.outputs.exports.nerfstudio import WRITTEN as NERFSTUDIO_FILES
from pipeline.io.outputs.run_folder import RunFolder, run_owning


@dataclass
class Exported:
    path: Path  # the file or folder written
    summary: str  # what it holds, one line


def export_run(
    run_dir: Path,
    fmt: str,
    output: Path | None = None,
    voxel_m: float = 0.02,
    device: torch.device | None = None,
    nerfstudio: NerfstudioOptions = NERFSTUDIO_DEFAULTS,
) -> Exported:
    """Write `fmt` (a key of EXPORTERS) of the run in `run_dir` to `output` (default: where the
    run folder keeps that export); a mesh is rendered on `device` (None: the CPU)."""
    if voxel_m <= 0:
        raise UserError(f"--voxel must be positive (metres), not {voxel_m}")
    folder = RunFolder.existing(run_dir)
    checkpoint, _ = folder.read_checkpoint()
    target = _checked_target(output or folder.export(fmt), fmt)
    try:
        job = ExportJob(folder, checkpoint, target, voxel_m, device, nerfstudio)
        exported = Exported(target, EXPORTERS[fmt].export(job))
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
