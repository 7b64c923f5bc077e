"""Whole runs with loop closure on (`loops.enabled`), both schedules: the outcome in
metrics.json, the pose graph in g2o's format that GTSAM reads back, the trajectory as tracked
beside the corrected one, and a checkpoint that carries loop closure's state through a resume.

A whole run on the CPU is too small and slow to show a loop accepted (that is
tests/slam/test_loop_closure.py's, on drifted keyframes); these check the plumbing."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from pipeline.app.cli import main
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.run_folder import RunFolder

gtsam = pytest.importorskip("gtsam")
LOOPS = ["--preset", "tiny", "--set", "loops.enabled=true", "--set", "keyframes.every=2", "--quiet"]


@pytest.fixture(scope="module")
def loop_room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("loops") / "room"
    synth = ["--layout", "tum", "--width", "64", "--height", "48", "--loops", "1", "--speed", "1.0", "--fps", "6"]
    assert main(["synth", str(path), *synth, "--depth-noise", "0.0015", "--holes", "0.02", "--quiet"]) == 0
    return path


@pytest.mark.slow
@pytest.mark.parametrize("schedule", ["sequential", "process"])
def test_a_run_with_loop_closure_writes_its_outcome_graph_and_both_trajectories(
    loop_room: Path, tmp_path: Path, schedule: str
) -> None:
    argv = [
        "run",
        str(loop_room),
        "--output",
        str(tmp_path),
        "--name",
        "r",
        *LOOPS,
        "--set",
        f"slam.schedule={schedule}",
    ]
    assert main(argv) == 0
    folder = RunFolder(tmp_path / "r")
    metrics = json.loads(folder.metrics.read_text())
    loops = metrics["loops"]
    assert loops["detected"] == loops["accepted"] + loops["rejected"] >= loops["verified"] - loops["unconfirmed"]
    assert loops["rejected"] == loops["failed_verification"] + loops["unconfirmed"] + loops["dropped_by_graph"]
    assert len(loops["closed"]) <= loops["accepted"]
    assert metrics["ate_as_tracked"]["frames"] == metrics["ate"]["frames"] == 35

    checkpoint, _ = folder.read_checkpoint()
    state = checkpoint.mapping.loops
    assert state is not None and len(state.creator) == len(checkpoint.gaussians)
    assert state.node_positions == [k.position for k in checkpoint.keyframes]  # a node per keyframe, none dropped
    assert set(state.creator.tolist()) <= set(range(len(state.node_positions)))
    tracked = checkpoint.tracking.tracked_poses
    assert tracked is not None and tracked.shape == checkpoint.poses.shape
    times, poses = read_tum_trajectory(folder.trajectory_as_tracked)
    assert len(times) == 35 and torch.allclose(torch.from_numpy(poses).float(), tracked, atol=1e-6)

    graph, initial = gtsam.readG2o(str(folder.pose_graph), True)
    assert initial.size() == len(state.node_positions) and graph.size() == len(state.node_positions) - 1 + len(
        state.loops
    )
    for node, position in enumerate(state.node_positions):  # the graph's nodes are the keyframes' poses
        expected = checkpoint.poses[position].double()
        assert torch.allclose(torch.from_numpy(initial.atPose3(node).matrix()), expected, atol=1e-5)


@pytest.mark.slow
def test_loop_closure_state_survives_a_resume(loop_room: Path, tmp_path: Path) -> None:
    first = ["run", str(loop_room), "--output", str(tmp_path), "--name", "r", *LOOPS, "--set", "dataset.end=20"]
    assert main(first) == 0
    before = RunFolder(tmp_path / "r").read_checkpoint()[0].mapping.loops
    assert before is not None
    assert main(["run", "--resume", str(tmp_path / "r"), "--set", "dataset.end=-1", "--quiet"]) == 0
    after = RunFolder(tmp_path / "r").read_checkpoint()[0]
    state = after.mapping.loops
    assert state is not None and after.frames_done == 35
    assert state.node_positions[: len(before.node_positions)] == before.node_positions
    assert len(state.node_positions) > len(before.node_positions)
    assert state.tally.detected >= before.tally.detected


def test_loop_closure_without_gtsam_is_one_line_naming_the_extra(
    loop_room: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "gtsam", None)  # `import gtsam` fails as if it were not installed
    assert main(["run", str(loop_room), "--output", str(tmp_path), "--name", "r", *LOOPS]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "gtsam" in error[0] and "'loops' extra" in error[0]
    assert not (tmp_path / "r").exists()  # refused before anything was written
