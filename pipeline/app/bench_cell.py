"""One benchmark cell: its config, its run, its row; and `run_cell_in_child`, which runs it in a
process of its own.

Why a process per cell: a cell's numbers are then those of a user's run on a warm machine (a
fresh interpreter with the compile caches on disk), not of an interpreter that has compiled the
cells before it, which made every cell's warm-up but the first look shorter than a user's; and a
cell that crashes (a segmentation fault inside a CUDA library) costs its own row, not the matrix.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

import torch
from tqdm.contrib.logging import logging_redirect_tqdm

from pipeline.app.bench_matrix import ABLATIONS, SYNTHETIC_SEQUENCES
from pipeline.app.logs import configure_logging
from pipeline.app.run import run_slam
from pipeline.config import Config, load_config
from pipeline.devices import placement, resolve_device
from pipeline.errors import UserError
from pipeline.io.outputs.run_metrics import RunMetrics
from pipeline.processes import STOP_SIGNALS, end_with_the_parent, signals_blocked, terminate_as_interrupt
from pipeline.runtime import catchable_signals

log = logging.getLogger("gsplatam")


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
    and its wall time. A cell that fails gives a row holding its error, so the rest of a matrix
    goes on; one stopped by a signal (SIGINT, SIGTERM) is marked `interrupted`: the matrix stops."""
    start = time.perf_counter()
    interrupted = False
    try:
        config = cell_config(cell, base_overrides, runs)
        # a cell's run folder is scratch: a later benchmark of the same cell replaces it
        metrics = run_slam(config, device, profile_trace=profile, progress=progress, overwrite=True).metrics
        if metrics is None:
            interrupted = True
            raise UserError("interrupted before its first frame")
        interrupted = metrics.interrupted
        row = row_of(cell, metrics)
    except Exception as exc:  # any failure of this cell, reported in its row
        log.error("bench: %s failed: %s", cell.name, exc)
        row = failed_row(cell, exc)
    except KeyboardInterrupt:  # a signal outside SLAM (the room's generation, the run folder's setting up)
        interrupted = True
        row = failed_row(cell, UserError("interrupted"))
    return {**row, **placement(), "wall_s": time.perf_counter() - start, "interrupted": interrupted}


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
    steps = metrics.large_steps
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
        "warmup_s": t.warmup_s,
        "compile_s": t.compile_s,
        "first_result_s": t.first_result_s,
        "warmup_stages_s": t.warmup_stages_s,
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
        "large_steps": steps.steps if steps else None,
        "large_step_error_cm": steps.mean_cm if steps and steps.steps else None,
        "frames_mapped": process["frames_mapped"]
        if process
        else metrics.frames_this_run - metrics.unmapped_frames - metrics.between_keyframes,
        "ate_before_loops_cm": before_loops.rmse_cm if before_loops else None,
        "loops_detected": loops.detected if loops else None,
        "loops_accepted": loops.accepted if loops else None,
        "loops_rejected": loops.rejected if loops else None,
        "loops_closed": len(closed) if loops else None,
        "loop_search_ms": loops.search_ms if loops else None,
        "loop_search_max_ms": loops.search_max_ms if loops else None,
        "loop_search_wait_ms": loops.search_wait_ms if loops else None,
        "loop_correct_ms": max((c.correct_ms for c in closed), default=None),
        "loop_published_ms": max((c.published_ms for c in closed), default=None),
        "warmup_frames_excluded": t.warmup_frames_excluded,
        "start_up": process["start_up"] if process else None,  # the process schedule's warm-up, in parts
        "error": None,
    }


def run_cell_in_child(
    cell: Cell, base_overrides: list[str], runs: Path, device: torch.device, progress: bool, profile: bool
) -> dict[str, Any]:
    """`run_cell` in a fresh process (spawn) -> its row. The child is a process group of its own
    and SIGINT/SIGTERM sent here are forwarded to it, so it gets each once (a terminal's Ctrl-C or
    `timeout` would otherwise reach it twice, and a second signal abandons a mapping process);
    it stops as a run does and its row says `interrupted`. A child that dies without a row (a
    crash, a kill) gives a row holding how it died; the matrix goes on, unless it was signalled."""
    start = time.perf_counter()
    context = multiprocessing.get_context("spawn")
    rows, sender = context.Pipe(duplex=False)
    args = (sender, cell, base_overrides, str(runs), str(device), progress, profile, log.level)
    child = context.Process(target=_cell_process, args=args, name=f"gsplatam-cell-{cell.name}")
    signalled: list[int] = []  # every stop signal received here
    pending: list[int] = []  # those received before the child existed

    def forward(signum: int, frame: FrameType | None) -> None:
        signalled.append(signum)
        if child.pid is None:
            pending.append(signum)
        elif child.exitcode is None:
            os.kill(child.pid, signum)

    previous = {sig: signal.signal(sig, forward) for sig in catchable_signals()}
    try:
        with signals_blocked():  # the child starts with them blocked; one sent meanwhile comes here after
            child.start()
        sender.close()  # the child's end: the pipe reads end-of-file once the child is gone
        for signum in pending:
            os.kill(child.pid, signum)  # type: ignore[arg-type]
        row: dict[str, Any] | None = json.loads(rows.recv_bytes())
    except EOFError:
        row = None
    finally:
        if child.pid is not None:
            child.join()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if row is not None:
        return row
    died = f"its process ended with {_how_it_ended(child.exitcode)} before giving its row"
    log.error("bench: %s failed: %s", cell.name, died)
    error = failed_row(cell, UserError(died))
    return {**error, **placement(), "wall_s": time.perf_counter() - start, "interrupted": bool(signalled)}


def _how_it_ended(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        return f"signal {signal.Signals(-exitcode).name}"
    return f"exit code {exitcode}"


def _cell_process(
    sender: Any,
    cell: Cell,
    base_overrides: list[str],
    runs: str,
    device: str,
    progress: bool,
    profile: bool,
    level: int,
) -> None:
    """The child's target: a process group of its own (the parent forwards the stop signals),
    the CLI's logging and signal handling, then the cell; its row goes back as JSON."""
    os.setpgid(0, 0)
    end_with_the_parent()
    configure_logging()
    log.setLevel(level)
    signal.signal(signal.SIGTERM, terminate_as_interrupt)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    with logging_redirect_tqdm():
        row = run_cell(cell, base_overrides, Path(runs), torch.device(device), progress, profile)
    sender.send_bytes(json.dumps(row).encode())
