"""The `serve` daemon: live reconstruction from a phone, until SIGINT/SIGTERM.

The same session as `run`, with a live source (keep-newest queues; reconnection inside the
source, so SLAM maps into one map across disconnections), a periodic save and a JSON status
endpoint on localhost.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.app.remote_control import RemoteControl
from pipeline.app.report import run_summary, timing_summary, versions
from pipeline.app.run_folders import new_run_folder
from pipeline.app.session import Session, complete_config, describe_run, execute_session, open_session
from pipeline.app.signals import signals_noted
from pipeline.config import Config
from pipeline.devices import describe, resolve_device
from pipeline.outputs.run_folder import RunFolder
from pipeline.runtime import Graph, RuntimeReport
from pipeline.slam.results import FrameResult
from pipeline.source import Source
from pipeline.sources.live.recording import RecordingSource
from pipeline.stages.sinks import ResultSink, ate_so_far_cm, recent_fps
from pipeline.ui.status_http import serve_status

log = logging.getLogger("gsplatam")

AGE_WINDOW = 100  # frames over which the status endpoint's frame ages are taken
BAR_EVERY_S = 1.0  # the progress bar's live counters are refreshed this often


@dataclass
class ServeResult:
    folder: RunFolder
    metrics: dict[str, Any] | None  # None when no frame was processed


def frame_age_ms(results: list[FrameResult]) -> dict[str, float | None]:
    """Median and 95th percentile of the frames' ages (arrival to the start of SLAM, and to the
    result), milliseconds; None without live frames."""

    def percentiles(ages: list[float]) -> tuple[float | None, float | None]:
        if not ages:
            return None, None
        p50, p95 = np.percentile(np.array(ages) * 1000.0, [50, 95])
        return float(p50), float(p95)

    start = percentiles([r.age_at_start_s for r in results if r.age_at_start_s is not None])
    done = percentiles([r.age_s for r in results if r.age_s is not None])
    return {"start_p50": start[0], "start_p95": start[1], "result_p50": done[0], "result_p95": done[1]}


def status_reader(session: Session, graph: Graph) -> Callable[[], dict[str, Any]]:
    """The status endpoint's view of the daemon (read on the event loop; plain attribute reads)."""
    source, sink = session.source, session.sink

    def read() -> dict[str, Any]:
        results, arrivals = sink.results, sink.arrivals
        dropped = graph.dropped()
        last = results[-1] if results else None
        return {
            "source": source.name,
            **vars(source.counters),
            "processed": len(results),
            "dropped": sum(dropped.values()),
            "dropped_by_queue": dropped,
            "frame_age_ms": frame_age_ms(results[-AGE_WINDOW:]),
            "fps": recent_fps(arrivals),
            "gaussians": last.gaussians if last else 0,
            "tracking": _tracking_state(last),
            "lost_frames": sink.lost_frames,
            "relocalised_frames": sink.relocalised_frames,
            "unmapped_frames": sink.unmapped_frames,
            "last_frame_ms": 1000 * last.seconds["total"] if last else None,
            "seconds_since_last_frame": _seconds_since_last_frame(sink),
            "ate_rmse_cm": ate_so_far_cm(results),
            "gpu_memory_gb": _gpu_memory_gb(session.device),
            "save_error": session.saver.error or None,
            "saved_frames": session.saver.saved_frames,
        }

    return read


def _seconds_since_last_frame(sink: ResultSink) -> float | None:
    return time.perf_counter() - sink.arrivals[-1] if sink.arrivals else None


def _gpu_memory_gb(device: torch.device) -> float | None:
    """Memory held by tensors on the compute device (the allocator's count: no synchronisation)."""
    return torch.cuda.memory_allocated(device) / 1e9 if device.type == "cuda" else None


def _tracking_state(last: FrameResult | None) -> str:
    if last is None:
        return "waiting"
    if last.lost:
        return f"lost: {last.lost}"
    return f"weak: {last.warning}" if last.warning else "ok"


def with_live_bounds(config: Config) -> Config:
    """A live session runs for hours: keyframes and map bounded by `live.max_keyframes` and
    `live.max_gaussians` unless keyframes.max_kept / mapping.max_gaussians are set."""
    if not config.keyframes.max_kept:
        config = replace(config, keyframes=replace(config.keyframes, max_kept=config.live.max_keyframes))
    if not config.mapping.max_gaussians:
        config = replace(config, mapping=replace(config.mapping, max_gaussians=config.live.max_gaussians))
    return config


