"""One SLAM session, built the same way for `run` and `serve`: device, run folder, SLAM,
its frame-boundary observers (periodic save, viewer), the graph, and its execution (with the
profiler when asked)."""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile

from pipeline.app.profiling import all_threads_config, summarise
from pipeline.config import Config, switched_on, with_dataset_defaults
from pipeline.devices import describe, resolve_device
from pipeline.files.atomic import atomic_write_text
from pipeline.outputs.intrinsics import IntrinsicsRecorder
from pipeline.outputs.periodic_save import FrameStamp, PeriodicSave
from pipeline.outputs.run_folder import RunFolder
from pipeline.render import make_renderer, resolve_backend
from pipeline.runtime import Graph, RuntimeReport, Service, execute
from pipeline.slam.splatam import SplaTAM
from pipeline.slam.state import Checkpoint
from pipeline.source import Source
from pipeline.stages.sinks import ResultSink
from pipeline.stages.slam import FrameObserver, overlapped_stages, sequential_stages
from pipeline.stages.upload import make_uploader
from pipeline.stages.worker import ThreadedStage
from pipeline.ui.viewer_feed import ViewerFeed, attach_viewer, release_on_stop

log = logging.getLogger("gsplatam")


def complete_config(config: Config, device: torch.device, dataset_format: str) -> Config:
    """The config as the run uses it: the render backend resolved for `device` and the values
    SplaTAM tunes per dataset family filled in (written into the run folder as such)."""
    config = with_dataset_defaults(config, dataset_format)
    return replace(config, render=replace(config.render, backend=resolve_backend(config.render, device)))


@dataclass
class Session:
    config: Config
    device: torch.device
    folder: RunFolder
    slam: SplaTAM
    source: Source
    sink: ResultSink
    intrinsics: IntrinsicsRecorder
    saver: PeriodicSave
    viewer: ViewerFeed | None = None
    services: list[Service] = field(default_factory=list)

    def linger(self, summary: str) -> None:
        """After the run: the viewer, if any, keeps the final map up for its watchers (`summary`
        in markdown on it) until they close it or press Stop."""
        if self.viewer is not None:
            self.viewer.linger(summary)

    def close(self) -> None:
        """Close the viewer (safe to call twice); the rest closes when the graph ends."""
        if self.viewer is not None:
            self.viewer.close()

    @property
    def observers(self) -> list[FrameObserver]:
        """Run after every frame in the SLAM thread; the viewer's last (it may pause SLAM)."""
        return [o for o in (self.intrinsics, self.saver, self.viewer) if o is not None]


def describe_run(source: str, live: bool, config: Config, **details: Any) -> dict[str, Any]:
    """What a checkpoint records of its run, so that a resume can tell it continues the same one:
    the source's name, whether it is live, the kind of map, and `details` (JSON-able: sizes, slicing)."""
    gaussians = {"gaussians": config.gaussians.kind, "isotropic": config.gaussians.isotropic}
    return {"source": source, "live": live, **gaussians, **details}


def open_session(
    config: Config,
    source: Source,
    folder: Path,
    *,
    progress: bool,
    run_info: dict[str, Any],
    save_every_s: float,
    stop_on_failure: bool = False,
    resume: Checkpoint | None = None,
    earlier: Sequence[FrameStamp] = (),
    total: int | None = None,
) -> Session:
    """Write the config into `folder` and build SLAM (continuing from `resume`, whose frames'
    stamps are `earlier`), the result sink (a bar over `total` frames), the periodic save (every
    `save_every_s`; on a write failure it stops the run if `stop_on_failure`, else reports it)
    and the viewer (when the config enables it). `config` must be complete (`complete_config`);
    `run_info` (`describe_run`) goes into every checkpoint."""
    device = resolve_device(config.run.device)
    run_folder = RunFolder(folder, run_info)
    run_folder.write_config(config)
    log.info("device: %s; run folder: %s", describe(device, config), run_folder.path)
    slam = SplaTAM(config, make_renderer(config.render, config.gaussians, device), device)
    initial = 0
    if resume is not None:
        slam.restore(resume)
        initial = resume.frames_done
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    viewer = attach_viewer(config, slam.renderer, run_folder, f"gsplatam: {source.name}")  # first: it may be missing
    saver = PeriodicSave(run_folder, save_every_s, earlier, stop_on_failure)
    sink = ResultSink(run_folder.append_frames, total, initial, progress, on_write_error=saver.report_failure)
    services: list[Service] = [partial(release_on_stop, viewer)] if viewer else []
    intrinsics = IntrinsicsRecorder(run_folder.intrinsics)
    return Session(config, device, run_folder, slam, source, sink, intrinsics, saver, viewer, services)


