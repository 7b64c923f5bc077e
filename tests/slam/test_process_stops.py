"""How a run under the process schedule stops, as users stop it and as it breaks: signals to the
whole process group (a terminal's Ctrl-C, `timeout`, a service manager), Ctrl-Z then fg, the
mapping process killed mid-run or during the final refinement, the parent killed, a small
/dev/shm. Each time: the exit code, the line, and a run folder whose checkpoint, trajectory,
frames.csv and metrics.json agree, which --resume continues.

Each run starts in a session of its own (its own process group, which the test signals) and is
killed with its group at the end whatever happens; waits poll files and log lines with generous
timeouts, never wall-clock speed.
"""

from __future__ import annotations

import csv
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import torch
from conftest import ROOT, SMALL_SYNTH
from live_helpers import spawned_children, wait_for

from pipeline.app.cli import main
from pipeline.config import DatasetConfig, load_config, with_dataset_defaults
from pipeline.errors import MappingProcessFailed
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.slam.process import messages as m
from pipeline.slam.process.client import MappingProcess
from pipeline.slam.process.schedule import ProcessSplaTAM, start_process_slam
from pipeline.slam.process.shared_map import MapReader, SharedMemoryShort, shared_memory_advice
from pipeline.stages.upload import host_frame_tensors

CPU = torch.device("cpu")
FAST = ["tracking.iters=2", "mapping.iters=2", "run.eval_every=100"]
FRAMES = 30
WAIT_S = 300  # generous: two cores shared with other test workers


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """30 frames of 32x24 (quick to generate): enough that a signal after the first few lands mid-run."""
    path = tmp_path_factory.mktemp("stops") / "room"
    write_synthetic(path, replace(SMALL_SYNTH, frames=FRAMES, width=32, height=24), progress=False)
    return path


