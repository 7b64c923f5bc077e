"""Whole runs under faults: nothing processed is lost, every stop says where and why, and
`--resume` continues (or refuses, touching nothing)."""

from __future__ import annotations

import errno
import json
import os
import random
import shlex
import shutil
import signal
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import ROOT, SMALL_SYNTH, make_checkpoint, tamper_checkpoint
from live_helpers import wait_for

from pipeline.app.cli import main
from pipeline.app.report import gsplatam_command
from pipeline.config import load_config, to_toml, with_value
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.checkpoint import write_checkpoint
from pipeline.io.outputs.frame_row import FrameRow
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.render.types import Gaussians
from pipeline.slam.keyframes import Keyframe

QUICK = [
    "--preset",
    "tiny",
    "--set",
    "tracking.iters=2",
    "--set",
    "mapping.iters=2",
    "--quiet",
]  # the outcome, not the map


def _last_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    return err[-1]


def _metrics(folder: Path) -> dict[str, Any]:
    return json.loads((folder / "metrics.json").read_text())


def _frames_in(folder: Path) -> tuple[int, int, list[int]]:
    """(trajectory rows, checkpoint frames, frames.csv indices)"""
    rows = len(read_tum_trajectory(folder / "trajectory.txt")[0])
    checkpoint = RunFolder(folder).read_checkpoint()[0].frames_done
    indices = [int(line.split(",")[0]) for line in (folder / "frames.csv").read_text().splitlines()[1:]]
    return rows, checkpoint, indices


@pytest.mark.slow
def test_an_unreadable_late_frame_keeps_the_frames_before_it_and_resume_continues(
    replica_seq: Path, tmp_path: Path, capsys
) -> None:
    dataset = tmp_path / "room"
    shutil.copytree(replica_seq, dataset)
    good = (dataset / "results" / "frame000003.jpg").read_bytes()
    (dataset / "results" / "frame000003.jpg").write_bytes(b"truncated")
    out = tmp_path / "out"
    assert main(["run", str(dataset), "--output", str(out), "--name", "r", "--set", "run.eval_every=6", *QUICK]) == 2
    line = _last_error(capsys)
    assert "stage 'decode' failed on frame 3: unreadable image" in line and "frame000003.jpg" in line
    folder = out / "r"
    assert _frames_in(folder) == (3, 3, [0, 1, 2])  # every frame before the bad one, none lost
    stopped = _metrics(folder)["stopped"]
    assert stopped["stage"] == "decode" and stopped["frame"] == 3 and "frame000003.jpg" in stopped["reason"]

    (dataset / "results" / "frame000003.jpg").write_bytes(good)
    assert main(["run", "--resume", str(folder), "--quiet"]) == 0
    assert _frames_in(folder) == (6, 6, list(range(6)))
    metrics = _metrics(folder)
    assert metrics["frames"] == 6 and metrics["stopped"] is None and metrics["evaluation"] == "complete"