def slam_stages(session: Session) -> list[ThreadedStage]:
    """The SLAM stages of the configured schedule."""
    slam, source, schedule = session.slam, session.source, session.config.slam
    warm_up = source.live and switched_on(session.config.live.warm_up, session.device.type == "cuda")
    if schedule.schedule == "overlapped":
        return overlapped_stages(slam, source.last_index, session.observers, schedule.max_lead, source.live, warm_up)
    return sequential_stages(slam, source.last_index, session.observers, source.live, warm_up)


def graph_of(session: Session) -> Graph:
    """source -> decode -> upload -> SLAM (with its observers) -> sink."""
    config = session.config
    return Graph(
        source=session.source,
        upload=make_uploader(session.device, slots=config.run.queue_size + 2),
        slam=slam_stages(session),
        sink=session.sink,
        queue_size=config.run.queue_size,
        services=list(session.services),
    )


def execute_session(
    session: Session, profile_trace: bool = False, on_graph: Callable[[Graph], None] | None = None
) -> RuntimeReport:
    """Run the session's graph to the end of its source or a stop; sink and saver are closed
    and the viewer shows the final state whatever happens (`Session.close` closes it). `on_graph`
    sees the graph before it runs (the status endpoint)."""
    graph = graph_of(session)
    if on_graph is not None:
        on_graph(graph)
    try:
        if not profile_trace:
            return execute(graph, session.config.run.loader)
        return _profiled(graph, session)
    finally:
        session.sink.close()
        session.saver.close()
        session.folder.close()
        if session.viewer is not None:
            session.viewer.finish()  # the final map on screen; it stays up until Session.close


def _profiled(graph: Graph, session: Session) -> RuntimeReport:
    """Run under the torch profiler; write trace.json and profile.txt into the run folder."""
    cuda = session.device.type == "cuda"
    folder = session.folder.path
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities, experimental_config=all_threads_config()) as prof:
        report = execute(graph, session.config.run.loader)
    partial_trace = folder / ".trace.json.tmp"  # the profiler writes the file itself: renamed when complete
    try:
        prof.export_chrome_trace(str(partial_trace))
        os.replace(partial_trace, folder / "trace.json")
    except BaseException:
        with contextlib.suppress(OSError):
            partial_trace.unlink()
        raise
    summary, table = summarise(prof, cuda, report.wall_s)
    report.profile = summary
    atomic_write_text(folder / "profile.txt", _profile_text(summary, table, report.wall_s, cuda))
    log.info("profile: %s and %s", folder / "trace.json", folder / "profile.txt")
    return report


def _profile_text(summary: dict[str, Any], table: str, wall_s: float, cuda: bool) -> str:
    stages = "\n".join(
        f"  {name:<10} {v['count']:>5} calls  host {v['cpu_ms']:9.1f} ms  device {v['device_ms']:9.1f} ms"
        for name, v in summary["stages"].items()
    )
    busy = (
        f"kernels and copies busy the GPU for {summary['kernel_busy_ms']:.0f} ms of {1000 * wall_s:.0f} ms wall "
        f"({summary['kernel_busy_fraction']:.1%})\n"
        if cuda
        else ""
    )
    return f"{busy}per stage:\n{stages}\n\n{table}\n"
