"""The `serve` daemon: live reconstruction from a phone, until SIGINT/SIGTERM.

The same session as `run`, with a live source (keep-newest queues; reconnection inside the
source, so SLAM maps into one map across disconnections), a periodic save and a JSON status
endpoint on localhost.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import torch

from pipeline.app.remote_control import RemoteControl
from pipeline.app.report import run_summary
from pipeline.app.session import Session, execute_session, open_session
from pipeline.app.setup import LIVE_LAYOUT, Setup, finish_config
from pipeline.app.signals import signals_noted
from pipeline.config import Config
from pipeline.errors import MappingProcessFailed, StageFailure
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.outputs.run_folders import new_run_folder
from pipeline.io.outputs.run_metrics import AteRecord, FrameAges, RunMetrics, StopRecord
from pipeline.io.sources.cameras import open_source
from pipeline.io.sources.live.recording import RecordingSource
from pipeline.runtime import Graph, RuntimeReport
from pipeline.slam.handoff import FrameResult
from pipeline.source import Source
from pipeline.stages.frame_log import ate_so_far_cm, referenced_poses
from pipeline.ui.progress import ProgressBar
from pipeline.ui.status_http import serve_status

log = logging.getLogger("gsplatam")

AGE_WINDOW = 100  # frames over which the status endpoint's frame ages are taken
BAR_EVERY_S = 1.0  # the progress bar's live counters are refreshed this often


@dataclass
class ServeResult:
    folder: RunFolder
    metrics: RunMetrics | None  # None when no frame was processed


def status_reader(session: Session, graph: Graph) -> Callable[[], dict[str, Any]]:
    """The status endpoint's view of the daemon (read on the event loop; plain attribute reads)."""
    source, frames = session.source, session.log

    def read() -> dict[str, Any]:
        results, last = frames.results, frames.last
        dropped = graph.dropped()
        return {
            "source": source.name,
            **vars(source.counters),
            "processed": len(results),
            "dropped": sum(dropped.values()),
            "dropped_by_queue": dropped,
            "frame_age_ms": asdict(FrameAges.of(results[-AGE_WINDOW:])),
            "fps": frames.recent_fps(),
            "gaussians": last.gaussians if last else 0,
            "tracking": _tracking_state(last),
            "lost_frames": frames.lost_frames,
            "relocalised_frames": frames.relocalised_frames,
            "unmapped_frames": frames.unmapped_frames,
            "last_frame_ms": 1000 * last.seconds["total"] if last else None,
            "seconds_since_last_frame": frames.seconds_since_last(),
            "ate_rmse_cm": ate_so_far_cm(results),
            "gpu_memory_gb": _gpu_memory_gb(session.device),
            "save_error": session.saver.error or None,
            "saved_frames": session.saver.saved_frames,
            "kernel_busy_fraction": _kernel_busy(session),
        }

    return read


def _kernel_busy(session: Session) -> float | None:
    """The GPU's kernel busy fraction once its sampled window (frames 10-60) has closed."""
    sample = None if session.kernels is None else session.kernels.sample
    return None if sample is None else sample.busy_fraction


def _gpu_memory_gb(device: torch.device) -> float | None:
    """Memory held by tensors on the compute device (the allocator's count: no synchronisation)."""
    return torch.cuda.memory_allocated(device) / 1e9 if device.type == "cuda" else None


def _tracking_state(last: FrameResult | None) -> str:
    if last is None:
        return "waiting"
    if last.lost:
        return f"lost: {last.lost}"
    return f"weak: {last.warning}" if last.warning else "ok"


def bar_counters(session: Session, graph: Graph) -> dict[str, Any]:
    """What the progress bar adds for a daemon: frames received, processed and dropped, and the
    age of the last result (a few attribute reads: no percentiles, no ATE)."""
    age = session.log.seconds_since_last()
    return {
        "received": session.source.counters.received,
        "processed": len(session.log.results),
        "dropped": sum(graph.dropped().values()),
        "age": "-" if age is None else f"{age:.1f}s",
    }


async def status_on_bar(bar: ProgressBar, counters: Callable[[], dict[str, Any]], stop: asyncio.Event) -> None:
    """A runtime service: `counters` on the progress bar, every BAR_EVERY_S, until `stop`."""
    while not stop.is_set():
        bar.show(counters())
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), BAR_EVERY_S)


def serve_live(
    spec: str,
    config: Config,
    device: torch.device,
    progress: bool = True,
    overwrite: bool = False,
    control: RemoteControl | None = None,
    changes: Sequence[tuple[str, Any]] = (),
) -> ServeResult:
    """`serve` from the live camera `spec` names (sources/cameras.py), with `config` finished for
    a live session on `device` (`changes`: the session's own, setup.finish_config)."""
    setup = finish_config(config, device, LIVE_LAYOUT, live=True, changes=changes)
    source = open_source(spec, setup.config.live, device)
    log.info("live from %s -> SLAM until Ctrl-C, which saves and stops", spec)
    return serve(setup, source, progress, overwrite, control)


