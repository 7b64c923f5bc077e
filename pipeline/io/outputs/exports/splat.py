"""The `.splat` format of antimatter15's web viewer (read by most web splat viewers).

32 bytes per Gaussian, no header, little-endian: position 3 x float32 (metres), scale
3 x float32 (metres, not logs), colour and opacity 4 x uint8, rotation 4 x uint8 (w, x, y, z of
the unit quaternion, stored as q x 128 + 128). Gaussians are stored most visible first (largest
scale x opacity), as the viewer's own converter does: it draws while the file streams in, and
sorts by depth for every view itself. (gsplat's exporter orders them by Morton code instead.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pipeline.io.files.atomic import atomic_write_bytes
from pipeline.io.outputs.exports.job import ExportJob
from pipeline.render.types import Gaussians

DEFAULT_NAME = "map.splat"  # in the run folder
FOR = "antimatter15's .splat for web viewers, 32 bytes per Gaussian"
NEEDS: str | None = None

SPLAT_RECORD = np.dtype(
    [("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rotation", "u1", (4,))]
)
BYTES_PER_GAUSSIAN = SPLAT_RECORD.itemsize  # 32


def splat_bytes(gaussians: Gaussians) -> bytes:
    """The `.splat` file of `gaussians`; colours are SplaTAM's RGB in [0, 1] (no SH)."""
    with torch.no_grad():
        scales = gaussians.scales().float()
        opacity = torch.sigmoid(gaussians.opacity_logits.float())
        order = torch.argsort(scales.prod(dim=1) * opacity, descending=True)
        rgba = torch.cat([gaussians.colors.float().clamp(0, 1), opacity[:, None]], dim=1)
        unit = torch.nn.functional.normalize(gaussians.quats.float(), dim=1)
        records = np.empty(len(gaussians), dtype=SPLAT_RECORD)
        records["position"] = gaussians.means.float()[order].cpu().numpy()
        records["scale"] = scales[order].cpu().numpy()
        records["rgba"] = (rgba[order] * 255).round().cpu().numpy().astype(np.uint8)
        records["rotation"] = (unit[order] * 128 + 128).clamp(0, 255).cpu().numpy().astype(np.uint8)
    return records.tobytes()


def write_splat(path: Path, gaussians: Gaussians) -> None:
    atomic_write_bytes(path, splat_bytes(gaussians))


def export(job: ExportJob) -> str:
    write_splat(job.target, job.checkpoint.gaussians)
    return f"{len(job.checkpoint.gaussians):,} Gaussians, 32 bytes each"
