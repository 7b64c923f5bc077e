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
import torch

from pipeline.app.report import timing_summary, versions
from pipeline.app.run_folders import new_run_folder
from pipeline.app.session import Session, complete_config, describe_run, execute_session, open_session
from pipeline.app.signals import signals_noted
from pipeline.config import Config
from pipeline.devices import describe, resolve_device
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.ui.status_http import serve_status
from pipeline.metrics import absolute_trajectory_error
from pipeline.runtime import Graph, RuntimeReport
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
            "save_error": session.saver.error or None,
            "saved_frames": session.saver.saved_frames,
        }

    return read


def serve(config: Config, source: Source, progress: bool = True, overwrite: bool = False) -> ServeResult:
    """Reconstruct from `source` until it ends or SIGINT/SIGTERM; save periodically and at the
    end, into a new run folder (`live_<source>_<preset>-<timestamp>`, or `run.name`). A save
    that fails (a full disk) is reported once in the log and the status and SLAM goes on; a
    final save that fails raises OutputError (the last complete save stays)."""
    device = resolve_device(config.run.device)
    config = complete_config(config, device, "tum")  # a phone's depth is a real sensor's, as TUM's
    stem = f"live_{source.name}_{config.preset}"
    with new_run_folder(Path(config.run.output), stem, config.run.name, overwrite) as folder:
        session = open_session(
            config,
            source,
            folder,
            progress=progress,
            run_info=describe_run(source.name, True, config),
            save_every_s=config.live.save_every_s,
        )

        def add_status(graph: Graph) -> None:
            if config.live.status_port:
                read = status_reader(session, graph)
                graph.services.append(partial(serve_status, config.live.status_host, config.live.status_port, read))

        with signals_noted():
            report = execute_session(session, on_graph=add_status)
            if session.slam.state.gaussians is None:
                log.info("stopped before any frame was processed: nothing to save")
                return ServeResult(session.folder, None)
            session.saver.save_now(session.slam)
            metrics = _metrics(session, report, device)
            session.folder.write_metrics(metrics)
    return ServeResult(session.folder, metrics)


def _metrics(session: Session, report: RuntimeReport, device: torch.device) -> dict[str, Any]:
    """metrics.json of a live run: frames, map size, the source's counters, timing, live ATE."""
    config, slam, sink, source = session.config, session.slam, session.sink, session.source
    assert slam.state.gaussians is not None
    return {
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
