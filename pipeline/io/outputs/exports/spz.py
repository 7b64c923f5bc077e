"""Niantic's SPZ (gzip-compressed Gaussians: 24-bit fixed-point positions, 8-bit log-scales,
colours and opacity, smallest-three rotations; about a tenth of a PLY), written by gsply
(MIT, the `spz` extra: `pip install 'gsplatam[spz]'`), version 3, the one Niantic's own
library and most viewers read."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.io.files.atomic import atomic_export
from pipeline.io.outputs.exports.job import ExportJob
from pipeline.io.outputs.ply import splat_fields
from pipeline.render.types import Gaussians

DEFAULT_NAME = "map.spz"  # in the run folder
FOR = "Niantic's SPZ (version 3, gzip, about a tenth of a PLY), by gsply"
NEEDS: str | None = "gsply"


def write_spz(path: Path, gaussians: Gaussians) -> None:
    import gsply

    a = {name: np.ascontiguousarray(values.numpy()) for name, values in splat_fields(gaussians).items()}
    data = gsply.GSData(a["means"], a["scales"], a["quats"], a["opacities"], a["sh0"], a["shN"])
    atomic_export(path, lambda staged: gsply.write_spz(staged, data))


def export(job: ExportJob) -> str:
    write_spz(job.target, job.checkpoint.gaussians)
    return f"{len(job.checkpoint.gaussians):,} Gaussians, SPZ version 3 (gzip)"
