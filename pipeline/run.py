"""The `run` job: SLAM over a dataset through the runtime, then metrics and outputs."""

from __future__ import annotations

import logging
import math
import os
import platform
import subprocess
from collections.abc import AsyncIterable, Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile, record_function
from tqdm import tqdm

from pipeline.config import Config, with_dataset_defaults
from pipeline.devices import describe, resolve_device, synthetic_for
from pipeline.errors import UserError
from pipeline.frame import Frame
from pipeline.io.dataset import Dataset, open_dataset
from pipeline.io.run_folder import RunFolder
from pipeline.io.synth_writer import cached_synthetic
from pipeline.metrics import absolute_trajectory_error, view_quality
from pipeline.profiling import all_threads_config, summarise
from pipeline.render import make_renderer, resolve_backend
from pipeline.runtime import Graph, RuntimeReport, execute
from pipeline.slam.splatam import FrameResult, SplaTAM
from pipeline.stages.queues import Policy
from pipeline.stages.sinks import ResultSink
from pipeline.stages.slam import FrameObserver, SlamStep
from pipeline.stages.source import DatasetSource
from pipeline.stages.upload import make_uploader
from pipeline.stages.viewer_feed import ViewerFeed, attach_viewer, release_on_stop

log = logging.getLogger("gsplatam")

WARMUP_FRAMES = 2  # frame 0 (map initialisation) and frame 1 (first tracking: compilation) are left out of timing means


@dataclass
class RunResult:
    folder: RunFolder
    metrics: dict[str, Any] | None  # None when interrupted before the first frame


def prepare_dataset(config: Config, device: torch.device, output: Path, progress: bool) -> tuple[Dataset, Config]:
    """Open the configured dataset (generating the embedded synthetic scene when none is given)."""
    dataset_config = config.dataset
    if not dataset_config.path:
        synthetic = synthetic_for(config.synthetic, device)
        path = cached_synthetic(output / "synthetic", synthetic, progress, device)
        dataset_config = replace(dataset_config, path=str(path), format=synthetic.layout)
        config = replace(config, synthetic=synthetic, dataset=dataset_config)
    dataset = open_dataset(dataset_config)
    return dataset, with_dataset_defaults(config, dataset.format)


def in_profiler_range(name: str, fn: Callable[[Any], Any], item: Any) -> Any:
    """`fn(item)` inside a named profiler range (the stage's name in traces)."""
    with record_function(name):
        return fn(item)


def run_slam(
    config: Config, resume: Path | None = None, profile_trace: bool = False, progress: bool = True
) -> RunResult:
    device = resolve_device(config.run.device)
    output = Path(config.run.output)
    dataset, config = prepare_dataset(config, device, output, progress)
    folder = RunFolder(
        resume if resume is not None else output / (config.run.name or f"{dataset.name}_{config.preset}")
    )
    backend = resolve_backend(config.render, device)
    config = replace(config, render=replace(config.render, backend=backend))
    folder.write_config(config)
    log.info("device: %s", describe(device, config))
    log.info("dataset: %s (%s, %d frames); run folder: %s", dataset.name, dataset.format, len(dataset), folder.path)

    slam = SplaTAM(config, make_renderer(config.render, config.gaussians, device), device)
    start_at = 0
    if resume is not None:
        start_at = _load_checkpoint(folder, slam)
        if start_at >= len(dataset):
            raise UserError(f"{folder.path} already holds all {len(dataset)} frames")
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)

    sink = ResultSink(folder, total=len(dataset), initial=start_at, progress=progress)
    viewer = attach_viewer(config, slam, folder, f"gsplatam: {dataset.name}")
    source = DatasetSource(dataset, start_at)
    graph = slam_graph(config, slam, source, "block", dataset.decode, sink, len(dataset) - 1, [], viewer)
    try:
        report = _execute(graph, config, folder, profile_trace, device)
    finally:
        sink.close()
        if viewer is not None:
            viewer.close()
    if slam.state.gaussians is None:
        if report.interrupted:
            log.info("interrupted before the first frame was processed: nothing to write")
            return RunResult(folder, None)
        raise UserError("no frame was processed")
    metrics = _finish(config, dataset, folder, slam, sink, report, device, progress)
    return RunResult(folder, metrics)


