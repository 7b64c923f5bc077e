"""The `run` job: SLAM over a dataset through the runtime, then metrics and outputs."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from pipeline.app.report import run_summary, timing_summary, versions
from pipeline.app.resume import read_resumable
from pipeline.app.run_folders import check_output, existing_run_folder, new_run_folder
from pipeline.app.session import Session, complete_config, describe_run, execute_session, open_session
from pipeline.app.signals import signals_noted
from pipeline.config import Config
from pipeline.devices import describe, resolve_device, synthetic_for
from pipeline.errors import OutputError, StageFailure, UserError
from pipeline.metrics import absolute_trajectory_error, view_quality
from pipeline.outputs.run_folder import RunFolder
from pipeline.runtime import RuntimeReport
from pipeline.slam.state import Checkpoint
from pipeline.sources.datasets.base import Dataset
from pipeline.sources.datasets.loader import open_dataset
from pipeline.sources.datasets.source import DatasetSource
from pipeline.sources.datasets.synthetic_writer import cached_synthetic
from pipeline.stages.upload import make_uploader

log = logging.getLogger("gsplatam")


@dataclass
class RunResult:
    folder: RunFolder
    metrics: dict[str, Any] | None  # None when interrupted before the first frame


def run_slam(
    config: Config,
    resume: Path | None = None,
    profile_trace: bool = False,
    progress: bool = True,
    overwrite: bool = False,
) -> RunResult:
    """SLAM over the configured dataset (or the generated room) into a new run folder (see
    `run_folders`; `overwrite` replaces a named one's earlier run); `resume` continues the run
    folder of an earlier run from its checkpoint, once it is known to be the same run.

    Outputs are saved every `run.save_every_s` and at the end. A frame that cannot be read, or a
    folder that cannot be written, ends the run: what was processed is written and marked in
    metrics.json, then the StageFailure is raised. A signal after SLAM (evaluation, writing)
    cuts the evaluation short; the outputs are still written."""
    device = resolve_device(config.run.device)
    if resume is None:
        check_output(Path(config.run.output))  # before a generated room is cached there
    dataset, config = _prepare_dataset(config, device, progress)
    run_info = describe_run(dataset.name, False, config, **_dataset_details(dataset, config))
    if resume is not None:
        claimed = existing_run_folder(resume)
    else:
        claimed = new_run_folder(Path(config.run.output), _default_name(dataset, config), config.run.name, overwrite)
    with claimed as folder:
        checkpoint = read_resumable(folder, run_info, len(dataset)) if resume is not None else None
        session = _open(config, dataset, folder, run_info, checkpoint, progress)
        try:
            with signals_noted() as signalled:
                report = _execute(session, dataset, profile_trace)
                if session.slam.gaussians is None:
                    if report.interrupted:
                        log.info("interrupted before the first frame was processed: nothing to write")
                        return RunResult(session.folder, None)
                    raise UserError("no frame was processed")
                metrics = _finish(session, dataset, report, signalled, progress)
            ate, render = metrics["ate"] or {}, metrics["render"] or {}
            summary = run_summary(metrics["frames"], metrics["gaussians"], ate.get("rmse_cm"), render.get("psnr_db"))
            session.linger(summary + f"\n\nin {session.folder.path}")
            return RunResult(session.folder, metrics)
        finally:
            session.close()


def _open(
    config: Config,
    dataset: Dataset,
    folder: Path,
    run_info: dict[str, Any],
    checkpoint: Checkpoint | None,
    progress: bool,
) -> Session:
    """The session over `dataset` into `folder`, from `checkpoint` when resuming (frames.csv
    kept to its frames); a write failure stops the run."""
    done = checkpoint.frames_done if checkpoint else 0
    RunFolder(folder).keep_frames(done)
    session = open_session(
        config,
        DatasetSource(dataset, done),
        folder,
        progress=progress,
        run_info=run_info,
        save_every_s=config.run.save_every_s,
        stop_on_failure=True,
        resume=checkpoint,
        earlier=[(r.timestamp, r.c2w_gt) for r in dataset.refs[:done]],
        total=len(dataset),
    )
    log.info("dataset: %s (%s, %d frames)", dataset.name, dataset.format, len(dataset))
    return session


def _execute(session: Session, dataset: Dataset, profile_trace: bool) -> RuntimeReport:
    """SLAM to the end of the dataset or a stop; after a failure, what was processed is written
    before the failure is raised again."""
    try:
        return execute_session(session, profile_trace)
    except StageFailure as failure:
        _write_after_failure(session, dataset, failure)
        raise


def _default_name(dataset: Dataset, config: Config) -> str:
    return f"{dataset.name}_{config.preset}"


def _dataset_details(dataset: Dataset, config: Config) -> dict[str, Any]:
    """What of the dataset a checkpoint must match to be continued (see app/resume.py)."""
    width, height = dataset.frame_size
    return {
        "format": dataset.format,
        "size": [width, height],
        "start": config.dataset.start,
        "stride": config.dataset.stride,
    }


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


def _finish(
    session: Session, dataset: Dataset, report: RuntimeReport, signalled: threading.Event, progress: bool
) -> dict[str, Any]:
    """Write trajectory, map and checkpoint, evaluate (unless the run was interrupted; a signal
    cuts it short), write metrics. OutputError where a file could not be written (a full disk)."""
    session.saver.save_now(session.slam.checkpoint())
    metrics = _metrics(session, dataset)
    results = session.sink.results
    earlier = session.folder.read_metrics() if not results else None  # a resume that only evaluates
    metrics.update(
        runtime=earlier.get("runtime") if earlier else report.summary(),
        time=earlier.get("time") if earlier else timing_summary(results, report, session.sink.arrivals),
    )
    if report.interrupted:
        metrics["evaluation"] = "skipped: SLAM was interrupted (continue with --resume)"
    else:
        metrics["render"], metrics["evaluation"] = _render_metrics(session, dataset, signalled, progress)
    metrics["interrupted"] = report.interrupted or signalled.is_set()
    metrics["write_error"] = session.saver.error or None  # a frames.csv line that could not be written
    session.folder.write_metrics(metrics)
    if session.saver.error:
        raise OutputError(f"{session.saver.error}; the other outputs are written")
    return metrics


def _metrics(session: Session, dataset: Dataset) -> dict[str, Any]:
    """What every metrics.json holds: frames, map size, lost frames, device and the ATE."""
    config, slam, sink, device = session.config, session.slam, session.sink, session.device
    poses = torch.stack(slam.poses).double().cpu().numpy()
    refs = dataset.refs[: len(poses)]
    known = [r.c2w_gt for r in refs if r.c2w_gt is not None]
    metrics: dict[str, Any] = {
        "dataset": dataset.name,
        "preset": config.preset,
        "frames": len(poses),
        "frames_this_run": len(sink.results),
        "gaussians": len(slam.gaussians) if slam.gaussians is not None else 0,
        "lost_frames": sink.lost_frames,  # the sink's counts, as serve's metrics take them
        "weak_frames": sink.weak_frames,
        "relocalised_frames": sink.relocalised_frames,
        "unmapped_frames": sink.unmapped_frames,
        "schedule": config.slam.schedule,
        "device": describe(device, config),
        "versions": versions(),
        "stopped": None,
        "ate": None,
        "render": None,
    }
    if device.type == "cuda":
        metrics["peak_gpu_memory_gb"] = torch.cuda.max_memory_allocated(device) / 1e9
    if len(known) == len(refs) and len(refs) >= 2:
        try:
            metrics["ate"] = _ate(poses, np.stack(known))
        except (ValueError, np.linalg.LinAlgError) as exc:  # never lose metrics.json over it
            log.warning("ATE not computed: %s", exc)
    return metrics


def _write_after_failure(session: Session, dataset: Dataset, failure: StageFailure) -> None:
    """Write what was processed before `failure` ended the run, and mark where and why it stopped
    in metrics.json; a write that fails too is logged (the failure is what the user sees)."""
    slam, saver = session.slam, session.saver
    if slam.frames_done == 0:
        return
    try:
        saver.save_now(slam.checkpoint())
    except OutputError as exc:
        log.error("%s", exc)
    metrics = _metrics(session, dataset)
    where = {"stage": failure.stage, "frame": failure.frame, "reason": str(failure.cause)}
    metrics["stopped"] = {**where, "frames_saved": saver.saved_frames}
    metrics["evaluation"] = "skipped: the run stopped on an error"
    try:
        session.folder.write_metrics(metrics)
    except OutputError as exc:
        log.error("%s", exc)
        return
    log.info(
        "saved %d of the %d frames processed in %s; once the cause is fixed: gsplatam run --resume %s",
        saver.saved_frames,
        slam.frames_done,
        session.folder.path,
        session.folder.path,
    )


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


def _render_metrics(
    session: Session, dataset: Dataset, signalled: threading.Event, progress: bool
) -> tuple[dict[str, Any] | None, str]:
    """PSNR, SSIM and depth L1 of the final map rendered at the estimated poses, every Nth frame;
    -> (their means, or None when no frame was evaluated; how complete the evaluation is). A
    signal (`signalled`) cuts it short after the frame in hand."""
    config, slam = session.config, session.slam
    gaussians, poses = slam.gaussians, slam.poses
    assert gaussians is not None
    uploader = make_uploader(session.device, slots=2)
    picks = list(range(0, slam.frames_done, config.run.eval_every))
    scores = []
    for i in tqdm(picks, desc="evaluate", unit="frame", disable=not progress, dynamic_ncols=True):
        if signalled.is_set():
            break
        frame = uploader(dataset.decode(dataset.refs[i])).wait()
        scores.append(view_quality(slam.renderer, gaussians, frame, poses[i], config.render.near, config.render.far))
    done = (
        "complete" if len(scores) == len(picks) else f"cut short by a signal after {len(scores)} of {len(picks)} frames"
    )
    if not scores:
        return None, done
    render = {
        "psnr_db": float(np.mean([s.psnr_db for s in scores])),
        "ssim": float(np.mean([s.ssim for s in scores])),
        "depth_l1_cm": float(np.mean([s.depth_l1_cm for s in scores])),
        "frames_evaluated": len(scores),
        "every": config.run.eval_every,
        "pixels": "valid-depth pixels only",
    }
    return render, done
