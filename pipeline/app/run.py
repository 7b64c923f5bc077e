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

from pipeline.app.report import resume_command, run_summary
from pipeline.app.resume import read_resumable
from pipeline.app.session import Session, execute_session, open_session
from pipeline.app.setup import Setup, finish_config
from pipeline.app.signals import signals_noted
from pipeline.config import Config
from pipeline.errors import MappingProcessFailed, OutputError, StageFailure, UserError
from pipeline.frame import DeviceFrame
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.pictures import render_picture, spread, write_render_picture, write_trajectory_png
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.outputs.run_folders import check_output, new_run_folder, resumed_run_folder
from pipeline.io.outputs.run_metrics import AteRecord, RenderRecord, RunMetrics, StepRecord, StopRecord
from pipeline.io.sources.datasets.base import Dataset
from pipeline.io.sources.datasets.depth_scale import check_depth_scale
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.source import DatasetSource
from pipeline.io.sources.datasets.synthetic import synthetic_for
from pipeline.io.sources.datasets.synthetic_writer import cached_synthetic
from pipeline.metrics import view_quality
from pipeline.package_builds import wait_for_builds
from pipeline.render import Gaussians, RenderOutput
from pipeline.runtime import RuntimeReport
from pipeline.slam.state import Checkpoint
from pipeline.stages.upload import make_uploader

log = logging.getLogger("gsplatam")


@dataclass
class RunResult:
    folder: RunFolder
    metrics: RunMetrics | None  # None when interrupted before the first frame


def run_slam(
    config: Config,
    device: torch.device,
    resume: RunFolder | None = None,
    profile_trace: bool = False,
    progress: bool = True,
    overwrite: bool = False,
) -> RunResult:
    """SLAM over the configured dataset (or the generated room) on `device` into a new run folder
    (see `run_folders`; `overwrite` replaces a named one's earlier run); `resume` continues the
    run folder of an earlier run from its checkpoint, once it is known to be the same run.

    Outputs are saved every `run.save_every_s` and at the end. A frame that cannot be read, a
    folder that cannot be written or a mapping process that fails ends the run: what was
    processed is written and marked in metrics.json, then the StageFailure (or, after SLAM,
    MappingProcessFailed) is raised. A signal after SLAM cuts the final refinement and the
    evaluation short (a second one: SLAM waits for nothing more); the outputs are still written."""
    if resume is None:
        check_output(Path(config.run.output))  # before a generated room is cached there
    dataset, setup = _open_dataset(config, device, progress)
    config = setup.config
    run = RunDescription.of_dataset(dataset.name, dataset.format, dataset.frame_size, config)
    if resume is not None:
        claimed = resumed_run_folder(resume)
    else:
        claimed = new_run_folder(Path(config.run.output), _default_name(dataset, config), config.run.name, overwrite)
    with claimed as folder:
        checkpoint = read_resumable(folder, run, len(dataset)) if resume is not None else None
        session = _open(setup, dataset, folder, run, checkpoint, progress)
        try:
            with signals_noted(on_again=session.slam.stop_waiting) as signalled:
                report = _execute(session, dataset, profile_trace)
                before_final = _map_to_the_end(session, dataset, report, signalled, progress)
                if session.slam.gaussians is None:
                    if session.slam.failure:  # before the first map version: frames.csv and metrics.json
                        failure = StageFailure("mapping", None, MappingProcessFailed(session.slam.failure))
                        _write_after_failure(session, dataset, failure)
                        raise failure
                    if report.interrupted:
                        log.info("interrupted before the first frame was processed: nothing to write")
                        return RunResult(session.folder, None)
                    raise UserError("no frame was processed")
                metrics = _finish(session, dataset, report, signalled, progress, before_final)
                wait_for_builds(signalled.is_set)  # (`run.precompile`: the packages for later runs)
            session.linger(run_summary(metrics) + f"\n\nin {session.folder.path}")
            return RunResult(session.folder, metrics)
        finally:
            session.close()