def slam_graph(
    config: Config,
    slam: SplaTAM,
    source: AsyncIterable[Any],
    policy: Policy,
    decode: Callable[[Any], Frame | None],
    sink: ResultSink,
    last_index: int | None,
    observers: list[FrameObserver],
    viewer: ViewerFeed | None,
) -> Graph:
    """The graph `run` and `serve` drive: source -> decode -> upload -> SLAM (with its
    frame-boundary observers, the viewer's last) -> sink, each stage in its profiler range."""
    uploader = make_uploader(slam.device, slots=config.run.queue_size + 2)
    return Graph(
        source=source,
        source_policy=policy,
        decode=partial(in_profiler_range, "decode", decode),
        upload=partial(in_profiler_range, "upload", uploader),
        slam=SlamStep(slam, last_index, observers=observers + ([viewer] if viewer else [])),
        sink=sink,
        queue_size=config.run.queue_size,
        services=[partial(release_on_stop, viewer)] if viewer else [],
    )


def _execute(
    graph: Graph, config: Config, folder: RunFolder, profile_trace: bool, device: torch.device
) -> RuntimeReport:
    if not profile_trace:
        return execute(graph, config.run.loader)
    cuda = device.type == "cuda"
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities, experimental_config=all_threads_config()) as prof:
        report = execute(graph, config.run.loader)
    prof.export_chrome_trace(str(folder.path / "trace.json"))
    summary, table = summarise(prof, cuda, report.wall_s)
    report.profile = summary
    stages = "\n".join(
        f"  {name:<10} {v['count']:>5} calls  host {v['cpu_ms']:9.1f} ms  device {v['device_ms']:9.1f} ms"
        for name, v in summary["stages"].items()
    )
    busy = (
        f"kernels and copies busy the GPU for {summary['kernel_busy_ms']:.0f} ms of {1000 * report.wall_s:.0f} ms wall "
        f"({summary['kernel_busy_fraction']:.1%})\n"
        if cuda
        else ""
    )
    (folder.path / "profile.txt").write_text(f"{busy}per stage:\n{stages}\n\n{table}\n")
    log.info("profile: %s and %s", folder.path / "trace.json", folder.path / "profile.txt")
    return report


def _load_checkpoint(folder: RunFolder, slam: SplaTAM) -> int:
    if not folder.checkpoint.exists():
        raise UserError(f"no checkpoint to resume from in {folder.path}")
    payload = torch.load(folder.checkpoint, map_location="cpu", weights_only=False)
    slam.load_state_dict(payload["slam"])
    return int(payload["frames_done"])


def _finish(
    config: Config,
    dataset: Dataset,
    folder: RunFolder,
    slam: SplaTAM,
    sink: ResultSink,
    report: RuntimeReport,
    device: torch.device,
    progress: bool,
) -> dict[str, Any]:
    """Write trajectory, map, checkpoint and metrics; evaluate unless the run was interrupted."""
    results = sink.results
    state = slam.state
    assert state.gaussians is not None
    done = slam.frames_done
    refs = dataset.refs[:done]
    timestamps = np.array([r.timestamp for r in refs])
    reference = np.stack([r.c2w_gt for r in refs]) if all(r.c2w_gt is not None for r in refs) else None
    saved = slam.state_dict()
    folder.write_state(saved, timestamps, reference)
    estimated = saved["poses"].double().numpy()

    metrics: dict[str, Any] = {
        "dataset": dataset.name,
        "preset": config.preset,
        "frames": done,
        "frames_this_run": len(results),
        "interrupted": report.interrupted,
        "gaussians": len(state.gaussians),
        "lost_frames": sum(bool(r.lost) for r in results),
        "device": describe(device, config),
        "versions": versions(),
        "runtime": report.summary(),
        "time": timing_summary(results, report, sink.arrivals),
        "ate": None,
        "render": None,
    }
    if device.type == "cuda":
        metrics["peak_gpu_memory_gb"] = torch.cuda.max_memory_allocated(device) / 1e9
    if reference is not None and done >= 2:
        ate = absolute_trajectory_error(estimated, reference)
        metrics["ate"] = {
            "rmse_cm": 100 * ate.rmse_m,
            "mean_cm": 100 * ate.mean_m,
            "median_cm": 100 * ate.median_m,
            "max_cm": 100 * ate.max_m,
            "frames": ate.frames,
            "alignment": "rigid (rotation + translation, no scale), least squares over camera centres",
        }
    if not report.interrupted:
        metrics["render"] = _render_metrics(config, dataset, slam, device, progress)
    folder.write_metrics(metrics)
    return metrics


