"""One SLAM session, built the same way for `run` and `serve` from a finished config and its
device (setup.py) and a claimed run folder: SLAM, its frame-boundary observers (periodic save,
viewer), the result sink, the graph, its execution (with the profiler when asked) and its metrics."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from functools import partial
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile

from pipeline.app.profiling import all_threads_config, summarise
from pipeline.app.report import timing_summary, versions
from pipeline.app.setup import Setup
from pipeline.compile_cache import compile_seconds
from pipeline.config import Config, switched_on
from pipeline.devices import describe
from pipeline.io.outputs.frame_row import FrameRow
from pipeline.io.outputs.intrinsics import IntrinsicsRecorder
from pipeline.io.outputs.periodic_save import FrameStamp, PeriodicSave
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.outputs.run_metrics import AteRecord, FrameAges, LoopRecord, RunMetrics
from pipeline.render import make_renderer
from pipeline.runtime import Graph, RuntimeReport, Service, execute
from pipeline.slam.handoff import FrameResult
from pipeline.slam.kernel_time import KernelSampler
from pipeline.slam.process.schedule import start_process_slam
from pipeline.slam.splatam import SplaTAM
from pipeline.slam.state import Checkpoint, LoopState
from pipeline.slam.view import SteppedSlam
from pipeline.source import Source
from pipeline.stages.frame_log import FrameLog
from pipeline.stages.odometry import FeatureDecode, OdometryUpload
from pipeline.stages.sinks import ResultConsumer, ResultSink
from pipeline.stages.slam import FrameObserver, slam_stage
from pipeline.stages.upload import make_uploader
from pipeline.stages.worker import ThreadedStage
from pipeline.ui.display import LiveFeed
from pipeline.ui.progress import ProgressBar
from pipeline.ui.viewer_feed import attach_viewer, release_on_stop

log = logging.getLogger("gsplatam")


@dataclass
class Session:
    config: Config
    device: torch.device
    folder: RunFolder
    slam: SteppedSlam
    source: Source
    sink: ResultSink
    bar: ProgressBar
    intrinsics: IntrinsicsRecorder
    saver: PeriodicSave
    viewer: LiveFeed | None = None  # viser, Open3D or rerun
    services: list[Service] = field(default_factory=list)
    kernels: KernelSampler | None = None  # the GPU's kernel busy fraction over a window (CUDA)

    @property
    def log(self) -> FrameLog:
        """The results so far, their arrival times and counts."""
        return self.sink.log

    def linger(self, summary: str) -> None:
        """After the run: the viewer, if any, keeps the final map up for its watchers (`summary`
        in markdown on it) until they close it or press Stop."""
        if self.viewer is not None:
            self.viewer.linger(summary)

    def close(self) -> None:
        """Close the viewer and end SLAM (a mapping process); safe to call twice. The rest closes
        when the graph ends."""
        if self.viewer is not None:
            self.viewer.close()
        self.slam.close()

    def metrics(
        self, report: RuntimeReport | None, ate: AteRecord | None, loops: LoopState | None = None
    ) -> RunMetrics:
        """What every metrics.json holds, a dataset's or a live session's: sizes, counts, device,
        the source's counters, frame ages, timing (`report`: None when the run failed), the ATE
        and loop closure's outcome (`loops`: the saved checkpoint's)."""
        config, slam, frames, device = self.config, self.slam, self.log, self.device
        peak = torch.cuda.max_memory_allocated(device) / 1e9 if device.type == "cuda" else None
        return RunMetrics(
            source=self.source.name,
            live=self.source.live,
            preset=config.preset,
            schedule=config.slam.schedule,
            mapping_process=slam.mapping_summary(),
            frames=slam.frames_done,
            frames_this_run=len(frames.results),
            gaussians=len(slam.gaussians) if slam.gaussians is not None else 0,
            lost_frames=frames.lost_frames,
            weak_frames=frames.weak_frames,
            relocalised_frames=frames.relocalised_frames,
            unmapped_frames=frames.unmapped_frames,
            between_keyframes=frames.between_keyframes,
            device=describe(device, config),
            versions=versions(),
            peak_gpu_memory_gb=peak,
            counters=dict(vars(self.source.counters)),
            frame_age_ms=FrameAges.of(frames.results),
            runtime=report.summary() if report is not None else {},
            time=timing_summary(frames, report) if report is not None else None,
            ate=ate,
            loops=None if loops is None else LoopRecord.of(loops.tally, loops.closed),
        )

    @property
    def observers(self) -> list[FrameObserver]:
        """Run after every frame in the SLAM thread; the viewer's last (it may pause SLAM)."""
        return [o for o in (self.intrinsics, self.saver, self.kernels, self.viewer) if o is not None]


