"""The benchmark harness: a matrix of presets x sequences x variants, one JSON and one table.

Each cell is a full `run` (the same runtime and metrics as the CLI), so a benchmark number is
always what a user would get.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from pipeline.app.report import WARMUP_FRAMES, versions
from pipeline.app.run import run_slam
from pipeline.config import Config, load_config
from pipeline.devices import describe, placement, resolve_device
from pipeline.errors import UserError
from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.outputs.run_metrics import RunMetrics

log = logging.getLogger("gsplatam")

# Side-by-side switches; each is compared with the default configuration in the same invocation.
ABLATIONS: dict[str, tuple[str, ...]] = {
    "default": (),
    "sync-loader": ("run.loader=sync",),
    "no-compile": ("run.compile=off",),
    "packed": ("render.packed=true",),
    "3d-anisotropic": ("gaussians.isotropic=false",),
    "2d-isotropic": ("gaussians.kind=2d",),
    "2d-anisotropic": ("gaussians.kind=2d", "gaussians.isotropic=false"),
    "sequential": ("slam.schedule=sequential",),
    "views2": ("mapping.views_per_step=2",),
    "views3": ("mapping.views_per_step=3",),
    "selective-adam": ("mapping.optimizer=selective_adam",),
    "adam": ("tracking.method=adam",),  # SplaTAM's tracker, whatever the preset's default
    "align": ("tracking.method=align",),  # dense RGB-D alignment to one render
    "align-refine": ("tracking.method=align", "tracking.refine_iters=2"),  # then 2 of adam's iterations
    "process": ("slam.schedule=process",),  # mapping in its own process, refining between frames
    "process-views2": ("slam.schedule=process", "mapping.views_per_step=2"),
    "process-lead1": ("slam.schedule=process", "slam.max_lead=1"),
    "process-no-refine": ("slam.schedule=process", "mapping.refine_while_idle=false"),
    "process-fixed-poses": ("slam.schedule=process", "mapping.refine_pose_lr=0"),
    "final-iters": ("mapping.final_iters=600",),  # then 600 view renders over every keyframe
    "process-final": ("slam.schedule=process", "mapping.final_iters=600"),
    "process-no-sample": ("slam.schedule=process", "run.kernel_sample=off"),  # the kernel sampler's own cost
    "loops": ("loops.enabled=true",),  # loop closure on the keyframe pose graph
    "process-loops": ("slam.schedule=process", "loops.enabled=true"),
}


# Generated sequences by name; any other sequence is a dataset folder.
SYNTHETIC_SEQUENCES: dict[str, tuple[str, ...]] = {
    "synthetic": (),  # the Replica-like room, 1200x680 on a GPU
    "synthetic-fast": ("synthetic.speed=1.0",),  # the same room, the camera 3.3x faster (1 m/s)
    "synthetic-tum": (  # TUM-like: 640x480, Kinect-like depth noise and holes, timestamp jitter
        "synthetic.layout=tum", "synthetic.width=640", "synthetic.height=480",
        "synthetic.depth_noise=0.0015", "synthetic.holes=0.02", "synthetic.time_jitter=0.004",
    ),
    "synthetic-loops": (  # TUM-like, twice round the room at 0.75 m/s: a long sequence that revisits places
        "synthetic.layout=tum", "synthetic.width=640", "synthetic.height=480", "synthetic.loops=2", "synthetic.speed=0.75",
        "synthetic.depth_noise=0.0015", "synthetic.holes=0.02", "synthetic.time_jitter=0.004",
    ),
    "synthetic-trap": (  # TUM-like in the room of look-alike halves: no place is revisited
        "synthetic.layout=tum", "synthetic.width=640", "synthetic.height=480", "synthetic.trap=true", "synthetic.speed=0.75",
        "synthetic.depth_noise=0.0015", "synthetic.holes=0.02", "synthetic.time_jitter=0.004",
    ),
}  # fmt: skip


@dataclass(frozen=True)
class Cell:
    sequence: str  # a dataset folder (absolute: every node of a cluster reads the same path), or a name in SYNTHETIC_SEQUENCES
    preset: str
    variant: str = "default"
    repeat: int = 0  # the same cell run again, for the run-to-run spread

    @property
    def name(self) -> str:
        """Its run folder's name under the runs folder."""
        return f"{Path(self.sequence).name}_{self.preset}_{self.variant}" + (f"_{self.repeat}" if self.repeat else "")


def cells_of(sequences: list[str], presets: list[str], variants: list[str], repeats: int = 1) -> list[Cell]:
    """The matrix in its order: sequences, then presets, then variants, each `repeats` times."""
    folders = [s if s in SYNTHETIC_SEQUENCES else str(Path(s).resolve()) for s in sequences]
    return [Cell(s, p, v, r) for s in folders for p in presets for v in variants for r in range(repeats)]


