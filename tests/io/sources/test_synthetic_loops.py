"""The generated loop and trap sequences: a closed path back at its start every turn, and a
symmetric room whose twin places look alike from poses far apart."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.app.cli import main
from pipeline.config import SyntheticConfig
from pipeline.io.sources.datasets.synthetic import (
    TRAP_TURNS,
    closed_path_frames,
    default_intrinsics,
    loop_length,
    make_scene,
    render_view,
    synthetic_for,
    trajectory,
)

SIZE = (64, 48)


def test_the_closed_path_is_back_at_its_start_every_turn_and_sized_by_its_speed() -> None:
    config = SyntheticConfig(loops=3, speed=0.3, jitter=0.0)
    frames = closed_path_frames(config)
    assert 1500 < frames < 1800  # 3 turns of a ~5.7 m ellipse at 0.3 m/s and 30 frames/s
    poses = trajectory(config, frames)
    per_turn = (frames - 1) / 3
    for turn in range(1, 4):
        back = poses[round(turn * per_turn)]
        assert np.linalg.norm(back[:3, 3] - poses[0][:3, 3]) < 0.01  # metres: within a frame's step
        assert np.arccos(np.clip((np.trace(back[:3, :3].T @ poses[0][:3, :3]) - 1) / 2, -1, 1)) < math.radians(1)
    middle = poses[round(per_turn / 2)]
    assert np.linalg.norm(middle[:3, 3] - poses[0][:3, 3]) > 1.5  # half a turn on: across the room
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps.mean() * 30 == pytest.approx(0.3, rel=0.05)  # metres per second


def test_closed_paths_take_all_their_frames_unless_told_and_open_ones_keep_the_device_default() -> None:
    import torch

    cpu = torch.device("cpu")
    assert synthetic_for(SyntheticConfig(loops=2, speed=1.0), cpu).frames == closed_path_frames(
        SyntheticConfig(loops=2, speed=1.0)
    )
    assert synthetic_for(SyntheticConfig(loops=2, frames=50), cpu).frames == 50
    assert synthetic_for(SyntheticConfig(), cpu).frames == 20
    trap = SyntheticConfig(trap=True)
    assert closed_path_frames(trap) == round(closed_path_frames(SyntheticConfig(loops=1)) * TRAP_TURNS)


def _view(scene: object, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return render_view(scene, pose, default_intrinsics(*SIZE), *SIZE)  # type: ignore[arg-type]


def test_the_trap_room_shows_the_same_view_from_the_turned_pose_half_a_turn_on() -> None:
    config = SyntheticConfig(trap=True, jitter=0.0, speed=loop_length() * 30 / 100)  # 100 frames a turn
    poses = trajectory(config, closed_path_frames(config))
    scene, plain = make_scene(0, symmetric=True), make_scene(0)
    for k in (0, 10, 20):
        twin = k + 50
        assert np.linalg.norm(poses[k][:3, 3] - poses[twin][:3, 3]) > 1.5  # metres apart
        color, depth = _view(scene, poses[k])
        twin_color, twin_depth = _view(scene, poses[twin])
        assert np.abs(color.astype(int) - twin_color).mean() < 1  # of 255: the same picture
        assert np.median(np.abs(depth - twin_depth)) < 0.01
        other_color, _ = _view(scene, poses[k + 8])
        assert np.abs(color.astype(int) - other_color).mean() > 15
        plain_color, _ = _view(plain, poses[k])
        plain_twin, _ = _view(plain, poses[twin])
        assert np.abs(plain_color.astype(int) - plain_twin).mean() > 15  # the usual room has no twins


def test_the_synth_command_writes_loops_and_traps(tmp_path: Path) -> None:
    small = ["--width", "32", "--height", "24", "-q"]
    assert main(["synth", str(tmp_path / "loops"), "--loops", "1", "--speed", "3", *small]) == 0
    assert len(list((tmp_path / "loops" / "results").glob("frame*.jpg"))) == closed_path_frames(
        SyntheticConfig(loops=1, speed=3.0)
    )
    assert main(["synth", str(tmp_path / "trap"), "--trap", "--frames", "4", "--layout", "tum", *small]) == 0
    assert len((tmp_path / "trap" / "rgb.txt").read_text().splitlines()) == 2 + 4
    assert main(["synth", str(tmp_path / "bad"), "--loops", "-1", *small]) == 2