def open_session(
    setup: Setup,
    source: Source,
    folder: RunFolder,
    *,
    progress: bool,
    run: RunDescription,
    save_every_s: float,
    stop_on_failure: bool = False,
    resume: Checkpoint | None = None,
    earlier: Sequence[FrameStamp] = (),
    total: int | None = None,
) -> Session:
    """Write the config into `folder` and build SLAM (continuing from `resume`, whose frames'
    stamps are `earlier`), the result sink (frames.csv and a bar over `total` frames), the
    periodic save (every `save_every_s`; on a write failure it stops the run if
    `stop_on_failure`, else reports it) and the viewer (when the config enables it). `run`
    goes into every checkpoint."""
    config, device = setup.config, setup.device
    folder.write_config(config)
    log.info("device: %s; run folder: %s", describe(device, config), folder.path)
    slam = _slam_of(config, source, device)
    initial = 0
    if resume is not None:
        slam.restore(resume)
        initial = resume.frames_done
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    viewer = attach_viewer(config, slam.renderer, device, folder, f"gsplatam: {source.name}")  # first: may be missing
    saver = PeriodicSave(folder, run, save_every_s, earlier, stop_on_failure)
    frames = FrameLog()
    bar = ProgressBar(frames, total, initial, progress)
    sink = ResultSink(frames, [_frame_rows(folder, saver), bar])
    services: list[Service] = [partial(release_on_stop, viewer)] if viewer else []
    intrinsics = IntrinsicsRecorder(folder.intrinsics)
    sampled = switched_on(config.run.kernel_sample, device.type == "cuda")
    kernels = KernelSampler(slam.sample_kernels) if sampled else None
    return Session(config, device, folder, slam, source, sink, bar, intrinsics, saver, viewer, services, kernels)


def _slam_of(config: Config, source: Source, device: torch.device) -> SteppedSlam:
    """SLAM of the configured schedule: mapping in this thread, or beside it in a process or a
    thread of its own."""
    if config.slam.schedule in ("process", "thread"):
        return start_process_slam(config, device, source.live)
    return SplaTAM(config, make_renderer(config.render, config.gaussians, device), device)


def _frame_rows(folder: RunFolder, saver: PeriodicSave) -> ResultConsumer:
    """Each result's row into frames.csv; a row that cannot be written is reported as a failed
    save (a dataset run then stops, a live daemon goes on)."""

    def write(result: FrameResult) -> None:
        try:
            folder.append_frame(FrameRow.of(result))
        except OSError as exc:
            saver.report_failure(f"the row of frame {result.index} in frames.csv", exc)

    return write


def slam_stage_of(session: Session) -> ThreadedStage:
    """SLAM per frame, with the session's observers (and, live on CUDA, a warm-up)."""
    slam, source = session.slam, session.source
    warm_up = source.live and switched_on(session.config.live.warm_up, session.device.type == "cuda")
    return slam_stage(slam, source.last_index, session.observers, source.live, warm_up)


def graph_of(session: Session) -> Graph:
    """source -> decode -> upload -> SLAM (with its observers) -> sink; with visual odometry
    (`tracking.odometry`), image features in decode and each frame's motion before its upload."""
    config, tracking = session.config, session.config.tracking
    upload = make_uploader(session.device, slots=config.run.queue_size + 2)
    odometry = tracking.odometry == "features"
    return Graph(
        source=session.source,
        upload=OdometryUpload(upload, tracking.odometry_min_inliers) if odometry else upload,
        slam=slam_stage_of(session),
        sink=session.sink,
        queue_size=config.run.queue_size,
        services=list(session.services),
        decode=FeatureDecode(session.source.decode, tracking.odometry_features) if odometry else None,
    )


def execute_session(
    session: Session, profile_trace: bool = False, on_graph: Callable[[Graph], None] | None = None
) -> RuntimeReport:
    """Run the session's graph to the end of its source or a stop; sink and saver are closed
    and the viewer shows the final state whatever happens (`Session.close` closes it). `on_graph`
    sees the graph before it runs (the status endpoint)."""
    if profile_trace:
        session.kernels = None  # the profiler records every kernel already (one profiler at a time)
    graph = graph_of(session)
    if on_graph is not None:
        on_graph(graph)
    compiled_before = compile_seconds()
    try:
        if not profile_trace:
            report = execute(graph, session.config.run.loader)
        else:
            report = _profiled(graph, session)
        compiled_after = compile_seconds()
        if compiled_before is not None and compiled_after is not None:
            report.compile_s = compiled_after - compiled_before
        if session.kernels is not None:
            session.kernels.close(session.slam.frames_done)
            sample = session.kernels.sample
            report.kernel_sample = None if sample is None else asdict(sample)
        return report
    finally:
        session.bar.close()
        session.saver.close()
        session.folder.close()
        if session.viewer is not None:
            session.viewer.finish()  # the final map on screen; it stays up until Session.close


def _profiled(graph: Graph, session: Session) -> RuntimeReport:
    """Run under the torch profiler; write its trace and profile.txt into the run folder."""
    cuda = session.device.type == "cuda"
    folder = session.folder
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities, experimental_config=all_threads_config()) as prof:
        report = execute(graph, session.config.run.loader)
    folder.write_trace(lambda path: prof.export_chrome_trace(str(path)))
    summary, table = summarise(prof, cuda, report.wall_s)
    report.profile = summary
    folder.write_profile(_profile_text(summary, table, report.wall_s, cuda))
    log.info("profile: %s and %s", folder.trace, folder.profile)
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
