"""Niantic's SPZ (gzip-compressed Gaussians: 24-bit fixed-point positions, 8-bit log-scales,
colours and opacity, smallest-three rotations; about a tenth of a PLY), written by gsply
(MIT, the `spz` extra: `pip install 'gsplatam[spz]'`), version 3, the one Niantic's own
library and most viewers read."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.io.files.atomic import atomic_export
from pipeline.io.outputs.ply import splat_fields
from pipeline.render.types import Gaussians


def write_spz(path: Path, gaussians: Gaussians) -> None:
    import gsply

    a = {name: np.ascontiguousarray(values.numpy()) for name, values in splat_fields(gaussians).items()}
    data = gsply.GSData(a["means"], a["scales"], a["quats"], a["opacities"], a["sh0"], a["shN"])
    atomic_export(path, lambda staged: gsply.write_spz(staged, data))
