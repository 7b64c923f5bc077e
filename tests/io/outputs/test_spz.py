"""`export --to spz`: Niantic's SPZ through gsply, read back by gsply's own reader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import write_gt_run

from pipeline.app.cli import main
from pipeline.io.outputs.ply import SH_C0
from pipeline.io.outputs.run_folder import RunFolder

gsply = pytest.importorskip("gsply", reason="gsply is the spz extra (pip install -e '.[spz]'; the test extra has it)")


def test_spz_reads_back_as_the_maps_gaussians(tmp_path: Path) -> None:
    run = write_gt_run(tmp_path)
    assert main(["export", str(run), "--to", "spz"]) == 0
    back = gsply.read_spz(str(run / "map.spz"))
    gaussians = RunFolder(run).read_checkpoint()[0].gaussians
    assert len(back.means) == len(gaussians)
    assert np.abs(back.means - gaussians.means.numpy()).max() <= 2**-12  # 12 fractional bits
    colors = np.asarray(back.sh0) * SH_C0 + 0.5
    assert np.abs(colors - gaussians.colors.numpy()).max() <= 0.02  # 8 bits of SH DC
