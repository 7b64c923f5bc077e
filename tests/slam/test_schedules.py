"""The sequential SLAM stage through the runtime: today's results, the live warm-up, a stop."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ROOT

from pipeline.app.cli import main
from pipeline.app.run import run_slam
from pipeline.config import DatasetConfig, load_config, with_dataset_defaults, with_value
from pipeline.frame import DeviceFrame
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.checkpoint import read_checkpoint
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.source import DatasetSource
from pipeline.metrics import view_quality
from pipeline.render import Gaussians, make_renderer
from pipeline.runtime import Graph, run_graph
from pipeline.slam.handoff import FrameResult
from pipeline.slam.splatam import SplaTAM
from pipeline.stages.frame_log import FrameLog
from pipeline.stages.sinks import ResultSink
from pipeline.stages.slam import slam_stage
from pipeline.stages.upload import HostUploader, UploadedFrame, host_frame_tensors

CPU = torch.device("cpu")
REFERENCE = ROOT / "tests" / "data" / "sequential_reference.json"
FAST = ["tracking.iters=3", "mapping.iters=3"]
RECORDED = ["tracking.method=adam", "gaussians.seed_scale=1.0", "gaussians.seed_opacity=0.5", "render.eps2d=0.3"]
RECORDED_PSNR_DB = 0.02  # the recorded run's renders on another CPU: 30x the rounding spread measured (REFERENCE)
RECORDED_L1_CM = 0.01


def _checksum(gaussians: Gaussians) -> str:
    digest = hashlib.sha256()
    for tensor in (gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits, gaussians.colors):
        digest.update(tensor.detach().contiguous().numpy().tobytes())
    return digest.hexdigest()


def _slam(overrides: list[str]) -> SplaTAM:
    config = with_dataset_defaults(load_config("tiny", overrides=overrides), "replica")
    return SplaTAM(config, make_renderer(config.render, config.gaussians, CPU), CPU)


def _run_graph(slam: SplaTAM, source: DatasetSource) -> ResultSink:
    sink = ResultSink(FrameLog())
    stage = slam_stage(slam, source.last_index, [])
    asyncio.run(run_graph(Graph(source, HostUploader(), stage, sink, queue_size=8), asyncio.Event()))
    return sink


@pytest.mark.slow
def test_sequential_through_the_runtime_is_the_plain_loop_and_the_recorded_run(replica_seq: Path) -> None:
    """The sequential schedule is SplaTAM.step frame after frame, bit for bit; and it reproduces
    the run recorded before tracking and mapping were split (tests/data/sequential_reference.json,
    same settings, SplaTAM's tracker and seeds; re-recorded when the reference renderer went to 8x8 tiles, the
    file says by how much it moved). Bit for bit on the machine that recorded it; another CPU rounds
    float32 reductions in another order, so poses, the Gaussian count and renders of the final map are
    compared, to tolerances the file derives ("tolerances")."""
    dataset = open_dataset(DatasetConfig(path=str(replica_seq)))
    plain = _slam(RECORDED)  # the recorded run's tracker and seeds (SplaTAM's)
    for frame in dataset.frames():
        plain.step(host_frame_tensors(frame))
    staged = _slam(RECORDED)
    sink = _run_graph(staged, DatasetSource(dataset))
    assert [r.index for r in sink.results] == list(range(len(dataset)))
    assert torch.equal(torch.stack(staged.poses), torch.stack(plain.poses))
    assert staged.gaussians is not None and plain.gaussians is not None
    assert _checksum(staged.gaussians) == _checksum(plain.gaussians)

    recorded = json.loads(REFERENCE.read_text())
    np.testing.assert_allclose(torch.stack(plain.poses).numpy(), np.array(recorded["poses_c2w"]), atol=1e-6)
    assert len(plain.gaussians) == recorded["gaussians"]
    config, frames = plain.config, [host_frame_tensors(frame) for frame in dataset.frames()]
    scores = [
        view_quality(plain.renderer, plain.gaussians, frame, c2w, config.render.near, config.render.far)
        for frame, c2w in zip(frames, plain.poses)
    ]
    np.testing.assert_allclose([s.psnr_db for s in scores], recorded["render"]["psnr_db"], atol=RECORDED_PSNR_DB)
    np.testing.assert_allclose([s.depth_l1_cm for s in scores], recorded["render"]["depth_l1_cm"], atol=RECORDED_L1_CM)


def test_a_live_warm_up_drops_the_first_frame_and_leaves_no_trace(replica_seq: Path) -> None:
    """The first frame a warming live stage takes runs through SLAM and is dropped (counted);
    the frames after it give, bit for bit, what a SLAM that never saw it gives."""
    frames = [host_frame_tensors(f) for f in open_dataset(DatasetConfig(path=str(replica_seq))).frames()][:4]
    warmed, cold = _slam(FAST), _slam(FAST)
    first = slam_stage(warmed, None, [], live=True, warm_up=True)

    def step(frame: DeviceFrame) -> FrameResult | None:
        return first.run(UploadedFrame(frame, None))

    assert step(frames[0]) is None and first.dropped == 1
    assert warmed.frames_done == 0 and warmed.gaussians is None and warmed.frontend.frames_done == 0
    results = [step(f) for f in frames[1:]]
    expected = [cold.step(f) for f in frames[1:]]
    assert [r.index for r in results if r is not None] == [r.index for r in expected] == [1, 2, 3]
    assert torch.equal(torch.stack(warmed.poses), torch.stack(cold.poses))
    assert torch.equal(warmed.poses[0], torch.eye(4))  # the map starts at the first frame kept
    assert warmed.gaussians is not None and cold.gaussians is not None
    assert _checksum(warmed.gaussians) == _checksum(cold.gaussians)
    ours, theirs = warmed.checkpoint(), cold.checkpoint()
    assert ours.mapping.rng_state == theirs.mapping.rng_state
    assert torch.equal(ours.mapping.generator_state, theirs.mapping.generator_state)
    assert ours.mapping.scene_radius == theirs.mapping.scene_radius
    assert ours.tracking.loss_history == theirs.tracking.loss_history
    assert [k.index for k in ours.keyframes] == [k.index for k in theirs.keyframes]
    counters = ("frames_seen", "last_keyframe_seen")
    assert [getattr(warmed.backend, c) for c in counters] == [getattr(cold.backend, c) for c in counters]
    assert first.dropped == 1


def test_warm_up_refuses_a_slam_that_has_started(replica_seq: Path) -> None:
    frame = host_frame_tensors(next(iter(open_dataset(DatasetConfig(path=str(replica_seq))).frames())))
    slam = _slam(FAST)
    slam.step(frame)
    with pytest.raises(RuntimeError, match="before the first frame"):
        slam.warm_up(frame)


@pytest.mark.slow
@pytest.mark.parametrize("stop_after", [1, 2])
def test_stopping_a_run_leaves_a_complete_resumable_folder(
    replica_seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, stop_after: int
) -> None:
    consume = ResultSink.consume

    def consume_then_stop(self: ResultSink, result) -> None:  # type: ignore[no-untyped-def]
        consume(self, result)
        if len(self.results) == stop_after:
            os.kill(os.getpid(), signal.SIGINT)  # as Ctrl-C: the runtime's handler stops the graph

    monkeypatch.setattr(ResultSink, "consume", consume_then_stop)
    config = load_config("tiny", overrides=FAST + [f"dataset.path={replica_seq}"])
    config = with_value(with_value(config, "run.output", str(tmp_path)), "run.name", "r")
    result = run_slam(config, CPU, progress=False)
    assert result.metrics is not None and result.metrics.interrupted
    folder = result.folder.path
    saved, _ = read_checkpoint(folder / "checkpoint.safetensors")
    frames = result.metrics.frames
    assert stop_after <= frames < len(open_dataset(DatasetConfig(path=str(replica_seq))))
    assert saved.frames_done == frames == len(read_tum_trajectory(folder / "trajectory.txt")[0])
    assert len((folder / "frames.csv").read_text().splitlines()) == 1 + frames

    monkeypatch.setattr(ResultSink, "consume", consume)
    assert main(["run", "--resume", str(folder), "--quiet", "--device", "cpu"]) == 0
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["frames"] == 6 and metrics["frames_this_run"] == 6 - frames and not metrics["interrupted"]
    assert len(read_tum_trajectory(folder / "trajectory.txt")[0]) == 6