def serve(
    setup: Setup,
    source: Source,
    progress: bool = True,
    overwrite: bool = False,
    control: RemoteControl | None = None,
) -> ServeResult:
    """Reconstruct from `source` until it ends or SIGINT/SIGTERM (or `control` stops it, from
    another thread); save periodically and at the end, into a new run folder
    (`live_<source>_<preset>-<timestamp>`, or `run.name`). A save that fails (a full disk) is
    reported once in the log and the status and SLAM goes on; a final save that fails raises
    OutputError (the last complete save stays). `setup` is finished for a live session."""
    config = setup.config
    stem = f"live_{source.name}_{config.preset}"
    with new_run_folder(Path(config.run.output), stem, config.run.name, overwrite) as folder:
        recording = RecordingSource(source, folder.recording) if config.live.record else None
        session = open_session(
            setup,
            recording or source,
            folder,
            progress=progress,
            run=RunDescription.of_live(source.name, config),
            save_every_s=config.live.save_every_s,
        )

        def add_status(graph: Graph) -> None:
            read = status_reader(session, graph)
            if progress:
                graph.services.append(partial(status_on_bar, session.bar, partial(bar_counters, session, graph)))
            if config.live.status_port:
                graph.services.append(partial(serve_status, config.live.status_host, config.live.status_port, read))
            if control is not None:
                graph.services.append(control.service(read))

        try:
            with signals_noted(on_again=session.slam.stop_waiting):
                report: RuntimeReport | StageFailure = _executed(session, add_status)
                if recording is not None:
                    recording.close()  # complete before the final save, and before the viewer lingers
                result = _save(session, report, recording.error if recording is not None else "")
            if isinstance(report, StageFailure):
                raise report
            if session.slam.failure:
                raise MappingProcessFailed(session.slam.failure)
            if result.metrics is not None:
                session.linger(run_summary(result.metrics) + f"\n\nin {folder.path}")
            return result
        finally:
            if recording is not None:
                recording.close()
            session.close()


def _executed(session: Session, add_status: Callable[[Graph], None]) -> RuntimeReport | StageFailure:
    """The session's graph run to its end or a stop -> its report, or the failure that ended it
    (raised once what was processed is saved)."""
    try:
        return execute_session(session, on_graph=add_status)
    except StageFailure as failure:
        return failure


def _save(session: Session, ended: RuntimeReport | StageFailure, recording_error: str = "") -> ServeResult:
    """The final save (map, trajectory, checkpoint: every frame processed) and metrics.json (with
    where and why the session stopped, if it failed, and `recording_error`: why the recording's
    last write failed, if it did)."""
    slam, saver, folder = session.slam, session.saver, session.folder
    slam.finish(0)  # the frames mapping was given
    if slam.frames_done == 0:
        log.info("stopped before any frame was processed: nothing to save")
        return ServeResult(folder, None)
    checkpoint = slam.checkpoint() if slam.gaussians is not None else None  # None: no map made yet
    if checkpoint is not None:
        saver.save_now(checkpoint)
    report = ended if isinstance(ended, RuntimeReport) else None
    poses = referenced_poses(session.log.results)  # NeRFCapture's with live.device_pose=groundtruth
    ate = AteRecord.between(*poses) if poses is not None else None
    metrics = session.metrics(report, ate, None if checkpoint is None else checkpoint.mapping.loops)
    write_error = "; ".join(e for e in (saver.error, recording_error) if e) or None
    stopped = _stop_record(ended, slam.failure, saver.saved_frames)
    metrics = replace(metrics, interrupted=report is not None and report.interrupted, write_error=write_error)
    folder.write_metrics(replace(metrics, stopped=stopped))
    if stopped is not None:
        replay = f"; gsplatam run {folder.recording} runs it again offline" if folder.recorded() else ""
        log.info(
            "saved %d of the %d frames processed in %s (a live session is not continued with --resume%s)",
            saver.saved_frames, slam.frames_done, folder.path, replay,
        )  # fmt: skip
    return ServeResult(folder, metrics)


def _stop_record(ended: RuntimeReport | StageFailure, failure: str, saved: int) -> StopRecord | None:
    """Where and why the session stopped on an error (None: it ended or was stopped as asked)."""
    if isinstance(ended, StageFailure):
        return StopRecord(ended.stage, ended.frame, str(ended.cause), saved)
    return StopRecord("mapping", None, failure, saved) if failure else None