def cell_config(cell: Cell, base_overrides: list[str], output: Path) -> Config:
    """The cell's config: its preset, its sequence, the matrix's settings, its variant's, and its
    run folder (`cell.name` under `output`)."""
    generated = list(SYNTHETIC_SEQUENCES.get(cell.sequence, ()))
    folder = [] if cell.sequence in SYNTHETIC_SEQUENCES else [f"dataset.path={cell.sequence}"]
    here = [*folder, f"run.output={output}", f"run.name={cell.name}"]
    return load_config(cell.preset, overrides=generated + base_overrides + list(ABLATIONS[cell.variant]) + here)


def bench_device(base_overrides: list[str]) -> torch.device:
    """The device this machine runs the matrix's cells on (run.device of the matrix's settings)."""
    return resolve_device(load_config(overrides=base_overrides).run.device)


def run_cell(
    cell: Cell, base_overrides: list[str], runs: Path, device: torch.device, progress: bool, profile: bool
) -> dict[str, Any]:
    """Run one cell here, on `device` (this process, or a Ray worker) -> its row, with where it ran
    and its wall time. A cell that fails gives a row holding its error, so the rest of a matrix goes on."""
    start = time.perf_counter()
    try:
        config = cell_config(cell, base_overrides, runs)
        # a cell's run folder is scratch: a later benchmark of the same cell replaces it
        metrics = run_slam(config, device, profile_trace=profile, progress=progress, overwrite=True).metrics
        if metrics is None:
            raise UserError("interrupted before its first frame")
        row = row_of(cell, metrics)
    except Exception as exc:  # any failure of this cell, reported in its row
        log.error("bench: %s failed: %s", cell.name, exc)
        row = failed_row(cell, exc)
    return {**row, **placement(), "wall_s": time.perf_counter() - start}


def failed_row(cell: Cell, error: BaseException) -> dict[str, Any]:
    """The row of a cell that did not finish: its name and the first line of its error."""
    message = str(error).strip().splitlines()
    return {
        "sequence": Path(cell.sequence).name,
        "preset": cell.preset,
        "variant": cell.variant,
        "repeat": cell.repeat,
        "error": f"{type(error).__name__}: {message[0] if message else ''}",
    }


def row_of(cell: Cell, metrics: RunMetrics) -> dict[str, Any]:
    t, runtime, ate, render, loops = metrics.time, metrics.runtime, metrics.ate, metrics.render, metrics.loops
    assert t is not None, "a finished run is timed"
    before_loops, closed = metrics.ate_as_tracked, loops.closed if loops else []
    process = metrics.mapping_process  # the process schedule: mapping's own times, per frame mapped
    before = metrics.render_before_final_iters
    return {
        "sequence": metrics.source,
        "preset": cell.preset,
        "variant": cell.variant,
        "repeat": cell.repeat,
        "frames": metrics.frames,
        "tracking_ms": 1000 * t.tracking_s,
        "densify_ms": process["densify_ms"] if process else 1000 * t.densify_s,
        "mapping_ms": process["mapping_ms"] if process else 1000 * t.mapping_s,
        "total_ms": 1000 * t.total_s,
        "fps_wall": t.fps_wall,
        "fps_steady": t.fps_steady,
        "kernel_busy": runtime.get("kernel_busy_fraction")
        or (runtime.get("profile") or {}).get("kernel_busy_fraction"),
        "gpu_gap_max_ms": runtime["gpu_gap_ms"]["max"],
        "gaussians": metrics.gaussians,
        "peak_gpu_gb": metrics.peak_gpu_memory_gb,
        "ate_rmse_cm": ate.rmse_cm if ate else None,
        "ate_mean_cm": ate.mean_cm if ate else None,
        "psnr_db": render.psnr_db if render else None,
        "keyframes_psnr_db": render.keyframes_psnr_db if render else None,
        "psnr_before_final_db": before.psnr_db if before else None,
        "keyframes_psnr_before_final_db": before.keyframes_psnr_db if before else None,
        "ssim": render.ssim if render else None,
        "depth_l1_cm": render.depth_l1_cm if render else None,
        "depth_rmse_cm": render.depth_rmse_cm if render else None,
        "lost_frames": metrics.lost_frames,
        "unmapped_frames": metrics.unmapped_frames,
        "ate_before_loops_cm": before_loops.rmse_cm if before_loops else None,
        "loops_accepted": loops.accepted if loops else None,
        "loops_rejected": loops.rejected if loops else None,
        "loops_closed": len(closed) if loops else None,
        "loop_search_ms": loops.search_ms if loops else None,
        "loop_correct_ms": max((c.correct_ms for c in closed), default=None),
        "loop_published_ms": max((c.published_ms for c in closed), default=None),
        "warmup_frames_excluded": t.warmup_frames_excluded,
        "error": None,
    }


def add_ratios(rows: list[dict[str, Any]]) -> None:
    """Each variant's total time, ATE and PSNR as ratios to the default of its sequence and preset."""
    ok_defaults = (r for r in rows if r["variant"] == "default" and r["repeat"] == 0 and not r["error"])
    defaults = {(r["sequence"], r["preset"]): r for r in ok_defaults}
    for row in rows:
        base = defaults.get((row["sequence"], row["preset"]))
        for key in ("total_ms", "fps_steady", "ate_rmse_cm", "psnr_db"):
            value = row.get(key)
            ok = base is not None and value is not None and base[key]
            row[f"{key}_ratio"] = value / base[key] if base is not None and ok else None


