"""The process schedule: mapping in a process of its own, map versions through shared slots."""

from __future__ import annotations

import asyncio
import hashlib
import json
import multiprocessing
import os
import signal
import time
from pathlib import Path

import pytest
import torch

from pipeline.app.cli import main
from pipeline.config import DatasetConfig, load_config, with_dataset_defaults
from pipeline.frame import DeviceFrame
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.checkpoint import read_checkpoint
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.source import DatasetSource
from pipeline.metrics import view_quality
from pipeline.render import Gaussians
from pipeline.runtime import Graph, run_graph
from pipeline.slam.keyframes import KeyframePose
from pipeline.slam.process.schedule import ProcessSplaTAM, start_process_slam
from pipeline.slam.process.shared_map import SLOTS, MapControl, MapReader, MapWriter
from pipeline.stages.frame_log import FrameLog
from pipeline.stages.sinks import ResultSink
from pipeline.stages.slam import slam_stage
from pipeline.stages.upload import HostUploader, host_frame_tensors

CPU = torch.device("cpu")
FAST = ["tracking.iters=3", "mapping.iters=3"]


def _checksum(gaussians: Gaussians) -> str:
    digest = hashlib.sha256()
    for tensor in (gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits, gaussians.colors):
        digest.update(tensor.detach().contiguous().numpy().tobytes())
    return digest.hexdigest()


def _map(count: int, value: float) -> Gaussians:
    return Gaussians(
        torch.full((count, 3), value), torch.full((count, 4), value), torch.full((count, 1), value),
        torch.full((count,), value), torch.full((count, 3), value),
    )  # fmt: skip


def test_shared_map_slots_are_never_written_while_held_and_grow_by_generation() -> None:
    """Three slots: the writer takes one that is neither the newest nor held; a version held
    stays intact while the writer publishes on; a map past capacity gets a larger generation."""
    control = MapControl.create(multiprocessing.get_context("spawn"))
    reader = MapReader(control, 1, CPU)
    writer = MapWriter(control, reader.first, reader.grow)
    assert reader.hold() is None
    pose = [KeyframePose(4, torch.eye(4) * 2, 3)]
    assert writer.publish(_map(5, 1.0), pose) == 1
    held = reader.hold()
    assert held is not None and held.number == 1 and len(held.gaussians) == 5
    assert held.keyframes[0].index == 4 and held.keyframes[0].position == 3
    before = _checksum(held.gaussians)
    for number in range(2, 12):  # the writer goes round the free slots, never the held one
        assert writer.publish(_map(5, float(number)), pose) == number
        assert _checksum(held.gaussians) == before
    newest = reader.hold()
    assert newest is not None and newest.number == 11 and float(newest.gaussians.means[0, 0]) == 11.0
    big = reader.first.capacity + 1
    assert writer.publish(_map(big, 7.0), pose) == 12 and writer.generation.number == 1
    grown = reader.hold()
    assert grown is not None and len(grown.gaussians) == big and float(grown.gaussians.colors[-1, 0]) == 7.0
    assert len(reader.first.slots) == SLOTS


def _process_slam(overrides: list[str], live: bool = False) -> ProcessSplaTAM:
    config = with_dataset_defaults(load_config("tiny", overrides=FAST + overrides), "replica")
    return start_process_slam(config, CPU, live)


@pytest.mark.slow
def test_process_schedule_tracks_every_frame_against_versions_never_written_meanwhile(replica_seq: Path) -> None:
    """One pose per frame; the versions tracking reads only increase; and none of them changes
    while it is tracked against (checksums before and after each tracking step), though the
    mapping process publishes refinement passes all the while."""
    dataset = open_dataset(DatasetConfig(path=str(replica_seq)))
    slam = _process_slam(["mapping.rate=frame"])  # every frame mapped (keyframe rate: test_keyframe_rate.py)
    track = slam.frontend.tracker
    seen: list[tuple[int, str, str]] = []

    def checked(gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor, large_step: bool = False):  # type: ignore[no-untyped-def]
        held = slam.held
        assert held is not None and held.gaussians is gaussians
        before = _checksum(gaussians)
        time.sleep(0.05)  # let the mapping process publish meanwhile
        result = track(gaussians, frame, c2w_init, large_step)
        seen.append((held.number, before, _checksum(gaussians)))
        return result

    slam.frontend.tracker = checked
    try:
        sink = ResultSink(FrameLog())
        stage = slam_stage(slam, len(dataset) - 1, [])
        graph = Graph(DatasetSource(dataset), HostUploader(), stage, sink, queue_size=8)
        asyncio.run(run_graph(graph, asyncio.Event()))
        slam.finish(0)
        assert [r.index for r in sink.log.results] == list(range(len(dataset)))
        assert len(slam.poses) == len(dataset) and len(seen) >= len(dataset) - 1
        assert all(before == after for _, before, after in seen)
        versions = [number for number, _, _ in seen]
        assert versions == sorted(versions) and versions[0] >= 1
        assert [r.mapped for r in sink.log.results] == [True] * len(dataset)
        assert sum(report.mapped for report in slam.mapping.mapped) == len(dataset)
        assert slam.mapping.newest_version() > versions[-1]  # mapping published after the last tracking
    finally:
        slam.close()