def _open(
    setup: Setup,
    dataset: Dataset,
    folder: RunFolder,
    run: RunDescription,
    checkpoint: Checkpoint | None,
    progress: bool,
) -> Session:
    """The session over `dataset` into `folder`, from `checkpoint` when resuming (frames.csv
    kept to its frames); a write failure stops the run."""
    done = checkpoint.frames_done if checkpoint else 0
    folder.keep_frames(done)
    session = open_session(
        setup,
        DatasetSource(dataset, done),
        folder,
        progress=progress,
        run=run,
        save_every_s=setup.config.run.save_every_s,
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


def _map_to_the_end(
    session: Session, dataset: Dataset, report: RuntimeReport, signalled: threading.Event, progress: bool
) -> RenderRecord | None:
    """Let mapping finish the frames it was given, then, unless SLAM was interrupted or did not
    run, refine over every keyframe (`mapping.final_iters` view renders; a signal cuts it short
    at its next step). -> the render metrics before that refinement (None without it)."""
    slam, final = session.slam, session.config.mapping.final_iters
    if not session.log.results or report.interrupted or not slam.frames_done:
        final = 0
    before = None
    if final:
        slam.finish(0)
        if slam.failure or signalled.is_set():
            return None
        before, _ = _render_metrics(session, dataset, signalled, progress)
        log.info(
            "final refinement: %d view renders over every keyframe (mapping.final_iters; Ctrl-C cuts it short)", final
        )
    renders = slam.finish(final, signalled.is_set)
    if final and signalled.is_set():
        log.info("final refinement cut short by a signal after %d of %d view renders", renders, final)
    elif renders:
        log.info("final refinement: %d view renders done", renders)
    return before


def _default_name(dataset: Dataset, config: Config) -> str:
    return f"{dataset.name}_{config.preset}"


def _open_dataset(config: Config, device: torch.device, progress: bool) -> tuple[Dataset, Setup]:
    """The configured dataset, or the embedded synthetic room generated for `device` (cached
    under the output folder), and the config finished for it."""
    if config.dataset.path:
        dataset = open_dataset(config.dataset)
        check_depth_scale(dataset, config.dataset)
        return dataset, finish_config(config, device, dataset.format)
    room = synthetic_for(config.synthetic, device)
    path = cached_synthetic(Path(config.run.output) / "synthetic", room, progress, device)
    changes = [("synthetic.width", room.width), ("synthetic.height", room.height), ("synthetic.frames", room.frames)]
    setup = finish_config(
        config, device, room.layout, changes=[*changes, ("dataset.path", str(path)), ("dataset.format", room.layout)]
    )
    return open_dataset(setup.config.dataset), setup


def _finish(
    session: Session,
    dataset: Dataset,
    report: RuntimeReport,
    signalled: threading.Event,
    progress: bool,
    before_final: RenderRecord | None = None,
) -> RunMetrics:
    """Write trajectory, map and checkpoint, evaluate (unless the run was interrupted; a signal
    cuts it short), write metrics (with `before_final`, the render metrics before
    `mapping.final_iters`). OutputError where a file could not be written (a full disk)."""
    checkpoint = session.slam.checkpoint()
    session.saver.save_now(checkpoint)
    failure = session.slam.failure  # the mapping process failed after SLAM: what it completed is saved
    _write_trajectory_plot(session.folder)
    poses = torch.stack(session.slam.poses).double().cpu().numpy()
    metrics = session.metrics(report, _ate_of(poses, dataset), checkpoint.mapping.loops)
    metrics = replace(metrics, large_steps=_steps_of(poses, dataset))
    if checkpoint.mapping.loops is not None and checkpoint.tracking.tracked_poses is not None:
        metrics = replace(metrics, ate_as_tracked=_ate_of(checkpoint.tracking.tracked_poses.double().numpy(), dataset))
    earlier = session.folder.read_metrics() if not session.log.results else None  # a resume that only evaluates
    if earlier is not None:
        metrics = replace(metrics, runtime=earlier.runtime, time=earlier.time)
    stopped = None
    if failure:
        render, evaluation = None, "skipped: the run stopped on an error"
        stopped = StopRecord("mapping", None, failure, session.saver.saved_frames)
    elif report.interrupted:
        render, evaluation = None, "skipped: SLAM was interrupted (continue with --resume)"
    else:
        render, evaluation = _render_metrics(session, dataset, signalled, progress)
    metrics = replace(
        metrics,
        render=render,
        render_before_final_iters=before_final,
        evaluation=evaluation,
        interrupted=report.interrupted or signalled.is_set(),
        write_error=session.saver.error or None,  # a frames.csv line that could not be written
        stopped=stopped,
    )
    session.folder.write_metrics(metrics)
    if failure:
        _say_saved(session)
        raise MappingProcessFailed(failure)
    if session.saver.error:
        raise OutputError(f"{session.saver.error}; the other outputs are written")
    return metrics


def _ate(session: Session, dataset: Dataset) -> AteRecord | None:
    """The ATE of every frame's pose against the dataset's, where it has one for every frame."""
    return _ate_of(torch.stack(session.slam.poses).double().cpu().numpy(), dataset)


def _ate_of(poses: np.ndarray, dataset: Dataset) -> AteRecord | None:
    """The ATE of `poses` [F, 4, 4] camera-to-world against the dataset's first F, where it has one for each."""
    reference = _references(dataset, len(poses))
    if reference is None:
        return None
    try:
        return AteRecord.between(poses, reference)
    except (ValueError, np.linalg.LinAlgError) as exc:  # never lose metrics.json over it
        log.warning("ATE not computed: %s", exc)
        return None


def _steps_of(poses: np.ndarray, dataset: Dataset) -> StepRecord | None:
    """The error of `poses`' [F, 4, 4] frame-to-frame motions over the dataset's large steps,
    where it has a reference pose for each of its first F frames."""
    reference = _references(dataset, len(poses))
    return None if reference is None else StepRecord.between(poses, reference)


def _references(dataset: Dataset, frames: int) -> np.ndarray | None:
    """The reference camera-to-world [F, 4, 4] of the dataset's first `frames`, where it has one
    for each (and at least two)."""
    refs = dataset.refs[:frames]
    known = [r.c2w_gt for r in refs if r.c2w_gt is not None]
    return np.stack(known) if len(known) == len(refs) >= 2 else None


def _write_after_failure(session: Session, dataset: Dataset, failure: StageFailure) -> None:
    """Write what was processed before `failure` ended the run (every frame tracked; without a
    map yet, frames.csv and metrics.json only), and mark where and why it stopped in
    metrics.json; a write that fails too is logged (the failure is what the user sees)."""
    slam, saver = session.slam, session.saver
    if slam.frames_done == 0:
        return
    if slam.gaussians is not None:
        try:
            saver.save_now(slam.checkpoint())
        except OutputError as exc:
            log.error("%s", exc)
    stopped = StopRecord(failure.stage, failure.frame, str(failure.cause), saver.saved_frames)
    metrics = session.metrics(None, _ate(session, dataset))
    metrics = replace(metrics, stopped=stopped, evaluation="skipped: the run stopped on an error")
    try:
        session.folder.write_metrics(metrics)
    except OutputError as exc:
        log.error("%s", exc)
        return
    _say_saved(session)


def _say_saved(session: Session) -> None:
    """The line after a run stopped on an error: what its folder holds now, which frames the map
    lacks, and `--resume` where it can continue (a checkpoint was saved)."""
    slam, saver, path = session.slam, session.saver, session.folder.path
    unmapped = slam.unmapped()
    lacks = f" (the map lacks frames {_listed(unmapped)}: tracked, never mapped)" if unmapped else ""
    if not saver.saved_frames:
        log.info(
            "no map was made of the %d frames tracked: %s holds their rows only; run again", slam.frames_done, path
        )
        return
    log.info(
        "saved %d of the %d frames processed in %s%s; once the cause is fixed: %s",
        saver.saved_frames, slam.frames_done, path, lacks, resume_command(path),
    )  # fmt: skip


def _listed(indices: list[int]) -> str:
    """`3, 4, 7` (the first ten, then how many more)."""
    more = f" and {len(indices) - 10} more" if len(indices) > 10 else ""
    return ", ".join(str(i) for i in indices[:10]) + more


def _render_metrics(
    session: Session, dataset: Dataset, signalled: threading.Event, progress: bool
) -> tuple[RenderRecord | None, str]:
    """PSNR, SSIM and depth L1 of the final map rendered at the estimated poses, every Nth frame;
    -> (their means, or None when no frame was evaluated; how complete the evaluation is). A
    signal (`signalled`) cuts it short after the frame in hand."""
    config, slam = session.config, session.slam
    gaussians, poses = slam.gaussians, slam.poses
    assert gaussians is not None
    uploader = make_uploader(session.device, slots=2)
    picks = list(range(0, slam.frames_done, config.run.eval_every))
    pictured = set(spread(picks, config.run.renders))
    scores = []
    for i in tqdm(picks, desc="evaluate", unit="frame", disable=not progress, dynamic_ncols=True):
        if signalled.is_set():
            break
        frame = uploader(dataset.decode(dataset.refs[i])).wait()
        near, far = config.render.near, config.render.far
        score = view_quality(slam.renderer, gaussians, frame, poses[i], near, far, keep_render=i in pictured)
        if score.render is not None:
            _write_render_picture(session.folder, frame, score.render)
        scores.append(score)
    done = (
        "complete" if len(scores) == len(picks) else f"cut short by a signal after {len(scores)} of {len(picks)} frames"
    )
    if not scores:
        return None, done
    render = RenderRecord(
        psnr_db=float(np.mean([s.psnr_db for s in scores])),
        ssim=float(np.mean([s.ssim for s in scores])),
        depth_l1_cm=float(np.mean([s.depth_l1_cm for s in scores])),
        depth_rmse_cm=float(np.mean([s.depth_rmse_cm for s in scores])),
        frames_evaluated=len(scores),
        every=config.run.eval_every,
    )
    if not signalled.is_set():
        render = replace(render, **_keyframe_psnr(session, gaussians, frame.intrinsics))
    return render, done


def _write_render_picture(folder: RunFolder, frame: DeviceFrame, render: RenderOutput) -> None:
    """renders/frameNNNNNN.png: the frame beside its render (colour, depth)."""
    picture = render_picture(
        frame.color.cpu().numpy(),
        frame.depth.cpu().numpy(),
        render.color.cpu().numpy(),
        render.depth.cpu().numpy(),
    )
    try:
        write_render_picture(folder.renders, frame.index, picture)
    except OSError as exc:
        raise OutputError(f"cannot write {folder.renders}: {exc.strerror or exc}") from None


def _write_trajectory_plot(folder: RunFolder) -> None:
    """trajectory.png from the trajectory (and reference) just saved; a plot that cannot be made
    is logged, never the end of a run's outputs."""
    try:
        timestamps, estimate = read_tum_trajectory(folder.trajectory)
        reference = read_tum_trajectory(folder.groundtruth)[1] if folder.groundtruth.is_file() else None
        if len(estimate) >= 2 and (reference is None or len(reference) == len(estimate)):
            write_trajectory_png(folder.trajectory_plot, timestamps, estimate, reference)
    except (OSError, ValueError, np.linalg.LinAlgError) as exc:
        log.warning("trajectory.png not written: %s", exc)


def _keyframe_psnr(session: Session, gaussians: Gaussians, intrinsics: torch.Tensor) -> dict[str, Any]:
    """PSNR of the map rendered at every keyframe's pose (as mapping refined it) against the
    keyframe's stored colour (8-bit), over its valid-depth pixels."""
    config, device = session.config, session.device
    keyframes = session.slam.checkpoint().keyframes
    scores = [
        view_quality(
            session.slam.renderer,
            gaussians,
            DeviceFrame(k.index, 0.0, k.color.to(device), k.depth.to(device), intrinsics, None),
            k.c2w.to(device),
            config.render.near,
            config.render.far,
        ).psnr_db
        for k in keyframes
    ]
    return {"keyframes_psnr_db": float(np.mean(scores)) if scores else None, "keyframes": len(scores)}
