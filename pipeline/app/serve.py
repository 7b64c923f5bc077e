"""The `serve` daemon: live reconstruction from a phone, until SIGINT/SIGTERM.

The same session as `run`, with a live source (keep-newest queues; reconnection inside the
source, so SLAM maps into one map across disconnections), a periodic save and a JSON status
endpoint on localhost.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.app.remote_control import RemoteControl
from pipeline.app.report import timing_summary, versions
from pipeline.app.session import Session, complete_config, execute_session, open_session
from pipeline.config import Config
from pipeline.devices import describe, resolve_device
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.ui.status_http import serve_status
from pipeline.metrics import absolute_trajectory_error
from pipeline.runtime import Graph
from pipeline.slam.splatam import FrameResult
from pipeline.source import Source

log = logging.getLogger("gsplatam")

FPS_WINDOW = 10  # frames over which the status endpoint's fps is measured


@dataclass
class ServeResult:
    folder: RunFolder
    metrics: dict[str, Any] | None  # None when no frame was processed


def live_ate_cm(results: list[FrameResult]) -> float | None:
    """ATE RMSE (cm) of the frames that came with a reference pose (NeRFCapture's device pose
    when live.device_pose = groundtruth); None with fewer than 3."""
    pairs = [(r.c2w, r.c2w_gt) for r in results if r.c2w_gt is not None]
    if len(pairs) < 3:
        return None
    estimated = np.stack([e.double().numpy() for e, _ in pairs])
    reference = np.stack([g.double().numpy() for _, g in pairs])
    return 100 * absolute_trajectory_error(estimated, reference).rmse_m


def status_reader(session: Session, graph: Graph) -> Callable[[], dict[str, Any]]:
    """The status endpoint's view of the daemon (read on the event loop; plain attribute reads)."""
    source, sink = session.source, session.sink

    def read() -> dict[str, Any]:
        results, arrivals = sink.results, sink.arrivals
        recent = arrivals[-FPS_WINDOW:]
        fps = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and recent[-1] > recent[0] else 0.0
        source_queue = graph.queues.get("source")
        last = results[-1] if results else None
        return {
            "source": source.name,
            **vars(source.counters),
            "processed": len(results),
            "dropped": source_queue.dropped if source_queue is not None else 0,
            "fps": fps,
            "gaussians": last.gaussians if last else 0,
            "tracking": "waiting" if last is None else ("lost: " + last.lost if last.lost else "ok"),
            "lost_frames": sink.lost_frames,
            "last_frame_ms": 1000 * last.seconds["total"] if last else None,
            "seconds_since_last_frame": time.perf_counter() - arrivals[-1] if arrivals else None,
            "ate_rmse_cm": live_ate_cm(results),
        }

    return read


def serve(config: Config, source: Source, progress: bool = True, control: RemoteControl | None = None) -> ServeResult:
    """Reconstruct from `source` until it ends or SIGINT/SIGTERM (or `control` stops it, from
    another thread); save periodically and at the end."""
    device = resolve_device(config.run.device)
    config = complete_config(config, device, "tum")  # a phone's depth is a real sensor's, as TUM's
    folder = Path(config.run.output) / (config.run.name or f"live_{source.name}_{config.preset}")
    session = open_session(config, source, folder, progress=progress, save_every_s=config.live.save_every_s)

    def add_status(graph: Graph) -> None:
        read = status_reader(session, graph)
        if config.live.status_port:
            graph.services.append(partial(serve_status, config.live.status_host, config.live.status_port, read))
        if control is not None:
            graph.services.append(control.service(read))

    report = execute_session(session, on_graph=add_status)
    slam, sink = session.slam, session.sink
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
        "device": describe(device, config),
        "versions": versions(),
        "runtime": report.summary(),
        "time": timing_summary(sink.results, report, sink.arrivals),
        "ate_rmse_cm": live_ate_cm(sink.results),
    }
    session.folder.write_metrics(metrics)
    return ServeResult(session.folder, metrics)
