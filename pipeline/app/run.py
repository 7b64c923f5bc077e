"""The `run` job: SLAM over a dataset through the runtime, then metrics and outputs."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from pipeline.app.report import run_summary, timing_summary, versions
from pipeline.app.session import Session, complete_config, execute_session, open_session
from pipeline.config import Config
from pipeline.devices import describe, resolve_device, synthetic_for
from pipeline.errors import UserError
from pipeline.io.datasets.base import Dataset
from pipeline.io.datasets.loader import open_dataset
from pipeline.io.datasets.source import DatasetSource
from pipeline.io.datasets.synthetic_writer import cached_synthetic
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.metrics import absolute_trajectory_error, view_quality
from pipeline.runtime import RuntimeReport
from pipeline.slam.state import Checkpoint
from pipeline.stages.upload import make_uploader

log = logging.getLogger("gsplatam")


@dataclass
class RunResult:
    folder: RunFolder
    metrics: dict[str, Any] | None  # None when interrupted before the first frame


def run_slam(
    config: Config, resume: Path | None = None, profile_trace: bool = False, progress: bool = True
) -> RunResult:
    """SLAM over the configured dataset (or the generated room) into a run folder; `resume`
    continues the run folder of an earlier run from its checkpoint."""
    device = resolve_device(config.run.device)
    dataset, config = _prepare_dataset(config, device, progress)
    checkpoint = _read_resume(resume, len(dataset)) if resume is not None else None
    folder = (
        resume if resume is not None else Path(config.run.output) / (config.run.name or _default_name(dataset, config))
    )
    source = DatasetSource(dataset, checkpoint.frames_done if checkpoint else 0)
    session = open_session(config, source, folder, progress=progress, resume=checkpoint, total=len(dataset))
    log.info("dataset: %s (%s, %d frames)", dataset.name, dataset.format, len(dataset))
    try:
        report = execute_session(session, profile_trace)
        if session.slam.gaussians is None:
            if report.interrupted:
                log.info("interrupted before the first frame was processed: nothing to write")
                return RunResult(session.folder, None)
            raise UserError("no frame was processed")
        metrics = _finish(session, dataset, report, progress)
        ate, render = metrics["ate"] or {}, metrics["render"] or {}
        summary = run_summary(metrics["frames"], metrics["gaussians"], ate.get("rmse_cm"), render.get("psnr_db"))
        session.linger(summary + f"\n\nin {session.folder.path}")
        return RunResult(session.folder, metrics)
    finally:
        session.close()


def _default_name(dataset: Dataset, config: Config) -> str:
    return f"{dataset.name}_{config.preset}"


def _prepare_dataset(config: Config, device: torch.device, progress: bool) -> tuple[Dataset, Config]:
    """Open the configured dataset (generating the embedded synthetic scene when none is given)
    -> (the dataset, the config completed for it)."""
    dataset_config = config.dataset
    if not dataset_config.path:
        synthetic = synthetic_for(config.synthetic, device)
        path = cached_synthetic(Path(config.run.output) / "synthetic", synthetic, progress, device)
        dataset_config = replace(dataset_config, path=str(path), format=synthetic.layout)
        config = replace(config, synthetic=synthetic, dataset=dataset_config)
    dataset = open_dataset(dataset_config)
    return dataset, complete_config(config, device, dataset.format)


def _read_resume(folder: Path, frames: int) -> Checkpoint:
    checkpoint, _ = RunFolder(folder).read_checkpoint()
    if checkpoint.frames_done >= frames:
        raise UserError(f"{folder} already holds all {frames} frames")
    return checkpoint


def _finish(session: Session, dataset: Dataset, report: RuntimeReport, progress: bool) -> dict[str, Any]:
    """Write trajectory, map, checkpoint and metrics; evaluate unless the run was interrupted."""
    config, slam, sink, device = session.config, session.slam, session.sink, session.device
    results = sink.results
    saved = slam.checkpoint()
    refs = dataset.refs[: saved.frames_done]
    timestamps = np.array([r.timestamp for r in refs])
    known = [r.c2w_gt for r in refs if r.c2w_gt is not None]
    reference = np.stack(known) if len(known) == len(refs) else None
    session.folder.write_state(saved, timestamps, reference)
    metrics: dict[str, Any] = {
        "dataset": dataset.name,
        "preset": config.preset,
        "frames": saved.frames_done,
        "frames_this_run": len(results),
        "interrupted": report.interrupted,
        "gaussians": len(saved.gaussians),
        "lost_frames": sum(bool(r.lost) for r in results),
        "weak_frames": sum(bool(r.warning) for r in results),
        "unmapped_frames": sum(not r.mapped for r in results),
        "schedule": config.slam.schedule,
        "device": describe(device, config),
        "versions": versions(),
        "runtime": report.summary(),
        "time": timing_summary(results, report, sink.arrivals),
        "ate": None,
        "render": None,
    }
    if device.type == "cuda":
        metrics["peak_gpu_memory_gb"] = torch.cuda.max_memory_allocated(device) / 1e9
    if reference is not None and saved.frames_done >= 2:
        metrics["ate"] = _ate(saved.poses.double().numpy(), reference)
    if not report.interrupted:
        metrics["render"] = _render_metrics(session, dataset, progress)
    session.folder.write_metrics(metrics)
    return metrics


def _ate(estimated: np.ndarray, reference: np.ndarray) -> dict[str, Any]:
    ate = absolute_trajectory_error(estimated, reference)
    return {
        "rmse_cm": 100 * ate.rmse_m,
        "mean_cm": 100 * ate.mean_m,
        "median_cm": 100 * ate.median_m,
        "max_cm": 100 * ate.max_m,
        "frames": ate.frames,
        "alignment": "rigid (rotation + translation, no scale), least squares over camera centres",
    }


def _render_metrics(session: Session, dataset: Dataset, progress: bool) -> dict[str, Any]:
    """PSNR, SSIM and depth L1 of the final map rendered at the estimated poses, every Nth frame."""
    config, slam = session.config, session.slam
    gaussians, poses = slam.gaussians, slam.poses
    assert gaussians is not None
    uploader = make_uploader(session.device, slots=2)
    picks = list(range(0, slam.frames_done, config.run.eval_every))
    scores = []
    for i in tqdm(picks, desc="evaluate", unit="frame", disable=not progress, dynamic_ncols=True):
        frame = uploader(dataset.decode(dataset.refs[i])).wait()
        scores.append(view_quality(slam.renderer, gaussians, frame, poses[i], config.render.near, config.render.far))
    return {
        "psnr_db": float(np.mean([s.psnr_db for s in scores])),
        "ssim": float(np.mean([s.ssim for s in scores])),
        "depth_l1_cm": float(np.mean([s.depth_l1_cm for s in scores])),
        "frames_evaluated": len(scores),
        "every": config.run.eval_every,
        "pixels": "valid-depth pixels only",
    }
