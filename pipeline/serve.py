"""The `serve` daemon: live reconstruction from a phone, until SIGINT/SIGTERM.

The same runtime as `run`, with a live source (keep-newest back-pressure, reconnection inside
the source, so SLAM maps into one map across disconnections), a periodic save, and a JSON
status endpoint on localhost.
"""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterable, Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.config import Config, with_dataset_defaults
from pipeline.devices import describe, resolve_device
from pipeline.frame import Frame
from pipeline.io.run_folder import RunFolder
from pipeline.io.status_http import serve_status
from pipeline.metrics import absolute_trajectory_error
from pipeline.render import make_renderer, resolve_backend
from pipeline.run import slam_graph, timing_summary, versions
from pipeline.runtime import Graph, execute
from pipeline.slam.splatam import FrameResult, SplaTAM
from pipeline.stages.periodic_save import PeriodicSave
from pipeline.stages.sinks import ResultSink
from pipeline.stages.viewer_feed import attach_viewer

log = logging.getLogger("gsplatam")

FPS_WINDOW = 10  # frames over which the status endpoint's fps is measured


@dataclass
class LiveInput:
    """A live source and the function that turns its items into frames (None: unusable)."""

    name: str
    source: AsyncIterable[Any]
    decode: Callable[[Any], Frame | None]
    counters: Any  # the source's dataclass of counters, reported by the status endpoint


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


def status_reader(live: LiveInput, graph: Graph, sink: ResultSink) -> Callable[[], dict[str, Any]]:
    """The status endpoint's view of the daemon (read on the event loop; plain attribute reads)."""

    def read() -> dict[str, Any]:
        results, arrivals = sink.results, sink.arrivals
        recent = arrivals[-FPS_WINDOW:]
        fps = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and recent[-1] > recent[0] else 0.0
        source_queue = graph.queues.get("source")
        last = results[-1] if results else None
        return {
            "source": live.name,
            **vars(live.counters),
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


def serve(config: Config, live: LiveInput, progress: bool = True) -> ServeResult:
    device = resolve_device(config.run.device)
    config = with_dataset_defaults(config, "tum")  # a phone's depth is a real sensor's, as TUM's
    config = replace(config, render=replace(config.render, backend=resolve_backend(config.render, device)))
    folder = RunFolder(Path(config.run.output) / (config.run.name or f"live_{live.name}_{config.preset}"))
    folder.write_config(config)
    log.info("device: %s; run folder: %s", describe(device, config), folder.path)

    slam = SplaTAM(config, make_renderer(config.render, config.gaussians, device), device)
    saver = PeriodicSave(folder, config.live.save_every_s)
    sink = ResultSink(folder, total=None, progress=progress)
    viewer = attach_viewer(config, slam, folder, f"gsplatam: live {live.name}")
    # Live input never waits for SLAM: the queue keeps the newest frames and counts the drops.
    graph = slam_graph(config, slam, live.source, "keep_newest", live.decode, sink, None, [saver], viewer)
    if config.live.status_port:
        read = status_reader(live, graph, sink)
        graph.services.append(partial(serve_status, config.live.status_host, config.live.status_port, read))
    try:
        report = execute(graph, "pipelined")
    finally:
        sink.close()
        saver.close()
        if viewer is not None:
            viewer.close()
    if slam.state.gaussians is None:
        log.info("stopped before any frame was processed: nothing to save")
        return ServeResult(folder, None)
    saver.save_now(slam)
    metrics = {
        "source": live.name,
        "preset": config.preset,
        "frames": slam.frames_done,
        "gaussians": len(slam.state.gaussians),
        "lost_frames": sink.lost_frames,
        "counters": vars(live.counters),
        "device": describe(device, config),
        "versions": versions(),
        "runtime": report.summary(),
        "time": timing_summary(sink.results, report, sink.arrivals),
        "ate_rmse_cm": live_ate_cm(sink.results),
    }
    folder.write_metrics(metrics)
    return ServeResult(folder, metrics)
