from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from pipeline.config import SyntheticConfig
from pipeline.io.synth_writer import write_synthetic

torch.set_num_threads(2)

SHARED_TUM = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "tum_fr1_xyz_37"
SMALL_SYNTH = SyntheticConfig(frames=6, width=64, height=48, seed=3)


@pytest.fixture(scope="session")
def replica_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replica") / "room"
    write_synthetic(path, SMALL_SYNTH, progress=False)
    return path


@pytest.fixture(scope="session")
def tum_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("tum") / "room"
    write_synthetic(path, replace(SMALL_SYNTH, layout="tum"), progress=False)
    return path


@pytest.fixture
def tum_sample() -> Path:
    if not (SHARED_TUM / "rgb.txt").exists():
        pytest.skip(f"the shared TUM sample is absent ({SHARED_TUM})")
    return SHARED_TUM
