"""What a run reports: its metrics (one record for datasets and live sessions), timing,
software versions, the printed table and the files it leaves."""

from __future__ import annotations

import importlib.util
import math
import os
import platform
import shlex
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import torch

from pipeline.extras import EXTRA_OF_MODULE, install_command, pip_command, unavailable_extra
from pipeline.io.outputs.exports import EXPORTERS
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.outputs.run_metrics import LoopRecord, RunMetrics, TimingRecord
from pipeline.runtime import RuntimeReport
from pipeline.stages.frame_log import FrameLog

WARMUP_FRAMES = 2  # frame 0 (map initialisation) and frame 1 (first tracking: compilation) are left out of timing means


def timing_summary(frames: FrameLog, report: RuntimeReport) -> TimingRecord:
    """Mean seconds per stage after the warm-up frames, frames per second, and where the warm-up
    went: its frames' seconds per stage (the rest of `warmup_s` is outside SLAM: reading, decoding
    and uploading the first frames) and the report's `compile_s`, torch.compile's own share of it all."""
    results = frames.results
    timed = [r for r in results if r.index >= WARMUP_FRAMES] or results
    warming = [r for r in results if r.index <= WARMUP_FRAMES]
    mean = {
        k: float(np.mean([r.seconds[k] for r in timed])) if timed else math.nan
        for k in ("tracking", "densify", "mapping", "total")
    }
    return TimingRecord(
        tracking_s=mean["tracking"],
        densify_s=mean["densify"],
        mapping_s=mean["mapping"],
        total_s=mean["total"],
        frames_timed=len(timed),
        warmup_frames_excluded=WARMUP_FRAMES,
        fps_wall=report.frames / report.wall_s if report.wall_s > 0 else 0.0,
        fps_steady=steady_fps(frames.arrivals),
        first_result_s=frames.arrivals[0] - frames.started_at if frames.arrivals else None,
        warmup_s=frames.arrivals[min(WARMUP_FRAMES, len(frames.arrivals) - 1)] - frames.started_at
        if frames.arrivals
        else None,
        warmup_stages_s={k: sum(r.seconds[k] for r in warming) for k in ("tracking", "densify", "mapping")}
        if warming
        else None,
        compile_s=report.compile_s,
    )


def steady_fps(arrivals: list[float]) -> float | None:
    """Frames per second of wall time after the warm-up frames: what a long run sustains."""
    if len(arrivals) <= WARMUP_FRAMES + 1:
        return None
    return (len(arrivals) - 1 - WARMUP_FRAMES) / (arrivals[-1] - arrivals[WARMUP_FRAMES])


def versions() -> dict[str, str | None]:
    """Python, torch, CUDA, gsplat and the commit, for every results file."""
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
    found["commit"] = os.environ.get("GSPLATAM_COMMIT") or _git_commit()  # a device copy's git is stale
    return found


def _git_commit() -> str | None:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).parent,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def format_table(metrics: RunMetrics) -> str:
    """A short human-readable summary of a run's metrics."""
    rows = [
        ("frames", f"{metrics.frames}" + (" (interrupted)" if metrics.interrupted else "")),
        ("Gaussians", f"{metrics.gaussians:,}"),
    ]
    if metrics.ate is not None:
        rows.append(("ATE RMSE / mean", f"{metrics.ate.rmse_cm:.2f} / {metrics.ate.mean_cm:.2f} cm"))
    if metrics.ate_as_tracked is not None:
        before = metrics.ate_as_tracked
        rows.append(("ATE before loops", f"{before.rmse_cm:.2f} / {before.mean_cm:.2f} cm"))
    if metrics.render is not None:
        r = metrics.render
        rows += [("PSNR", f"{r.psnr_db:.2f} dB"), ("SSIM", f"{r.ssim:.3f}"), ("depth L1", f"{r.depth_l1_cm:.2f} cm")]
        if r.depth_rmse_cm is not None:
            rows.append(("depth RMSE", f"{r.depth_rmse_cm:.2f} cm"))
    if metrics.time is not None:
        t = metrics.time
        rows += [
            ("tracking", f"{1000 * t.tracking_s:.1f} ms/frame"),
            ("densify + keyframes", f"{1000 * t.densify_s:.1f} ms/frame"),
            ("mapping", f"{1000 * t.mapping_s:.1f} ms/frame"),
            ("total", f"{1000 * t.total_s:.1f} ms/frame"),
            (
                "throughput",
                f"{t.fps_wall:.2f} fps over the whole run"
                + (f", {t.fps_steady:.2f} after warm-up" if t.fps_steady else "")
                + (f" (warm-up {t.warmup_s:.1f} s)" if t.warmup_s is not None else ""),
            ),
        ]
    rows += [
        ("tracking lost", f"{metrics.lost_frames} frames"),
        ("tracking weak", f"{metrics.weak_frames} frames (mapped; low map coverage)"),
    ]
    if metrics.loops is not None:
        rows.append(("loops", loops_outcome(metrics.loops)))
    if metrics.peak_gpu_memory_gb is not None:
        rows.append(("peak GPU memory", f"{metrics.peak_gpu_memory_gb:.2f} GB"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)


def files_and_next_steps(folder: RunFolder) -> str:
    """The end of a run's output: every file in its run folder, then the commands that take it further."""
    root = folder.path
    exports = folder.exports_made()
    defaults = (exporter.DEFAULT_NAME for exporter in EXPORTERS.values())
    derived = {folder.exports_record.name, *defaults, *(str(e.get("path")) for e in exports.values())}
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file() and not p.name.startswith("."))
    files = [p for p in files if p.parts[0] not in derived and str(p) not in derived]
    shown = [str(p) for p in files if len(p.parts) == 1]
    shown += sorted(
        {f"{p.parts[0]}/ ({sum(q.parts[0] == p.parts[0] for q in files)} files)" for p in files if len(p.parts) > 1}
    )
    lines = [f"outputs: {root}/", *(f"  {name}" for name in shown)]
    if exports:
        lines.append(f"exports made before this run ({folder.exports_record.name}):")
        lines += [f"  {e.get('path')}: {e.get('stale') or 'of this map'}" for e in exports.values()]
    return "\n".join([*lines, "next:", *next_steps(folder)])