def _keyframe_psnr(slam: ProcessSplaTAM) -> float:
    checkpoint = slam.checkpoint()
    gaussians, config = checkpoint.gaussians, slam.config
    intrinsics = slam.mapping.ring.slots[0].intrinsics  # type: ignore[union-attr]
    scores = [
        view_quality(
            slam.renderer,
            gaussians,
            DeviceFrame(k.index, 0.0, k.color, k.depth, intrinsics, None),
            k.c2w,
            config.render.near,
            config.render.far,
        ).psnr_db
        for k in checkpoint.keyframes
    ]
    return sum(scores) / len(scores)


@pytest.mark.slow
def test_refinement_between_frames_improves_the_map(replica_seq: Path) -> None:
    """The same frames with the same frame-driven iterations: with refinement passes in the spare
    time between frames (here: waited for), the PSNR over the keyframes at the end is higher."""
    frames = [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(replica_seq))).frames()][:3]
    slams = {
        r: _process_slam([f"mapping.refine_while_idle={str(r).lower()}", "keyframes.every=1"]) for r in (False, True)
    }
    scores = {}
    try:  # both processes start at once
        for refine, slam in slams.items():
            for frame in frames:
                slam.step(frame)
                wanted, deadline = slam.mapping.refinement_renders + 6, time.monotonic() + 120
                while refine and slam.mapping.refinement_renders < wanted and time.monotonic() < deadline:
                    time.sleep(0.05)
            slam.finish(0)
            assert (slam.mapping.refinement_renders >= 6 * len(frames)) == refine
            assert sum(report.mapped for report in slam.mapping.mapped) == len(frames)
            scores[refine] = _keyframe_psnr(slam)
    finally:
        for slam in slams.values():
            slam.close()
    assert scores[True] > scores[False] + 0.1, scores


def _mapping_process() -> multiprocessing.process.BaseProcess:
    (process,) = [p for p in multiprocessing.active_children() if p.name == "gsplatam-mapping"]
    return process


def _run_argv(dataset: Path, output: Path, extra: list[str]) -> list[str]:
    sets = [f"--set={s}" for s in FAST + ["slam.schedule=process", "run.save_every_s=1e9"] + extra]
    return ["run", str(dataset), "--preset", "tiny", "--device", "cpu", "--quiet", "--output", str(output),
            "--name", "r", *sets]  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize(("after", "how"), [(2, "kill"), (4, "hang")], ids=["killed", "hung"])
def test_a_failing_mapping_process_leaves_a_complete_resumable_run(
    replica_seq: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    after: int,
    how: str,
) -> None:
    """Killed (SIGKILL) or hung (SIGSTOP: no sign of life for slam.backend_timeout_s) after
    `after` frames: one line, exit code 1, every frame tracked so far saved with the last
    complete map; --resume finishes the run (here with mapping.final_iters, whose render
    metrics before it are reported where frames were left to run)."""
    consume = ResultSink.consume

    def consume_then_fail(self: ResultSink, result) -> None:  # type: ignore[no-untyped-def]
        consume(self, result)
        if len(self.log.results) == after:
            os.kill(_mapping_process().pid, signal.SIGKILL if how == "kill" else signal.SIGSTOP)

    monkeypatch.setattr(ResultSink, "consume", consume_then_fail)
    timeout = "slam.backend_timeout_s=" + ("2" if how == "hang" else "60")  # an optimiser step on the CPU: < 1 s
    assert main(_run_argv(replica_seq, tmp_path, [timeout, "mapping.rate=frame"])) == 1
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "mapping process" in error and ("ended unexpectedly" if how == "kill" else "no sign of life") in error
    folder = tmp_path / "r"
    saved, _ = read_checkpoint(folder / "checkpoint.safetensors")
    assert after <= saved.frames_done and saved.mapping.frames_seen <= saved.frames_done
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["stopped"]["frames_saved"] == saved.frames_done == metrics["frames"]
    rows = [int(line.split(",")[0]) for line in (folder / "frames.csv").read_text().splitlines()[1:]]
    assert rows == list(range(saved.frames_done))  # one snapshot: frames.csv, trajectory, checkpoint
    assert len(read_tum_trajectory(folder / "trajectory.txt")[0]) == saved.frames_done

    monkeypatch.setattr(ResultSink, "consume", consume)
    resume = ["run", "--resume", str(folder), "--quiet", "--device", "cpu", "--set", "mapping.final_iters=6"]
    assert main(resume) == 0
    resumed = json.loads((folder / "metrics.json").read_text())
    assert resumed["frames"] == 6 and resumed["stopped"] is None and resumed["ate"] is not None
    assert resumed["schedule"] == "process" and resumed["mapping_process"]["frames_mapped"] == 6 - saved.frames_done
    if saved.frames_done < 6:  # tracking may finish every frame before the failure is noticed: nothing to resume then
        assert resumed["render"]["keyframes"] >= 1  # (then a checkpoint from before mapping's first state has none)
        assert resumed["render_before_final_iters"]["psnr_db"] > 0
    rows = [int(line.split(",")[0]) for line in (folder / "frames.csv").read_text().splitlines()[1:]]
    assert rows == list(range(6))  # no hole left by the failure