def timing_summary(results: list[FrameResult], report: RuntimeReport, arrivals: list[float]) -> dict[str, Any]:
    timed = [r for r in results if r.index >= WARMUP_FRAMES] or results
    mean = {
        k: float(np.mean([r.seconds[k] for r in timed])) if timed else math.nan
        for k in ("tracking", "densify", "mapping", "total")
    }
    return {
        "tracking_s": mean["tracking"],
        "densify_s": mean["densify"],
        "mapping_s": mean["mapping"],
        "total_s": mean["total"],
        "frames_timed": len(timed),
        "warmup_frames_excluded": WARMUP_FRAMES,
        "fps_wall": report.frames / report.wall_s if report.wall_s > 0 else 0.0,
        "fps_steady": _steady_fps(arrivals),
    }


def _steady_fps(arrivals: list[float]) -> float | None:
    """Frames per second of wall time after the warm-up frames: what a long run sustains."""
    if len(arrivals) <= WARMUP_FRAMES + 1:
        return None
    return (len(arrivals) - 1 - WARMUP_FRAMES) / (arrivals[-1] - arrivals[WARMUP_FRAMES])


def _render_metrics(
    config: Config, dataset: Dataset, slam: SplaTAM, device: torch.device, progress: bool
) -> dict[str, Any]:
    """PSNR, SSIM and depth L1 of the final map rendered at the estimated poses, every Nth frame."""
    state = slam.state
    assert state.gaussians is not None
    uploader = make_uploader(device, slots=2)
    picks = list(range(0, slam.frames_done, config.run.eval_every))
    scores = []
    for i in tqdm(picks, desc="evaluate", unit="frame", disable=not progress, dynamic_ncols=True):
        frame = uploader(dataset.decode(dataset.refs[i])).wait()
        scores.append(
            view_quality(slam.renderer, state.gaussians, frame, state.poses[i], config.render.near, config.render.far)
        )
    return {
        "psnr_db": float(np.mean([s.psnr_db for s in scores])),
        "ssim": float(np.mean([s.ssim for s in scores])),
        "depth_l1_cm": float(np.mean([s.depth_l1_cm for s in scores])),
        "frames_evaluated": len(scores),
        "every": config.run.eval_every,
        "pixels": "valid-depth pixels only",
    }


def versions() -> dict[str, str | None]:
    found: dict[str, str | None] = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
    }
    try:
        from importlib.metadata import version

        found["gsplat"] = version("gsplat")
    except Exception:
        found["gsplat"] = None
    found["commit"] = os.environ.get("GSPLATAM_COMMIT")  # set by bench/gpu_suite.sh: a device copy's git is stale
    if not found["commit"]:
        try:
            found["commit"] = subprocess.run(
                ["git", "rev-parse", "--short", "HEAD"],
                capture_output=True,
                text=True,
                check=True,
                cwd=Path(__file__).parent,
            ).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            found["commit"] = None
    return found


def format_table(metrics: dict[str, Any]) -> str:
    """A short human-readable summary of a run's metrics."""
    t = metrics["time"]
    rows = [
        ("frames", f"{metrics['frames']}" + (" (interrupted)" if metrics["interrupted"] else "")),
        ("Gaussians", f"{metrics['gaussians']:,}"),
    ]
    if metrics["ate"]:
        rows.append(("ATE RMSE / mean", f"{metrics['ate']['rmse_cm']:.2f} / {metrics['ate']['mean_cm']:.2f} cm"))
    if metrics["render"]:
        r = metrics["render"]
        rows += [
            ("PSNR", f"{r['psnr_db']:.2f} dB"),
            ("SSIM", f"{r['ssim']:.3f}"),
            ("depth L1", f"{r['depth_l1_cm']:.2f} cm"),
        ]
    rows += [
        ("tracking", f"{1000 * t['tracking_s']:.1f} ms/frame"),
        ("densify + keyframes", f"{1000 * t['densify_s']:.1f} ms/frame"),
        ("mapping", f"{1000 * t['mapping_s']:.1f} ms/frame"),
        ("total", f"{1000 * t['total_s']:.1f} ms/frame"),
        (
            "throughput",
            f"{t['fps_wall']:.2f} fps over the whole run"
            + (f", {t['fps_steady']:.2f} after warm-up" if t["fps_steady"] else ""),
        ),
        ("tracking lost", f"{metrics['lost_frames']} frames"),
    ]
    if "peak_gpu_memory_gb" in metrics:
        rows.append(("peak GPU memory", f"{metrics['peak_gpu_memory_gb']:.2f} GB"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)
