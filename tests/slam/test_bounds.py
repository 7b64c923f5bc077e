"""Bounded memory for long sessions: the keyframe store and the map stay under their limits."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from pipeline.config import DatasetConfig, load_config, with_dataset_defaults
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.render import make_renderer
from pipeline.slam.keyframes import most_redundant
from pipeline.slam.splatam import SplaTAM
from pipeline.stages.upload import host_frame_tensors

CPU = torch.device("cpu")


def _pose(x: float, yaw: float = 0.0) -> torch.Tensor:
    pose = torch.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    pose[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    pose[0, 3] = x
    return pose


def test_the_most_redundant_keyframe_is_the_one_nearest_its_successor() -> None:
    poses = torch.stack([_pose(0.0), _pose(0.5), _pose(0.51), _pose(1.0), _pose(1.5), _pose(1.501)])
    assert most_redundant(poses, protected_newest=2) == 1  # 1 cm from its successor; 5 is protected
    turned = torch.stack([_pose(0.0), _pose(0.5), _pose(0.51, yaw=1.0), _pose(1.0), _pose(1.02), _pose(2.0)])
    assert most_redundant(turned, protected_newest=1) == 3  # 2 cm; keyframe 1's successor turned 57 degrees
    with pytest.raises(ValueError):
        most_redundant(poses[:3], protected_newest=2)


@pytest.mark.slow
def test_keyframes_and_map_stay_bounded_over_a_long_looping_stream(replica_seq: Path) -> None:
    """The 6-frame room looped 5 times with a keyframe every frame: at most 4 keyframes and a
    map of at most 3000 Gaussians after every frame (the first frame alone seeds ~3000)."""
    overrides = ["tracking.iters=2", "mapping.iters=2", "keyframes.every=1", "keyframes.max_kept=4"]
    config = with_dataset_defaults(load_config("tiny", overrides=overrides + ["mapping.max_gaussians=3000"]), "replica")
    slam = SplaTAM(config, make_renderer(config.render, config.gaussians, CPU), CPU)
    frames = [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(replica_seq))).frames()]
    sizes = []
    for loop in range(5):
        for frame in frames:
            frame.index = loop * len(frames) + frame.index % len(frames)
            slam.step(frame)
            assert slam.gaussians is not None
            sizes.append((len(slam.backend.keyframes), len(slam.gaussians)))
    assert max(k for k, _ in sizes) == 4 and max(g for _, g in sizes) <= 3000
    assert min(g for _, g in sizes) >= 1000  # cut to 90% of the bound when past it, never emptied
