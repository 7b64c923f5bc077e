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
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from pipeline.app.report import run_summary, timing_summary, versions
from pipeline.app.session import Session, complete_config, execute_session, open_session
from pipeline.config import Config
from pipeline.devices import describe, resolve_device
from pipeline.io.live.recording import RecordingSource
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.ui.status_http import serve_status
from pipeline.runtime import Graph, RuntimeReport
from pipeline.source import Source
from pipeline.stages.sinks import ResultSink, ate_so_far_cm, recent_fps

log = logging.getLogger("gsplatam")

BAR_EVERY_S = 1.0  # the progress bar's live counters are refreshed this often


@dataclass
class ServeResult:
    folder: RunFolder
    metrics: dict[str, Any] | None  # None when no frame was processed


def status_reader(session: Session, graph: Graph) -> Callable[[], dict[str, Any]]:
    """The status endpoint's view of the daemon (read on the event loop; plain attribute reads)."""
    source, sink = session.source, session.sink

    def read() -> dict[str, Any]:
        results, arrivals = sink.results, sink.arrivals
        source_queue = graph.queues.get("source")
        last = results[-1] if results else None
        return {
            "source": source.name,
            **vars(source.counters),
            "processed": len(results),
            "dropped": source_queue.dropped if source_queue is not None else 0,
            "fps": recent_fps(arrivals),
            "gaussians": last.gaussians if last else 0,
            "tracking": "waiting" if last is None else ("lost: " + last.lost if last.lost else "ok"),
            "lost_frames": sink.lost_frames,
            "last_frame_ms": 1000 * last.seconds["total"] if last else None,
            "seconds_since_last_frame": time.perf_counter() - arrivals[-1] if arrivals else None,
            "ate_rmse_cm": ate_so_far_cm(results),
        }

    return read


async def status_on_bar(sink: ResultSink, read: Callable[[], dict[str, Any]], stop: asyncio.Event) -> None:
    """A runtime service: the daemon's counters on the progress bar, every BAR_EVERY_S, until `stop`."""
    while not stop.is_set():
        status = read()
        age = status["seconds_since_last_frame"]
        fields = {k: status[k] for k in ("received", "processed", "dropped")}
        sink.show(fields | {"age": "-" if age is None else f"{age:.1f}s"})
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), BAR_EVERY_S)


def serve(config: Config, source: Source, progress: bool = True) -> ServeResult:
    """Reconstruct from `source` until it ends or SIGINT/SIGTERM; save periodically and at the end."""
    device = resolve_device(config.run.device)
    config = complete_config(config, device, "tum")  # a phone's depth is a real sensor's, as TUM's
    folder = Path(config.run.output) / (config.run.name or f"live_{source.name}_{config.preset}")
    recording = RecordingSource(source, folder / "recording") if config.live.record else None
    source = recording or source
    session = open_session(config, source, folder, progress=progress, save_every_s=config.live.save_every_s)

    def add_status(graph: Graph) -> None:
        read = status_reader(session, graph)
        graph.services.append(partial(status_on_bar, session.sink, read))
        if config.live.status_port:
            graph.services.append(partial(serve_status, config.live.status_host, config.live.status_port, read))

    try:
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
    config, slam, sink, source = session.config, session.slam, session.sink, session.source
    if slam.state.gaussians is None:
        log.info("stopped before any frame was processed: nothing to save")
        return ServeResult(session.folder, None)
    assert session.saver is not None
    session.saver.save_now(slam)
    metrics = {
        "source": source.name,
        "preset": config.preset,
        "frames": slam.frames_done,
        "gaussians": len(slam.state.gaussians),
        "lost_frames": sink.lost_frames,
        "counters": vars(source.counters),
        "device": describe(session.device, config),
        "versions": versions(),
        "runtime": report.summary(),
        "time": timing_summary(sink.results, report, sink.arrivals),
        "ate_rmse_cm": ate_so_far_cm(sink.results),
    }
    session.folder.write_metrics(metrics)
    return ServeResult(session.folder, metrics)
