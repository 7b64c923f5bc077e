"""The common 3D Gaussian-splatting PLY: x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3.

Binary little-endian float32, as written by the original 3DGS code and read by common splat
viewers. Colours are stored as degree-0 spherical-harmonic coefficients, f_dc = (rgb - 0.5) / C0;
opacity as a logit; scales as logs (an isotropic scale repeated); rotations as (w, x, y, z).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pipeline.errors import DataError
from pipeline.io.files.atomic import atomic_write_bytes
from pipeline.render.types import Gaussians

SH_C0 = 0.28209479177387814
PROPERTIES = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)
PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "uchar": "u1", "int": "<i4", "uint": "<u4"}


def splat_fields(gaussians: Gaussians) -> dict[str, torch.Tensor]:
    """The map as the 3DGS exporters of other libraries take it (gsplat's, gsply's): float32 on
    the host, means [N, 3], log-scales [N, 3] (an isotropic one repeated), quaternions [N, 4]
    (w, x, y, z), opacity logits [N], the colour as its SH DC coefficient [N, 3] and no
    higher-order SH ([N, 0, 3])."""
    n = len(gaussians)
    return {
        "means": gaussians.means.detach().float().cpu(),
        "scales": gaussians.log_scales.detach().float().expand(-1, 3).cpu(),
        "quats": gaussians.quats.detach().float().cpu(),
        "opacities": gaussians.opacity_logits.detach().float().cpu(),
        "sh0": (gaussians.colors.detach().float().cpu() - 0.5) / SH_C0,
        "shN": torch.zeros(n, 0, 3),
    }


def gaussian_columns(
    gaussians: Gaussians, sh_rest: int = 0, normals: torch.Tensor | None = None
) -> dict[str, np.ndarray]:
    """The 3DGS properties in their usual order, one float32 column each: position, normal
    (`normals` [N, 3], zeros without), SH DC, `sh_rest` higher-order SH coefficients (zeros),
    opacity logit, log-scales, rotation (w, x, y, z)."""
    n = len(gaussians)
    blocks = {
        "xyz": gaussians.means,
        "n": normals if normals is not None else torch.zeros(n, 3),
        "f_dc_": (gaussians.colors - 0.5) / SH_C0,
        "f_rest_": torch.zeros(n, sh_rest),
        "opacity": gaussians.opacity_logits[:, None],
        "scale_": gaussians.log_scales.expand(-1, 3),
        "rot_": gaussians.quats,
    }
    names = {"xyz": ["x", "y", "z"], "n": ["nx", "ny", "nz"], "opacity": ["opacity"]}
    columns = {}
    for prefix, block in blocks.items():
        values = block.detach().cpu().float().numpy()
        for i, name in enumerate(names.get(prefix) or [f"{prefix}{j}" for j in range(values.shape[1])]):
            columns[name] = values[:, i]
    return columns


def ply_bytes(vertices: dict[str, np.ndarray], faces: np.ndarray | None = None) -> bytes:
    """A binary little-endian PLY of named vertex columns (float32 or uint8 arrays of one
    length) and optional triangles `faces` [F, 3] (vertex indices)."""
    kinds = {np.dtype("<f4"): "float", np.dtype("u1"): "uchar"}
    count = len(next(iter(vertices.values())))
    table = np.empty(count, dtype=[(name, column.dtype.newbyteorder("<")) for name, column in vertices.items()])
    for name, column in vertices.items():
        table[name] = column
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {count}"]
    header += [f"property {kinds[column.dtype]} {name}" for name, column in vertices.items()]
    body = [table.tobytes()]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
        packed = np.empty(len(faces), dtype=[("n", "u1"), ("indices", "<i4", (3,))])
        packed["n"], packed["indices"] = 3, faces
        body.append(packed.tobytes())
    return ("\n".join(header + ["end_header"]) + "\n").encode("ascii") + b"".join(body)


def write_ply(path: Path, gaussians: Gaussians) -> None:
    """Write the map atomically (the layout of the module docstring)."""
    atomic_write_bytes(path, gaussian_ply_bytes(gaussians))


def gaussian_ply_bytes(gaussians: Gaussians) -> bytes:
    """The map as the bytes of a PLY file in the layout of the module docstring."""
    return ply_bytes(gaussian_columns(gaussians))


def read_ply(path: Path) -> Gaussians:
    """Read a 3DGS PLY (any property order; extra properties such as f_rest_* are ignored)."""
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read {path}: {exc}") from None
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise DataError(f"{path} is not a PLY file")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise DataError(f"{path}: only binary little-endian PLY is supported")
    count, names, types = None, [], []
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            if len(parts) != 3 or not parts[2].isdigit():
                raise DataError(f"{path}: malformed header line '{line}'")
            count = int(parts[2])
        elif parts[:1] == ["property"] and len(parts) == 3:
            if parts[1] not in PLY_TYPES:
                raise DataError(f"{path}: unsupported property type {parts[1]}")
            types.append(PLY_TYPES[parts[1]])
            names.append(parts[2])
    if count is None:
        raise DataError(f"{path}: the header has no 'element vertex' line")
    missing = [p for p in PROPERTIES if p not in names and not p.startswith("n")]
    if missing:
        raise DataError(f"{path}: not a Gaussian-splatting PLY (missing {', '.join(missing)})")
    try:
        layout = np.dtype(list(zip(names, types)))
    except ValueError as exc:  # e.g. a property named twice
        raise DataError(f"{path}: malformed header ({exc})") from None
    body = len(raw) - end - len(b"end_header\n")
    if body < count * layout.itemsize:
        raise DataError(
            f"{path} is truncated: its header announces {count} Gaussians, the file holds {body // layout.itemsize}"
        )
    table = np.frombuffer(raw, dtype=layout, count=count, offset=end + len(b"end_header\n"))
    if not all(np.isfinite(table[name]).all() for name in PROPERTIES if name in names):
        raise DataError(f"{path} holds NaN or infinite values: not a map a run saved")

    def cols(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([table[k].astype(np.float32) for k in keys], axis=1))

    return Gaussians(
        means=cols("x", "y", "z"),
        quats=cols("rot_0", "rot_1", "rot_2", "rot_3"),
        log_scales=cols("scale_0", "scale_1", "scale_2"),
        opacity_logits=cols("opacity")[:, 0],
        colors=cols("f_dc_0", "f_dc_1", "f_dc_2") * SH_C0 + 0.5,
    )
