"""Niantic's SPZ (gzip-compressed Gaussians: 24-bit fixed-point positions, 8-bit log-scales,
colours and opacity, smallest-three rotations; about a tenth of a PLY), written by gsply
(MIT, the `spz` extra: `pip install 'gsplatam[spz]'`), version 3, the one Niantic's own
library and most viewers read."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.files.atomic import atomic_export
from pipeline.outputs.ply import SH_C0
from pipeline.render.types import Gaussians


def write_spz(path: Path, gaussians: Gaussians) -> None:
    import gsply

    def array(values: object) -> np.ndarray:
        return np.ascontiguousarray(np.asarray(values, dtype=np.float32))

    n = len(gaussians)
    data = gsply.GSData(
        means=array(gaussians.means.detach().float().cpu()),
        scales=array(gaussians.log_scales.detach().float().expand(-1, 3).cpu()),
        quats=array(gaussians.quats.detach().float().cpu()),
        opacities=array(gaussians.opacity_logits.detach().float().cpu()),
        sh0=array((gaussians.colors.detach().float().cpu() - 0.5) / SH_C0),
        shN=np.zeros((n, 0, 3), dtype=np.float32),
    )
    atomic_export(path, lambda staged: gsply.write_spz(staged, data))
