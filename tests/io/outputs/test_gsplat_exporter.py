"""gsplat's exporter (`gsplat.exporter.export_splats`) against the project's own writers: the
compressed PLY is gsplat's, read back by plyfile and decoded here; the 3DGS PLY and `.splat`
stay the project's, and these tests show why (what gsplat's writer cannot write, and its order)."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import write_gt_run

from pipeline.app.cli import main
from pipeline.io.outputs.exports.splat import SPLAT_RECORD, splat_bytes
from pipeline.io.outputs.ply import SH_C0, gaussian_ply_bytes
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.render.types import Gaussians

plyfile = pytest.importorskip("plyfile", reason="plyfile is a test dependency (pip install -e '.[test]')")


@pytest.fixture(scope="module")
def gaussians(tmp_path_factory: pytest.TempPathFactory) -> Gaussians:
    return RunFolder(write_gt_run(tmp_path_factory.mktemp("gsplat"))).read_checkpoint()[0].gaussians


def _gsplat(gaussians: Gaussians, fmt: str) -> bytes:
    from gsplat.exporter import export_splats

    n = len(gaussians)
    sh0 = ((gaussians.colors - 0.5) / SH_C0)[:, None, :]
    scales = gaussians.log_scales.expand(-1, 3)
    return export_splats(
        gaussians.means, scales, gaussians.quats, gaussians.opacity_logits, sh0, torch.zeros(n, 0, 3), fmt
    )


def _unorm(packed: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((packed >> shift) & ((1 << bits) - 1)) / ((1 << bits) - 1)


def test_gsplats_exporter_loads_no_cuda_code() -> None:
    """In a fresh interpreter: importing it builds and loads none of gsplat's CUDA extension."""
    probe = (
        "import sys, gsplat.exporter; print('gsplat.csrc' in sys.modules, 'torch.utils.cpp_extension' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False", "False"]


def test_the_compressed_ply_holds_the_maps_positions_in_chunks_of_256(tmp_path: Path) -> None:
    run = write_gt_run(tmp_path)
    assert main(["export", str(run), "--to", "compressed-ply"]) == 0
    ply = plyfile.PlyData.read(str(run / "map.compressed.ply"))
    chunks, vertices = ply["chunk"], ply["vertex"]
    means = RunFolder(run).read_checkpoint()[0].gaussians.means.numpy()
    assert len(vertices) == len(means) and len(chunks) == -(-len(means) // 256)  # every one is opaque enough
    packed = vertices["packed_position"].astype(np.int64)
    low = np.stack([chunks[f"min_{a}"] for a in "xyz"], 1).repeat(256, 0)[: len(packed)]
    high = np.stack([chunks[f"max_{a}"] for a in "xyz"], 1).repeat(256, 0)[: len(packed)]
    unit = np.stack([_unorm(packed, 21, 11), _unorm(packed, 11, 10), _unorm(packed, 0, 11)], 1)
    decoded = low + unit * (high - low)
    nearest = torch.cdist(torch.from_numpy(decoded).float(), torch.from_numpy(means)).min(dim=1).values
    assert float(nearest.max()) <= float((high - low).max()) / 1023  # within a quantisation step


def test_gsplats_ply_is_the_maps_layout_without_normals_which_the_full_ply_needs(gaussians: Gaussians) -> None:
    ours = plyfile.PlyData.read(io.BytesIO(gaussian_ply_bytes(gaussians)))["vertex"]
    theirs = plyfile.PlyData.read(io.BytesIO(_gsplat(gaussians, "ply")))["vertex"]
    names = [p.name for p in theirs.properties]
    assert [p.name for p in ours.properties if p.name not in ("nx", "ny", "nz")] == names
    assert all(np.array_equal(ours[name], theirs[name]) for name in names)  # the same values
    assert not {"nx", "ny", "nz"} & set(names)  # it has no way to write the surface normals of map_3dgs.ply


def test_gsplats_splat_has_the_same_records_in_morton_order_not_most_visible_first(gaussians: Gaussians) -> None:
    ours = np.frombuffer(splat_bytes(gaussians), dtype=SPLAT_RECORD)
    theirs = np.frombuffer(_gsplat(gaussians, "splat"), dtype=SPLAT_RECORD)
    assert np.array_equal(np.sort(ours["position"], axis=0), np.sort(theirs["position"], axis=0))
    visibility = np.prod(theirs["scale"], axis=1) * theirs["rgba"][:, 3]
    assert not np.all(np.diff(visibility) <= 0)  # theirs: not most visible first, which viewers stream
    visible = np.prod(ours["scale"], axis=1) * ours["rgba"][:, 3]
    assert np.all(np.diff(visible.astype(np.float64)) <= 1e-6 * visible.max())