def next_steps(folder: RunFolder) -> list[str]:
    """Commands that take the run further, one per line, each one that runs when pasted into a
    shell: a tool or extra that is not installed comes with its install command first."""
    gsplatam, root = gsplatam_command(), shlex.quote(str(folder.path))
    lines = [_needing("viser", f"{gsplatam} view {root}")]
    if folder.groundtruth.is_file():
        lines.append(evo_command(folder) + "   # the same ATE, by evo")
    lines += [_needing(exporter.NEEDS, f"{gsplatam} export {root} --to {fmt}") for fmt, exporter in EXPORTERS.items()]
    if folder.recorded():
        lines.append(f"{gsplatam} run {shlex.quote(str(folder.recording))}   # the live session again, offline")
    return [f"  {line}" for line in lines]


def evo_command(folder: RunFolder) -> str:
    """evo's ATE of the run against its reference, as a shell runs it: evo_ape of this Python's
    environment by its absolute path (a virtual environment need not be activated), else the one
    on the PATH, else evo installed into this environment first."""
    arguments = f"tum {shlex.quote(str(folder.groundtruth))} {shlex.quote(str(folder.trajectory))} -a"
    beside = Path(sysconfig.get_path("scripts")) / "evo_ape"
    if beside.is_file():
        return f"{shlex.quote(str(beside))} {arguments}"
    if shutil.which("evo_ape"):
        return f"evo_ape {arguments}"
    return f"{pip_command()} install evo && {shlex.quote(str(beside))} {arguments}"


def resume_command(folder: Path) -> str:
    """The command that continues the run in `folder`, as a shell runs it."""
    return f"{gsplatam_command()} run --resume {shlex.quote(str(folder))}"


def gsplatam_command() -> str:
    """How this gsplatam is called from a shell: its script where it is on the PATH, else
    `python -m pipeline` with this interpreter (a virtual environment not activated)."""
    return "gsplatam" if shutil.which("gsplatam") else f"{shlex.quote(sys.executable)} -m pipeline"


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ImportError:  # a finder that refuses the module outright
        return False


def _needing(module: str | None, command: str) -> str:
    """`command`, after the pip command of the extra that brings `module` when it is missing;
    where `module` is installed but cannot load (a system library missing), what it lacks."""
    if module is None:
        return command
    if not _installed(module):
        return f"{install_command(EXTRA_OF_MODULE[module])} && {command}"
    broken = unavailable_extra(module)
    return command if broken is None else f"# {command}   # not here yet: {broken}"


def live_outcome(folder: RunFolder, metrics: RunMetrics) -> str:
    """What a live session printed at its end: its size, then its files and what to do next."""
    return f"{metrics.frames} frames, {metrics.gaussians:,} Gaussians\n{files_and_next_steps(folder)}"


def run_summary(metrics: RunMetrics) -> str:
    """One markdown line for the viewer at the end of a run."""
    parts = [f"**run finished**: {metrics.frames} frames, {metrics.gaussians:,} Gaussians"]
    if metrics.ate is not None:
        parts.append(f"ATE RMSE {metrics.ate.rmse_cm:.2f} cm")
    if metrics.render is not None:
        parts.append(f"PSNR {metrics.render.psnr_db:.1f} dB")
    if metrics.loops is not None:
        parts.append(f"loops: {loops_outcome(metrics.loops)}")
    return ", ".join(parts)


def loops_outcome(loops: LoopRecord) -> str:
    """Loop closure's run in a few words: `2 closed (3 accepted, 5 rejected of 8 candidates)`."""
    verdicts = f"{loops.accepted} accepted, {loops.rejected} rejected of {loops.detected} candidates"
    return f"{len(loops.closed)} closed ({verdicts})"