class Run:
    """`gsplatam run` in a session of its own, its log in a file; killed with its group on exit."""

    def __init__(self, argv: list[str], log: Path) -> None:
        self.log = log
        with open(log, "w") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "pipeline", *argv], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip

    def wait_for(self, ready: Any, what: str) -> None:
        wait_for(lambda: ready() or self.proc.poll() is not None, WAIT_S, what, self.log)
        assert self.proc.poll() is None, f"the run ended before {what}:\n{self.log.read_text()[-3000:]}"

    def signal_group(self, sig: int) -> None:
        os.killpg(self.proc.pid, sig)

    def mapping_pid(self) -> int:
        """The mapping process: the spawned child of the run (not multiprocessing's resource tracker)."""
        self.wait_for(lambda: len(spawned_children(self.proc.pid)) == 1, "the mapping process")
        (pid,) = spawned_children(self.proc.pid)
        return pid

    def ended(self) -> int:
        return self.proc.wait(WAIT_S)

    def said(self) -> str:
        return self.log.read_text()

    def close(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.fixture
def runs() -> Iterator[list[Run]]:
    started: list[Run] = []
    yield started
    for run in started:
        run.close()


def _start(runs: list[Run], room: Path, out: Path, sets: list[str], name: str = "r") -> Run:
    argv = ["run", str(room), "--preset", "tiny", "--device", "cpu", "--quiet", "--output", str(out), "--name", name,
            *[f"--set={s}" for s in ["slam.schedule=process", *FAST, *sets]]]  # fmt: skip
    runs.append(Run(argv, out.parent / f"{name}.log"))
    return runs[-1]


def _rows(folder: Path) -> int:
    csv = folder / "frames.csv"
    return len(csv.read_text().splitlines()) - 1 if csv.exists() else 0


def _consistent(folder: Path) -> dict[str, Any]:
    """metrics.json, once checkpoint, trajectory and frames.csv (one row per frame, in order)
    are seen to hold the same frames as it."""
    metrics = json.loads((folder / "metrics.json").read_text())
    checkpoint = RunFolder(folder).read_checkpoint()[0].frames_done
    trajectory = len(read_tum_trajectory(folder / "trajectory.txt")[0])
    indices = [int(line.split(",")[0]) for line in (folder / "frames.csv").read_text().splitlines()[1:]]
    assert checkpoint == trajectory == metrics["frames"] and indices == list(range(checkpoint)), (
        checkpoint, trajectory, metrics["frames"], indices,
    )  # fmt: skip
    assert [p.name for p in folder.iterdir() if p.name.endswith(".tmp")] == []
    return metrics


def _resumed(folder: Path, frames: int) -> None:
    assert main(["run", "--resume", str(folder), "--device", "cpu", "--quiet"]) == 0
    metrics = _consistent(folder)
    assert metrics["frames"] == frames and metrics["stopped"] is None


@pytest.mark.slow
@pytest.mark.parametrize(
    "sig, save_every_s", [(signal.SIGINT, "0.2"), (signal.SIGTERM, "1e9")], ids=["sigint-saved", "sigterm-unsaved"]
)
def test_a_stop_signal_to_the_group_saves_every_frame_and_exits_0(
    runs: list[Run], room: Path, tmp_path: Path, sig: int, save_every_s: str
) -> None:
    """Ctrl-C (after a periodic save) or systemctl stop (before the first) to the whole group:
    the mapping process ignores it, the parent stops, mapping finishes what it holds, every
    frame processed is saved and the run exits 0; --resume continues to the end."""
    out = tmp_path / "out"
    run = _start(runs, room, out, [f"run.save_every_s={save_every_s}"])
    folder = out / "r"
    saved = (lambda: (folder / "checkpoint.safetensors").exists()) if save_every_s == "0.2" else (lambda: True)
    run.wait_for(lambda: _rows(folder) >= 3 and saved(), "frames processed")
    mapping = run.mapping_pid()
    run.signal_group(sig)
    assert run.ended() == 0, run.said()[-3000:]
    assert "Traceback" not in run.said() and "interrupted: continue with" in run.said()
    metrics = _consistent(folder)
    assert metrics["interrupted"] is True and metrics["stopped"] is None and 3 <= metrics["frames"] < FRAMES
    handed = [row["mapped"] == "1" for row in csv.DictReader((folder / "frames.csv").open())]
    assert metrics["mapping_process"]["frames_mapped"] == sum(handed)  # mapping finished what it was handed
    assert not _alive(mapping)
    if sig == signal.SIGINT:
        _resumed(folder, FRAMES)


@pytest.mark.slow
def test_the_mapping_process_killed_during_the_final_refinement_leaves_every_frame(
    runs: list[Run], room: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    run = _start(runs, room, out, ["dataset.end=6", "mapping.final_iters=100000", "run.save_every_s=1e9"])
    run.wait_for(lambda: "final refinement: 100000 view renders" in run.said(), "the final refinement")
    os.kill(run.mapping_pid(), signal.SIGKILL)
    assert run.ended() == 1
    said = run.said()
    last = said.strip().splitlines()[-1]
    assert "Traceback" not in said and last.startswith("gsplatam: error: the mapping process ended unexpectedly")
    assert "saved 6 of the 6 frames processed" in said and "--resume" in said
    folder = out / "r"
    metrics = _consistent(folder)
    assert metrics["frames"] == 6 and metrics["stopped"]["frames_saved"] == 6
    _resumed(folder, 6)  # no frame left: it evaluates


@pytest.mark.slow
@pytest.mark.parametrize("schedule", ["process", "sequential"])
def test_a_signal_cuts_the_final_refinement_short(runs: list[Run], room: Path, tmp_path: Path, schedule: str) -> None:
    """SIGINT during mapping.final_iters=100000 (hours on this CPU): the refinement ends at its
    next step, the outputs are written, exit 0."""
    out = tmp_path / "out"
    run = _start(runs, room, out, ["dataset.end=6", "mapping.final_iters=100000", f"slam.schedule={schedule}"])
    run.wait_for(lambda: "final refinement: 100000 view renders" in run.said(), "the final refinement")
    run.signal_group(signal.SIGINT)
    assert run.ended() == 0, run.said()[-3000:]
    assert "final refinement cut short by a signal after" in run.said()
    metrics = _consistent(out / "r")
    assert metrics["frames"] == 6 and metrics["interrupted"] is True


@pytest.mark.slow
def test_the_mapping_process_ends_with_its_parent_even_by_kill_9(runs: list[Run], room: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    run = _start(runs, room, out, [])
    run.wait_for(lambda: _rows(out / "r") >= 1, "a frame processed")
    mapping = run.mapping_pid()
    run.proc.kill()  # the parent alone
    run.proc.wait()
    wait_for(lambda: not _alive(mapping), WAIT_S, "the orphaned mapping process to end", run.log)


@pytest.mark.slow
def test_ctrl_z_then_fg_longer_than_the_timeout_leaves_a_healthy_run_going(
    runs: list[Run], room: Path, tmp_path: Path
) -> None:
    """SIGSTOP then SIGCONT to the group (Ctrl-Z, fg; a suspended laptop) for longer than
    slam.backend_timeout_s: the time the parent was stopped itself is not the mapping process's
    silence."""
    out = tmp_path / "out"
    run = _start(runs, room, out, ["dataset.end=12", "slam.backend_timeout_s=2"])
    run.wait_for(lambda: _rows(out / "r") >= 2, "frames processed")
    run.signal_group(signal.SIGSTOP)
    time.sleep(6)  # three times the timeout, stopped
    run.signal_group(signal.SIGCONT)
    assert run.ended() == 0, run.said()[-3000:]
    assert _consistent(out / "r")["frames"] == 12


def _process_slam(overrides: list[str], live: bool) -> ProcessSplaTAM:
    config = with_dataset_defaults(load_config("tiny", overrides=FAST + overrides), "replica")
    return start_process_slam(config, CPU, live)


@pytest.mark.slow
def test_live_the_first_frames_step_ends_with_its_map_and_a_failed_mapping_process_costs_no_tracked_frame(
    replica_seq: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Live, the first frame's step ends once its map is published (the next frame taken is the
    newest, as under sequential). A map that outgrows /dev/shm fails the mapping process with the
    advice; the frame in hand completes, the next is refused before it is tracked, and the
    checkpoint holds every frame tracked with the last complete map."""
    frames = [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(replica_seq))).frames()][:3]
    slam = _process_slam([], live=True)
    try:
        slam.step(frames[0])
        assert slam.mapping.newest_version() >= 1  # published before the step returned
        slam.step(frames[1])

        def short(self: MapReader, capacity: int, keyframe_capacity: int) -> None:
            raise SharedMemoryShort(shared_memory_advice(capacity * 48))

        monkeypatch.setattr(MapReader, "grow", short)
        slam.mapping._dispatch(m.GrowMap(10**6, 100))
        assert "/dev/shm" in slam.failure and "slam.schedule=sequential" in slam.failure
        with pytest.raises(MappingProcessFailed, match="outgrew the shared memory"):
            slam.step(frames[2])
        assert slam.finish(0) == 0
        checkpoint = slam.checkpoint()
        assert checkpoint.frames_done == 2 and len(checkpoint.gaussians) > 0
    finally:
        slam.close()


@pytest.mark.slow
def test_a_live_session_whose_mapping_process_dies_saves_every_frame_and_does_not_advise_resume(
    replica_seq: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """serve under process, the mapping process killed after 3 frames: every frame processed is
    in checkpoint, trajectory, frames.csv and metrics.json (stopped), and the line says that a
    live session is not continued with --resume (which refuses live folders)."""
    import logging
    import multiprocessing

    from pipeline.app import serve as serve_module
    from pipeline.app.setup import LIVE_LAYOUT, finish_config
    from pipeline.errors import StageFailure
    from pipeline.io.sources.datasets.source import DatasetSource
    from pipeline.stages.sinks import ResultSink

    consume = ResultSink.consume

    def consume_then_kill(self: ResultSink, result: Any) -> None:
        consume(self, result)
        if len(self.log.results) == 3:
            (process,) = [p for p in multiprocessing.active_children() if p.name == "gsplatam-mapping"]
            os.kill(process.pid, signal.SIGKILL)

    monkeypatch.setattr(ResultSink, "consume", consume_then_kill)
    settings = [f"run.output={tmp_path}", "run.name=live", "run.device=cpu", "live.status_port=0",
                "slam.schedule=process", *FAST]  # fmt: skip
    setup = finish_config(load_config("tiny", overrides=settings), CPU, LIVE_LAYOUT, live=True)
    source = DatasetSource(open_dataset(DatasetConfig(path=str(replica_seq))))
    with caplog.at_level(logging.INFO, "gsplatam"), pytest.raises((StageFailure, MappingProcessFailed)) as failed:
        serve_module.serve(setup, source, progress=False)
    assert "the mapping process ended unexpectedly" in str(failed.value)
    metrics = _consistent(tmp_path / "live")
    assert metrics["frames"] >= 3 and metrics["stopped"]["frames_saved"] == metrics["frames"]
    said = [r.getMessage() for r in caplog.records if "frames processed" in r.getMessage()]
    assert said and "not continued with --resume" in said[-1] and "--resume " not in said[-1]
    caplog.clear()
    with caplog.at_level(logging.INFO, "gsplatam"):  # refused at once: no room generated for it first
        assert main(["run", "--resume", str(tmp_path / "live"), "--quiet", "--output", str(tmp_path)]) == 2
    assert "is a live run" in capsys.readouterr().err and "synthetic room" not in caplog.text


@pytest.mark.slow
def test_a_second_signal_stops_waiting_for_a_stopped_mapping_process_and_keeps_what_is_complete(
    replica_seq: Path,
) -> None:
    """The mapping process stopped (SIGSTOP) with a frame handed to it: after stop_waiting (what a
    second signal calls) nothing waits for it any more; the checkpoint holds every frame tracked,
    the map lacks the frame it never took, and it is no failure (the user asked)."""
    frames = [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(replica_seq))).frames()][:3]
    slam = _process_slam([], live=False)
    try:
        for frame in frames[:2]:
            slam.step(frame)
        slam.finish(0)  # mapping took both
        os.kill(slam.mapping.process.pid, signal.SIGSTOP)
        slam.step(frames[2], is_last=True)  # a keyframe at either rate, handed over into a free slot, never taken
        assert slam.unmapped() == [2]
        slam.stop_waiting()
        assert slam.finish(0) == 0
        checkpoint = slam.checkpoint()
        assert checkpoint.frames_done == 3 and slam.failure == ""
    finally:
        slam.close()  # kills the stopped process


def test_a_backend_timeout_of_0_is_refused_before_anything_is_written(
    replica_seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["run", str(replica_seq), "--output", str(tmp_path / "out"), "--quiet", "--set", "slam.backend_timeout_s=0"]
    assert main(argv) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "slam.backend_timeout_s must be > 0" in line and not (tmp_path / "out").exists()


def test_a_small_dev_shm_is_one_line_saying_what_to_do(
    replica_seq: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.slam.process import shared_map

    monkeypatch.setattr(shared_map, "shared_memory_free", lambda: 64 * 1024)  # a container's 64 KiB
    out = tmp_path / "out"
    argv = ["run", str(replica_seq), "--output", str(out), "--name", "r", "--quiet", "--set", "slam.schedule=process"]
    assert main(argv) == 2
    (line,) = [line for line in capsys.readouterr().err.strip().splitlines() if "error" in line]
    assert "/dev/shm, which has 0.1 MiB free; it needs" in line and "--shm-size" in line
    assert "slam.schedule=sequential" in line and not (out / "r").exists()


@pytest.mark.slow
def test_a_real_small_dev_shm_in_a_mount_namespace(runs: list[Run], replica_seq: Path, tmp_path: Path) -> None:
    """A 4 MiB /dev/shm mounted in a namespace of the test's own (where unprivileged namespaces
    are allowed): the check, not torch's allocator, says it."""
    if shutil.which("unshare") is None:
        pytest.skip("unshare is not installed")
    probe = subprocess.run(["unshare", "-Urm", "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no unprivileged mount namespace here: {probe.stderr.decode().strip()}")
    command = (
        f"mount -t tmpfs -o size=4m tmpfs /dev/shm && exec {sys.executable} -m pipeline run {replica_seq} "
        f"--output {tmp_path / 'out'} --name r --quiet --set slam.schedule=process"
    )
    done = subprocess.run(
        ["unshare", "-Urm", "sh", "-c", command], env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True, text=True, timeout=WAIT_S,
    )  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert "/dev/shm, which has 4.0 MiB free" in done.stderr.strip().splitlines()[-1]


def test_a_mapping_side_that_reported_its_failure_and_ended_is_not_called_an_unexplained_end() -> None:
    """The listener's wait may time out just before the mapping side's last message, and the next
    check then finds it ended: its MappingFailed, still queued, names the cause (seen in a fresh
    clone's suite: "the mapping thread ended unexpectedly (exit code 1)" for a mapping that raised)."""
    client = object.__new__(MappingProcess)  # its listener's state alone: no mapping side started
    client.side, client.failure, client._done = "the mapping thread", "", queue.SimpleQueue()
    client.process = SimpleNamespace(is_alive=lambda: False, exitcode=1)
    client.from_mapping = queue.Queue()
    client.from_mapping.put(m.MappingFailed("RuntimeError: mapping broke\nTraceback ..."))
    client._watch()
    assert client.failure == "the mapping thread failed: RuntimeError: mapping broke"