@pytest.mark.slow
def test_a_full_disk_mid_run_stops_it_and_says_so(
    replica_seq: Path, tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = RunFolder.append_frame

    def full_from_the_second_row(self: RunFolder, row: FrameRow) -> None:
        if row.index >= 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(self, row)

    monkeypatch.setattr(RunFolder, "append_frame", full_from_the_second_row)
    out = tmp_path / "out"
    assert main(["run", str(replica_seq), "--output", str(out), "--name", "full", *QUICK]) == 2
    assert "cannot write the row of frame 1 in frames.csv" in _last_error(capsys)
    folder = out / "full"
    metrics = _metrics(folder)
    said = (metrics["stopped"] or {}).get("reason") or metrics["write_error"]
    assert "No space left on device" in said
    rows, saved, indices = _frames_in(folder)
    assert rows == saved == metrics["frames"] >= 2 and indices == [0]
    assert [p.name for p in folder.iterdir() if p.name.endswith(".tmp")] == []


@pytest.mark.slow
@pytest.mark.parametrize("when", ["evaluation", "writing"])
def test_a_signal_after_slam_still_writes_every_output_and_exits_0(
    replica_seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys, when: str
) -> None:
    import pipeline.app.run as run_module
    from pipeline.io.outputs.periodic_save import PeriodicSave

    def signal_first(target: Any, name: str, sig: int) -> None:
        original = getattr(target, name)

        def wrapped(*args: Any, **kwargs: Any) -> Any:
            monkeypatch.setattr(target, name, original)
            os.kill(os.getpid(), sig)  # delivered at once, to this (main) thread
            return original(*args, **kwargs)

        monkeypatch.setattr(target, name, wrapped)

    if when == "evaluation":
        signal_first(run_module, "view_quality", signal.SIGTERM)
    else:
        signal_first(PeriodicSave, "save_now", signal.SIGINT)
    out = tmp_path / "out"
    argv = ["run", str(replica_seq), "--output", str(out), "--name", "s", "--set", "run.eval_every=2", *QUICK]
    assert main(argv) == 0
    folder = out / "s"
    resume = f"{gsplatam_command()} run --resume {shlex.quote(str(folder))}"
    assert f"interrupted: continue with  {resume}" in capsys.readouterr().out
    metrics = _metrics(folder)
    assert metrics["frames"] == 6 and metrics["interrupted"] is True and _frames_in(folder)[:2] == (6, 6)
    evaluated = 1 if when == "evaluation" else 0  # a signal while writing: the files, then no evaluation
    assert metrics["evaluation"] == f"cut short by a signal after {evaluated} of 3 frames"
    assert (metrics["render"] or {}).get("frames_evaluated") == (evaluated or None)
    assert main(["run", "--resume", str(folder), "--quiet"]) == 0  # no SLAM left: the evaluation is finished
    metrics = _metrics(folder)
    assert metrics["evaluation"] == "complete" and metrics["render"]["frames_evaluated"] == 3
    assert metrics["frames"] == 6 and metrics["frames_this_run"] == 0 and _frames_in(folder)[2] == list(range(6))
    assert main(["run", "--resume", str(folder), "--quiet"]) == 2  # complete now


@pytest.mark.slow
def test_a_killed_run_keeps_its_periodic_save_and_resumes_from_it(tmp_path: Path) -> None:
    sequence, out, log_path = tmp_path / "seq", tmp_path / "out", tmp_path / "run.log"
    write_synthetic(sequence, replace(SMALL_SYNTH, frames=8), progress=False)  # enough frames to be killed midway
    saves = ["--set", "run.save_every_s=0.001", "--set", "run.eval_every=8"]
    argv = ["run", str(sequence), "--output", str(out), "--name", "k", *saves, *QUICK]
    with open(log_path, "w") as log_file:
        command = [sys.executable, "-m", "pipeline", *argv]
        proc = subprocess.Popen(command, env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT, stderr=log_file)
    folder = out / "k"

    def saved_and_going_on() -> bool:
        rows = len((folder / "frames.csv").read_text().splitlines()) if (folder / "frames.csv").exists() else 0
        return proc.poll() is not None or ((folder / "checkpoint.safetensors").exists() and rows > 2)

    wait_for(saved_and_going_on, 240, "a periodic save", log_path)
    proc.kill()  # SIGKILL: nothing runs after it
    proc.wait()
    saved = RunFolder(folder).read_checkpoint()[0].frames_done
    assert 1 <= saved < 8 and not (folder / "metrics.json").exists()
    # each file complete; the checkpoint is replaced last, so a kill between two replacements
    # leaves the trajectory one save ahead of it, never behind
    assert len(read_tum_trajectory(folder / "trajectory.txt")[0]) >= saved
    assert main(["run", "--resume", str(folder), "--quiet"]) == 0
    assert _frames_in(folder) == (8, 8, list(range(8)))  # frames.csv rows after the save were dropped, not doubled
    assert _metrics(folder)["frames_this_run"] == 8 - saved


def _resumable_folder(tmp_path: Path, dataset: Path, run_info: dict[str, Any], keyframe_size: tuple[int, int]) -> Path:
    """A run folder as a run over `dataset` leaves it, with a small checkpoint of 2 frames."""
    folder = tmp_path / "run"
    folder.mkdir()
    config = with_value(load_config("tiny"), "dataset.path", str(dataset))
    (folder / "config.toml").write_text(to_toml(config))
    n, (width, height) = 5, keyframe_size
    keyframe = Keyframe(0, torch.zeros(height, width, 3, dtype=torch.uint8), torch.ones(height, width), torch.eye(4))
    gaussians = Gaussians(torch.zeros(n, 3), torch.ones(n, 4), torch.zeros(n, 1), torch.zeros(n), torch.rand(n, 3))
    checkpoint = make_checkpoint(gaussians, [keyframe], torch.eye(4).repeat(2, 1, 1))
    write_checkpoint(folder / "checkpoint.safetensors", checkpoint, RunDescription.from_json(run_info))
    return folder


SAME = {"source": "room", "live": False, "gaussians": "3d", "isotropic": True, "format": "replica",
        "size": [64, 48], "start": 0, "stride": 1}  # fmt: skip


@pytest.mark.parametrize(
    "run_info, keyframe_size, argv, message",
    [
        ({**SAME, "source": "kitchen"}, (64, 48), [], "was run with dataset 'kitchen', this run has 'room'"),
        (SAME, (64, 48), ["--set", "dataset.width=32", "--set", "dataset.height=24"],
         "was run with frame size (width, height) 64x48, this run has 32x24"),
        (SAME, (64, 48), ["--set", "gaussians.kind=2d"], "was run with Gaussian kind (gaussians.kind) '3d', this run has '2d'"),
        (SAME, (64, 48), ["--set", "dataset.stride=2"], "was run with dataset.stride 1, this run has 2"),
        ({**SAME, "live": True, "source": "record3d"}, (64, 48), [], "is a live run (record3d): --resume continues dataset runs only"),
        ({"source": "room", "live": False, "gaussians": "3d"}, (32, 24), [], "holds keyframes of 32x24, this run's frames are 64x48"),
        ("empty", (64, 48), [], "is not a readable checkpoint"),
        ("random", (64, 48), [], "is not a readable checkpoint"),
        ("truncated", (64, 48), [], "is not a readable checkpoint"),
    ],
)  # fmt: skip
def test_resume_refuses_another_run_touching_nothing(
    replica_seq: Path,
    tmp_path: Path,
    capsys,
    run_info: Any,
    keyframe_size: tuple[int, int],
    argv: list[str],
    message: str,
) -> None:
    folder = _resumable_folder(tmp_path, replica_seq, run_info if isinstance(run_info, dict) else SAME, keyframe_size)
    checkpoint = folder / "checkpoint.safetensors"
    if run_info == "empty":
        checkpoint.write_bytes(b"")
    elif run_info == "random":
        checkpoint.write_bytes(random.Random(1).randbytes(4096))
    elif run_info == "truncated":
        checkpoint.write_bytes(checkpoint.read_bytes()[: checkpoint.stat().st_size // 2])
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.iterdir()}
    assert main(["run", "--resume", str(folder), "--device", "cpu", "--quiet", *argv]) == 2
    line = _last_error(capsys)
    assert line.startswith("gsplatam: error: ") and message in line and str(folder) in line
    after = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.iterdir() if p.name != ".lock"}
    assert after == before  # config.toml not rewritten, nothing else written


@pytest.mark.parametrize("change", ["int32", "one axis fewer", "nan"])
def test_resume_refuses_a_checkpoint_of_tampered_tensors_touching_nothing(
    replica_seq: Path, tmp_path: Path, capsys, change: str
) -> None:
    folder = _resumable_folder(tmp_path, replica_seq, SAME, (64, 48))
    tamper_checkpoint(folder / "checkpoint.safetensors", "gaussians.means", change)
    (folder / "frames.csv").write_text("earlier rows\n")
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.iterdir()}
    assert main(["run", "--resume", str(folder), "--device", "cpu", "--quiet"]) == 2
    line = _last_error(capsys)
    assert f"{folder / 'checkpoint.safetensors'} is not a gsplatam checkpoint" in line and "gaussians.means" in line
    after = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in folder.iterdir() if p.name != ".lock"}
    assert after == before  # config.toml and frames.csv not rewritten


def test_a_resumable_folder_of_the_same_run_passes_the_checks(replica_seq: Path, tmp_path: Path) -> None:
    from pipeline.app.resume import read_resumable

    folder = RunFolder(_resumable_folder(tmp_path, replica_seq, SAME, (64, 48)))
    assert read_resumable(folder, RunDescription.from_json(SAME), frames=6).frames_done == 2
    folder.metrics.write_text(json.dumps({"evaluation": "complete"}))
    assert read_resumable(folder, RunDescription.from_json(SAME), frames=3).frames_done == 2
