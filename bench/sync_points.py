"""Where the SLAM loop makes the host wait for the GPU: every synchronising call, counted by the
line of our code (or gsplat's) that made it.

Runs the embedded synthetic room with CUDA's sync debug mode on; each synchronising operation
(a read-back such as `.item()` or a boolean-mask index, a blocking copy) raises a warning whose
Python stack names the caller. Counts divided by the frames run give syncs per frame; lines
counted once or twice are start-up (compilation, the first frame).

    python bench/sync_points.py --out bench/results [--preset tiny] [--frames 30] [--set KEY=VALUE ...] [--stem NAME]
"""

from __future__ import annotations

import argparse
import json
import threading
import traceback
import warnings
from collections import Counter
from pathlib import Path

import torch

from pipeline.app.report import versions
from pipeline.app.run import run_slam
from pipeline.config import load_config, with_value
from pipeline.devices import resolve_device
from pipeline.io.files.atomic import atomic_write_text

OURS = ("/pipeline/", "/gsplat/")


def caller(stack: list[traceback.FrameSummary]) -> str:
    """The innermost frame in this project or gsplat, with the project frame that led to it."""
    ours = [f for f in stack if any(part in f.filename for part in OURS)]
    if not ours:
        return "elsewhere"
    inner = ours[-1]
    name = f"{inner.filename.split('/')[-2]}/{Path(inner.filename).name}:{inner.lineno} {inner.name}"
    project = [f for f in ours if "/pipeline/" in f.filename]
    if project and project[-1] is not inner:
        outer = project[-1]
        name += f" <- {Path(outer.filename).name}:{outer.lineno} {outer.name}"
    return name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--stem", help="the JSON file's name (default: sync_points_<preset>)")
    args = parser.parse_args()
    config = load_config(args.preset, overrides=[f"synthetic.frames={args.frames}", *args.overrides])
    config = with_value(config, "run.output", "/tmp/sync_points")

    counts: Counter[str] = Counter()
    lock = threading.Lock()

    def record(message, category, filename, lineno, file=None, line=None) -> None:
        if "synchroniz" in str(message):
            with lock:
                counts[caller(traceback.extract_stack()[:-1])] += 1

    warnings.showwarning = record
    warnings.simplefilter("always")
    torch.cuda.set_sync_debug_mode("warn")
    try:
        metrics = run_slam(config, resolve_device(config.run.device), progress=False).metrics
    finally:
        torch.cuda.set_sync_debug_mode("default")
    frames = metrics.frames if metrics else args.frames
    rows = [{"where": k, "count": v, "per_frame": v / frames} for k, v in counts.most_common()]
    report = {
        "device": torch.cuda.get_device_name(),
        "versions": versions(),
        "preset": args.preset,
        "overrides": args.overrides,
        "frames": frames,
        "syncs_per_frame": sum(counts.values()) / frames,
        "rows": rows,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(
        args.out / f"{args.stem or 'sync_points_' + args.preset}.json", json.dumps(report, indent=1) + "\n"
    )
    print(f"{report['syncs_per_frame']:.1f} synchronising calls per frame over {frames} frames")
    for row in rows:
        print(f"{row['per_frame']:7.2f}  {row['where']}")


if __name__ == "__main__":
    main()