def run_matrix(
    cells: list[Cell],
    base_overrides: list[str],
    runs: Path,
    device: torch.device,
    progress: bool,
    profile: bool = False,
) -> dict[str, Any]:
    """Run every cell here on `device`, one after the other; run folders (and the generated
    synthetic room) go under `runs`."""
    start = time.perf_counter()
    rows = []
    for done, cell in enumerate(cells):
        log.info("bench: cell %d of %d: %s", done + 1, len(cells), cell.name)
        rows.append(run_cell(cell, base_overrides, runs, device, progress, profile))
    return report_of(rows, base_overrides, profile, time.perf_counter() - start, device, cluster=None)


def report_of(
    rows: list[dict[str, Any]],
    base_overrides: list[str],
    profile: bool,
    wall_s: float,
    device: torch.device,
    cluster: dict[str, Any] | None,
) -> dict[str, Any]:
    """The report of a whole matrix (rows in matrix order): the same keys for a local run and one
    on a Ray cluster (`cluster`: its address, nodes and what each cell declared; None: local);
    `device` is this machine's (the driver's, on a cluster)."""
    add_ratios(rows)
    return {
        "device": describe(device, load_config("base")),
        "driver": _driver_version(device),
        "versions": versions(),
        "overrides": base_overrides,
        "profiled": profile,
        "cluster": cluster,
        "wall_s": wall_s,
        "rows": rows,
    }


def _driver_version(device: torch.device) -> str | None:
    if device.type != "cuda":
        return None
    try:
        import subprocess

        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"], capture_output=True, text=True
        )
        return out.stdout.strip().splitlines()[0]
    except (OSError, IndexError):
        return None


COLUMNS = [
    ("sequence", "{}"), ("preset", "{}"), ("variant", "{}"), ("repeat", "{}"), ("frames", "{}"),
    ("tracking_ms", "{:.1f}"), ("densify_ms", "{:.1f}"), ("mapping_ms", "{:.1f}"), ("total_ms", "{:.1f}"),
    ("total_ms_ratio", "{:.2f}"), ("fps_steady", "{:.2f}"), ("fps_steady_ratio", "{:.2f}"), ("kernel_busy", "{:.3f}"), ("gaussians", "{:,}"),
    ("peak_gpu_gb", "{:.2f}"), ("ate_rmse_cm", "{:.2f}"), ("ate_mean_cm", "{:.2f}"), ("psnr_db", "{:.2f}"),
    ("keyframes_psnr_db", "{:.2f}"),
    ("depth_l1_cm", "{:.2f}"), ("depth_rmse_cm", "{:.2f}"), ("lost_frames", "{}"), ("unmapped_frames", "{}"),
    ("ate_before_loops_cm", "{:.2f}"), ("loops_accepted", "{}"), ("loops_rejected", "{}"), ("loops_closed", "{}"),
    ("loop_search_ms", "{:.1f}"), ("loop_correct_ms", "{:.1f}"), ("loop_published_ms", "{:.1f}"),
]  # fmt: skip


PLACEMENT_COLUMNS = [("node", "{}"), ("gpu", "{}")]  # shown for a run on a cluster


def markdown(report: dict[str, Any]) -> str:
    rows, cluster = report["rows"], report["cluster"]
    columns = COLUMNS + (PLACEMENT_COLUMNS if cluster else []) + ([("error", "{}")] if _failed(rows) else [])
    where = "this machine, one cell after the other"
    if cluster:
        where = f"Ray cluster {cluster['address']} ({len(cluster['nodes'])} nodes), {cluster['declared']} per cell"
    lines = [
        f"Device: {report['device']}; driver {report['driver']}; versions {report['versions']}",
        f"Extra settings: {report['overrides'] or 'none'}. Times are means per frame; the first "
        f"{WARMUP_FRAMES} frames (initialisation, compilation) excluded."
        + (
            " Run under the torch profiler (slower; kernel_busy is from its kernel timeline)."
            if report["profiled"]
            else ""
        ),
        f"Ran on {where}: {len(rows)} cells in {report['wall_s']:.1f} s"
        + (f", {len(_failed(rows))} failed." if _failed(rows) else "."),
        "",
        "| " + " | ".join(name for name, _ in columns) + " |",
        "|" + "---|" * len(columns),
    ]
    for row in rows:
        cells = ["-" if row.get(name) is None else fmt.format(row[name]) for name, fmt in columns]
        lines.append("| " + " | ".join(cell.replace("|", "/") for cell in cells) + " |")
    return "\n".join(lines) + "\n"


def _failed(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [row for row in rows if row["error"]]


def write_report(report: dict[str, Any], out: Path, stem: str) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    json_path, md_path = out / f"{stem}.json", out / f"{stem}.md"
    atomic_write_text(json_path, json.dumps(report, indent=2) + "\n")
    atomic_write_text(md_path, markdown(report))
    return json_path, md_path


def default_variants(ablations: bool) -> list[str]:
    return list(ABLATIONS) if ablations else ["default"]