def test_mapping_state_travels_packed(tmp_path: Path) -> None:
    """A checkpoint's mapping part crosses the process boundary as a few stacked tensors and comes
    back the same."""
    from conftest import make_checkpoint

    from pipeline.slam.keyframes import Keyframe
    from pipeline.slam.process.messages import PackedBackendState

    keyframes = [
        Keyframe(i, torch.full((2, 3, 3), i, dtype=torch.uint8), torch.rand(2, 3), torch.eye(4) * i, i + 1)
        for i in (2, 5)
    ]
    state = make_checkpoint(_map(3, 0.5), keyframes, torch.eye(4).repeat(6, 1, 1)).mapping
    back = PackedBackendState.of(state).unpacked()
    assert [(k.index, k.position) for k in back.keyframes] == [(2, 3), (5, 6)]
    assert all(
        torch.equal(a.color_u8, b.color_u8) and torch.equal(a.c2w, b.c2w) for a, b in zip(back.keyframes, keyframes)
    )
    assert back.frames_seen == 6 and back.rng_state == state.rng_state


def test_kernel_busy_time_is_the_union_of_the_intervals() -> None:
    from pipeline.slam.kernel_time import union_ms

    assert union_ms([]) == 0.0
    assert union_ms([(0.0, 2.0), (1.0, 3.0), (5.0, 6.0), (5.5, 5.7)]) == 4.0


@pytest.mark.slow
@pytest.mark.parametrize("schedule", ["process", "thread"])
def test_the_tracker_warms_up_while_the_mapping_process_maps_the_first_frame(replica_seq: Path, schedule: str) -> None:
    """On the first frame the tracker is called once more, after the frame went to mapping and
    against a map seeded from that frame alone (one Gaussian per valid pixel), its result
    dropped; the run's start is reported in parts. The same with the mapping side in a thread."""
    frames = [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(replica_seq))).frames()][:2]
    slam = _process_slam(["mapping.rate=frame", "mapping.refine_while_idle=false", f"slam.schedule={schedule}"])
    slam.warms_tracker = True  # as on CUDA
    track = slam.frontend.tracker
    calls: list[tuple[list[int], int]] = []

    def counted(gaussians: Gaussians, frame: DeviceFrame, c2w_init: torch.Tensor, large_step: bool = False):  # type: ignore[no-untyped-def]
        calls.append((list(slam.mapping.handed), len(gaussians)))
        return track(gaussians, frame, c2w_init, large_step)

    slam.frontend.tracker = counted
    try:
        first = slam.step(frames[0])
        valid = int((frames[0].depth > 0).sum())
        assert calls == [([0], valid)] and first.mapped
        assert slam.frames_done == 1 and torch.equal(slam.poses[0], torch.eye(4))
        slam.step(frames[1], is_last=True)
        assert len(calls) == 2  # frame 1 tracked once, against the mapping process's version
        slam.finish(0)
        start = slam.mapping_summary()["start_up"]
        assert set(start) == {"interpreter_s", "setup_s", "first_frame_s", "tracker_s"}
        assert all(value is not None and value > 0 for value in start.values())
    finally:
        slam.close()


@pytest.mark.parametrize("schedule", ["process", "thread"])
def test_a_warm_up_leaves_no_map_behind_and_the_run_starts_afresh(replica_seq: Path, schedule: str) -> None:
    """After a live warm-up on a frame, nothing is published for the session (a stop at once has
    nothing to save); the next frames start a map at the identity."""
    frames = [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(replica_seq))).frames()][:3]
    slam = _process_slam([f"slam.schedule={schedule}"], live=True)
    try:
        slam.warm_up(frames[0])
        assert slam.frames_done == 0 and slam.gaussians is None
        slam.finish(0)
        assert slam.gaussians is None  # the warm-up's versions are not this session's map
        results = [slam.step(frame) for frame in frames[1:]]
        assert torch.equal(slam.poses[0], torch.eye(4)) and results[-1].map_version > results[0].map_version
        slam.finish(0)
        assert slam.gaussians is not None and slam.checkpoint().frames_done == 2
    finally:
        slam.close()
