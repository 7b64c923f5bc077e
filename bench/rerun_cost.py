"""SLAM's cost per frame with the rerun sink (to a .rrd) and with the web viewer's feed (one
client connected), against no viewer, in one invocation, the three interleaved `--repeats`
times.

    python bench/rerun_cost.py --out bench/results [--preset tiny] [--frames 20] [--repeats 3]

Per run: the SLAM step (mean ms per frame after the 2 warm-up frames, as metrics.json has it)
and frames/s after warm-up, both in wall-clock time that other load on a shared machine moves;
the feed's observer call at the frame boundary (the median over the run's frames: what SLAM's
thread pays directly); the CPU time of the feed's own thread per frame (rerun: its logging;
viser: rendering and packing; rerun's Rust threads not included); and the whole process's CPU
time per frame (SLAM, evaluation and writes too: the sinks' threads take from the same cores).
Each variant comes first in one repeat of three. On the CPU the synthetic room is 128x96.
"""

from __future__ import annotations

import argparse
import functools
import json
import resource
import statistics
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from viewer_overhead import run_once  # bench/ is the script's folder

from pipeline.app.report import versions
from pipeline.config import Config, load_config, with_value
from pipeline.io.files.atomic import atomic_write_text
from pipeline.ui.rerun_feed import RerunFeed
from pipeline.ui.viewer_feed import ViewerFeed

VARIANTS = ("none", "rerun", "viser")
PER_FRAME = ("boundary_ms", "worker_cpu_ms_per_frame", "process_cpu_s_per_frame")

BOUNDARY_S: list[float] = []  # every observer call of the feed under test, seconds
WORKER_CPU_S: list[float] = []  # the feed's own thread: CPU seconds per frame it logged or showed


def _timed(call: Callable[..., None], times: list[float], clock: Callable[[], float]) -> Callable[..., None]:
    @functools.wraps(call)
    def timed(*args: Any) -> None:
        started = clock()
        call(*args)
        times.append(clock() - started)

    return timed


def _process_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _run(config: Config, variant: str, name: str, port: int, rrd: Path) -> dict[str, Any]:
    BOUNDARY_S.clear()
    WORKER_CPU_S.clear()
    if variant == "rerun":
        config = replace(config, viewer=replace(config.viewer, enabled=True, kind="rerun", rerun_save=str(rrd)))
    cpu_before = _process_cpu_s()
    row = run_once(config, name, port if variant == "viser" else None, map_every_s=5.0)
    row.update(
        variant=variant,
        process_cpu_s_per_frame=(_process_cpu_s() - cpu_before) / row["frames"],  # SLAM, evaluation, writes too
        boundary_ms=1000 * statistics.median(BOUNDARY_S) if BOUNDARY_S else 0.0,
        worker_cpu_ms_per_frame=1000 * sum(WORKER_CPU_S) / row["frames"],
    )
    if variant == "rerun":
        row["rrd_megabytes"] = rrd.stat().st_size / 1e6
    return row


def _summary(rows: list[dict[str, Any]], variant: str) -> dict[str, Any]:
    mine = [r for r in rows if r["variant"] == variant]
    out: dict[str, Any] = {"variant": variant, "runs": len(mine)}
    for key in ("total_ms", "fps_steady", *PER_FRAME):
        values = [r[key] for r in mine]
        out[key] = {"min": min(values), "median": statistics.median(values), "max": max(values)}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--port", type=int, default=8097)
    parser.add_argument("--runs", default="/tmp/rerun_cost_runs")
    parser.add_argument("--stem", default="rerun_cost")
    args = parser.parse_args()
    RerunFeed.__call__ = _timed(RerunFeed.__call__, BOUNDARY_S, time.perf_counter)  # type: ignore[method-assign]
    ViewerFeed.__call__ = _timed(ViewerFeed.__call__, BOUNDARY_S, time.perf_counter)  # type: ignore[method-assign]
    RerunFeed._log = _timed(RerunFeed._log, WORKER_CPU_S, time.thread_time)  # type: ignore[method-assign]
    ViewerFeed._show = _timed(ViewerFeed._show, WORKER_CPU_S, time.thread_time)  # type: ignore[method-assign]
    ViewerFeed.linger = lambda self, summary: None  # type: ignore[method-assign]  # the client never leaves
    config = with_value(
        load_config(args.preset, overrides=[f"synthetic.frames={args.frames}"]), "run.output", args.runs
    )
    Path(args.runs).mkdir(parents=True, exist_ok=True)
    rows = []
    for repeat in range(args.repeats):
        for k, variant in enumerate(VARIANTS[repeat % 3 :] + VARIANTS[: repeat % 3]):  # each first once in 3
            port = args.port + 3 * repeat + k  # a fresh port each time: the last server may still hold its own
            rows.append(_run(config, variant, f"{variant}_{repeat}", port, Path(args.runs) / f"{variant}_{repeat}.rrd"))
            print({key: rows[-1][key] for key in ("variant", "total_ms", "fps_steady", *PER_FRAME)}, flush=True)
    report = {
        "rows": rows,
        "summary": [_summary(rows, v) for v in VARIANTS],
        "versions": versions(),
    }
    out = Path(args.out) / f"{args.stem}.json"
    atomic_write_text(out, json.dumps(report, indent=2) + "\n")
    for line in report["summary"]:
        print(line)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
