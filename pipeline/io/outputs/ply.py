"""The common 3D Gaussian-splatting PLY: x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3.

Written binary little-endian float32, as by the original 3DGS code and read by common splat
viewers; read in any encoding (plyfile). Colours are stored as degree-0 spherical-harmonic coefficients, f_dc = (rgb - 0.5) / C0;
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
    """A 3DGS map from a PLY file of any encoding plyfile reads (ASCII, binary of either byte
    order; any property order, extra properties such as f_rest_* ignored), or the compressed PLY
    (`export --to compressed-ply`, decoded by gsply: the 'spz' extra). DataError naming the file
    where it is none of these, or holds NaN or infinite values."""
    from plyfile import PlyData, PlyParseError

    try:
        data = PlyData.read(str(path))
    except OSError as exc:
        raise DataError(f"cannot read {path}: {exc.strerror or exc}") from None
    except (PlyParseError, ValueError, UnicodeDecodeError) as exc:
        raise DataError(f"{path} is not a PLY file that can be read ({exc})") from None
    elements = {element.name: element for element in data.elements}
    if "chunk" in elements:  # the compressed PLY: positions, rotations, scales and colours packed per chunk
        return _read_compressed_ply(path)
    if "vertex" not in elements:
        raise DataError(f"{path}: the header has no 'element vertex' line")
    table = elements["vertex"].data
    names = table.dtype.names or ()
    missing = [p for p in PROPERTIES if p not in names and not p.startswith("n")]
    if missing:
        raise DataError(f"{path}: not a Gaussian-splatting PLY (missing {', '.join(missing)})")
    if not all(np.isfinite(table[name]).all() for name in PROPERTIES if name in names):
        raise DataError(f"{path} holds NaN or infinite values: not a map a run saved")

    def cols(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(table[k], dtype=np.float32) for k in keys], axis=1))

    return Gaussians(
        means=cols("x", "y", "z"),
        quats=cols("rot_0", "rot_1", "rot_2", "rot_3"),
        log_scales=cols("scale_0", "scale_1", "scale_2"),
        opacity_logits=cols("opacity")[:, 0],
        colors=cols("f_dc_0", "f_dc_1", "f_dc_2") * SH_C0 + 0.5,
    )


def _read_compressed_ply(path: Path) -> Gaussians:
    """The compressed PLY (PlayCanvas's layout, as gsplat writes it), decoded by gsply."""
    import gsply

    try:
        data = gsply.plyread(path)
    except (ValueError, KeyError, IndexError) as exc:
        raise DataError(f"{path} is not a compressed PLY that can be read ({exc})") from None

    def tensor(values: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))

    columns = [tensor(data.means), tensor(data.quats), tensor(data.scales), tensor(data.opacities), tensor(data.sh0)]
    if not all(bool(torch.isfinite(c).all()) for c in columns):
        raise DataError(f"{path} holds NaN or infinite values: not a map a run saved")
    means, quats, log_scales, opacity_logits, sh0 = columns
    return Gaussians(means, quats, log_scales, opacity_logits.reshape(-1), sh0 * SH_C0 + 0.5)
