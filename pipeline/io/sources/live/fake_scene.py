"""What a fake phone streams: a dataset folder, or the generated room at the iPhone LiDAR's size."""

from __future__ import annotations

from pathlib import Path

from pipeline.config import DatasetConfig, SyntheticConfig
from pipeline.io.sources.datasets.base import Dataset
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic_writer import cached_synthetic

# 256x192 is the iPhone LiDAR's depth resolution; 300 frames are 10 s at 30 frames/s.
FAKE_PHONE_SCENE = SyntheticConfig(frames=300, width=256, height=192)


def fake_phone_dataset(folder: str | None, cache: Path, progress: bool) -> Dataset:
    """The dataset in `folder`, or the generated room (cached under `cache`) when none is given."""
    path = folder or str(cached_synthetic(cache / "synthetic", FAKE_PHONE_SCENE, progress))
    return open_dataset(DatasetConfig(path=path))