def bar_counters(session: Session, graph: Graph) -> dict[str, Any]:
    """What the progress bar adds for a daemon: frames received, processed and dropped, and the
    age of the last result (a few attribute reads: no percentiles, no ATE)."""
    age = _seconds_since_last_frame(session.sink)
    return {
        "received": session.source.counters.received,
        "processed": len(session.sink.results),
        "dropped": sum(graph.dropped().values()),
        "age": "-" if age is None else f"{age:.1f}s",
    }


async def status_on_bar(sink: ResultSink, counters: Callable[[], dict[str, Any]], stop: asyncio.Event) -> None:
    """A runtime service: `counters` on the progress bar, every BAR_EVERY_S, until `stop`."""
    while not stop.is_set():
        sink.show(counters())
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), BAR_EVERY_S)


def serve(
    config: Config,
    source: Source,
    progress: bool = True,
    overwrite: bool = False,
    control: RemoteControl | None = None,
) -> ServeResult:
    """Reconstruct from `source` until it ends or SIGINT/SIGTERM (or `control` stops it, from
    another thread); save periodically and at the end, into a new run folder (`live_<source>_<preset>-<timestamp>`, or `run.name`). A save
    that fails (a full disk) is reported once in the log and the status and SLAM goes on; a
    final save that fails raises OutputError (the last complete save stays)."""
    device = resolve_device(config.run.device)
    config = with_live_bounds(complete_config(config, device, "tum"))  # a phone's depth is a real sensor's, as TUM's
    stem = f"live_{source.name}_{config.preset}"
    with new_run_folder(Path(config.run.output), stem, config.run.name, overwrite) as folder:
        recording = RecordingSource(source, folder / "recording") if config.live.record else None
        session = open_session(
            config,
            recording or source,
            folder,
            progress=progress,
            run_info=describe_run(source.name, True, config),
            save_every_s=config.live.save_every_s,
        )

        def add_status(graph: Graph) -> None:
            read = status_reader(session, graph)
            if progress:
                graph.services.append(partial(status_on_bar, session.sink, partial(bar_counters, session, graph)))
            if config.live.status_port:
                graph.services.append(partial(serve_status, config.live.status_host, config.live.status_port, read))
            if control is not None:
                graph.services.append(control.service(read))

        try:
            with signals_noted():
                report = execute_session(session, on_graph=add_status)
                if recording is not None:
                    recording.close()  # complete before the final save, and before the viewer lingers
                result = _save(session, report)
            if result.metrics is not None:
                m = result.metrics
                session.linger(run_summary(m["frames"], m["gaussians"], m["ate_rmse_cm"], None) + f"\n\nin {folder}")
            return result
        finally:
            if recording is not None:
                recording.close()
            session.close()


def _save(session: Session, report: RuntimeReport) -> ServeResult:
    """The final save (map, trajectory, checkpoint) and metrics.json."""
    if session.slam.gaussians is None:
        log.info("stopped before any frame was processed: nothing to save")
        return ServeResult(session.folder, None)
    session.saver.save_now(session.slam.checkpoint())
    metrics = _metrics(session, report)
    session.folder.write_metrics(metrics)
    return ServeResult(session.folder, metrics)


def _metrics(session: Session, report: RuntimeReport) -> dict[str, Any]:
    """metrics.json of a live run: frames, map size, the source's counters, timing, frame ages, live ATE."""
    config, slam, sink, source = session.config, session.slam, session.sink, session.source
    assert slam.gaussians is not None
    return {
        "source": source.name,
        "preset": config.preset,
        "frames": slam.frames_done,
        "gaussians": len(slam.gaussians),
        "lost_frames": sink.lost_frames,
        "relocalised_frames": sink.relocalised_frames,
        "unmapped_frames": sink.unmapped_frames,
        "counters": vars(source.counters),
        "device": describe(session.device, config),
        "versions": versions(),
        "runtime": report.summary(),
        "time": timing_summary(sink.results, report, sink.arrivals),
        "frame_age_ms": frame_age_ms(sink.results),
        "ate_rmse_cm": ate_so_far_cm(sink.results),
    }
