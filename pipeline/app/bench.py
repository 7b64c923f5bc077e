"""The benchmark harness: a matrix of presets x sequences x variants, one JSON and one table.

Each cell is a full `run` (the same runtime and metrics as the CLI) in a process of its own
(bench_cell.py), so a benchmark number is always what a user would get.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from pipeline.app.bench_cell import Cell, run_cell_in_child
from pipeline.app.bench_matrix import SYNTHETIC_SEQUENCES
from pipeline.app.report import WARMUP_FRAMES, versions
from pipeline.config import load_config
from pipeline.devices import describe
from pipeline.io.files.atomic import atomic_write_text

log = logging.getLogger("gsplatam")


def cells_of(sequences: list[str], presets: list[str], variants: list[str], repeats: int = 1) -> list[Cell]:
    """The matrix in its order: sequences, then presets, then variants, each `repeats` times."""
    folders = [s if s in SYNTHETIC_SEQUENCES else str(Path(s).resolve()) for s in sequences]
    return [Cell(s, p, v, r) for s in folders for p in presets for v in variants for r in range(repeats)]


RATIO_KEYS = ("total_ms", "fps_steady", "ate_rmse_cm", "psnr_db")


def add_ratios(rows: list[dict[str, Any]]) -> str:
    """Each row's total time, frames/s, ATE and PSNR as ratios (`<key>_ratio`) to its reference
    row -> what the reference is, for the table's header. The reference: with several variants,
    the first variant of the same sequence and preset; else, with several presets, the first
    preset of the same sequence; else, with repeats, the first run of the same cell; else none
    (one cell per sequence: no ratio, where every one would read 1.00)."""
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    presets = list(dict.fromkeys(r["preset"] for r in rows))
    if len(variants) > 1:
        described = f"to variant '{variants[0]}' of the same sequence and preset"

        def reference_of(row: dict[str, Any]) -> tuple[Any, ...]:
            return (row["sequence"], row["preset"], variants[0], 0)
    elif len(presets) > 1:
        described = f"to preset '{presets[0]}' of the same sequence"

        def reference_of(row: dict[str, Any]) -> tuple[Any, ...]:
            return (row["sequence"], presets[0], row["variant"], 0)
    else:
        described = "to the first run of the same cell (--repeats)"

        def reference_of(row: dict[str, Any]) -> tuple[Any, ...]:
            return (row["sequence"], row["preset"], row["variant"], 0)

    rows_by = {(r["sequence"], r["preset"], r["variant"], r["repeat"]): r for r in rows if not r["error"]}
    comparable = any(reference_of(r) != (r["sequence"], r["preset"], r["variant"], r["repeat"]) for r in rows)
    for row in rows:
        base = rows_by.get(reference_of(row)) if comparable else None
        for key in RATIO_KEYS:
            value = row.get(key)
            ok = base is not None and value is not None and base.get(key)
            row[f"{key}_ratio"] = value / base[key] if base is not None and ok else None
    return described if comparable else "none (one cell per sequence)"


def run_matrix(
    cells: list[Cell],
    base_overrides: list[str],
    runs: Path,
    device: torch.device,
    progress: bool,
    profile: bool = False,
    on_report: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Run every cell on this machine's `device`, one after the other, each in a process of its own;
    run folders (and the generated synthetic room) go under `runs`. A signal stops the matrix after
    the cell it interrupted (whose run folder is written, or removed when it had saved nothing): the
    report holds the cells run. `on_report` gets the report of the cells run so far after each cell
    (so that a matrix killed midway keeps its finished cells)."""
    start = time.perf_counter()
    rows = []
    for done, cell in enumerate(cells):
        log.info("bench: cell %d of %d: %s", done + 1, len(cells), cell.name)
        rows.append(run_cell_in_child(cell, base_overrides, runs, device, progress, profile))
        if on_report is not None and done + 1 < len(cells):
            on_report(
                report_of([dict(r) for r in rows], base_overrides, profile, time.perf_counter() - start, device, None)
            )
        if rows[-1]["interrupted"]:
            log.info("bench: stopped by a signal after %d of %d cells", done + 1, len(cells))
            break
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
    reference = add_ratios(rows)
    return {
        "device": describe(device, load_config("base")),
        "driver": _driver_version(device),
        "versions": versions(),
        "overrides": base_overrides,
        "profiled": profile,
        "cluster": cluster,
        "wall_s": wall_s,
        "ratios": reference,
        "interrupted": any(row.get("interrupted") for row in rows),
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
    ("total_ms_ratio", "{:.2f}"), ("fps_steady", "{:.2f}"), ("fps_steady_ratio", "{:.2f}"), ("fps_wall", "{:.2f}"),
    ("warmup_s", "{:.1f}"), ("compile_s", "{:.1f}"), ("kernel_busy", "{:.3f}"), ("gaussians", "{:,}"),
    ("peak_gpu_gb", "{:.2f}"), ("ate_rmse_cm", "{:.2f}"), ("ate_mean_cm", "{:.2f}"), ("psnr_db", "{:.2f}"),
    ("keyframes_psnr_db", "{:.2f}"),
    ("depth_l1_cm", "{:.2f}"), ("depth_rmse_cm", "{:.2f}"), ("lost_frames", "{}"), ("unmapped_frames", "{}"),
    ("frames_mapped", "{}"), ("large_steps", "{}"), ("large_step_error_cm", "{:.2f}"),
    ("ate_before_loops_cm", "{:.2f}"), ("loops_detected", "{}"), ("loops_accepted", "{}"), ("loops_rejected", "{}"),
    ("loops_closed", "{}"),
    ("loop_search_ms", "{:.1f}"), ("loop_search_max_ms", "{:.1f}"), ("loop_search_wait_ms", "{:.1f}"),
    ("loop_correct_ms", "{:.1f}"), ("loop_published_ms", "{:.1f}"),
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
        + (f", {len(_failed(rows))} failed." if _failed(rows) else ".")
        + (" Stopped by a signal: the last cell is the one it interrupted." if report.get("interrupted") else ""),
        f"Ratios (*_ratio): {report.get('ratios', 'to the default variant')}.",
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
