"""`gsplatam render`: a run's map seen again: a fly-through video along its trajectory."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from pipeline.errors import UserError

HELP = "a run's map seen again: a fly-through video (MP4) along its trajectory"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", help="run folder")
    parser.add_argument("--video", action="store_true", help="render the fly-through MP4 (the 'live' extra: PyAV)")
    parser.add_argument(
        "--output", metavar="FILE", help="the .mp4 to write (default: flythrough.mp4 in the run folder)"
    )
    parser.add_argument("--fps", type=float, default=30.0, help="frames per second of the video (default: 30)")
    parser.add_argument("--stride", type=int, default=1, help="every Nth camera pose of the trajectory (default: 1)")
    parser.add_argument(
        "--back", type=float, default=0.0, metavar="M",
        help="seen from this many metres behind each camera (default: 0, the camera's own view)",
    )  # fmt: skip
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="where to render")


def run(args: argparse.Namespace) -> int:
    if not args.video:
        raise UserError("say what to render: --video (a fly-through MP4 along the trajectory)")
    if not (math.isfinite(args.fps) and 0 < args.fps <= 240):
        raise UserError(f"--fps must be > 0 and at most 240, not {args.fps}")
    if args.stride < 1:
        raise UserError(f"--stride must be >= 1, not {args.stride}")
    if not (math.isfinite(args.back) and 0 <= args.back <= 100):
        raise UserError(f"--back must be 0 to 100 metres, not {args.back}")
    from pipeline.app.render import render_video
    from pipeline.devices import resolve_device

    output = Path(args.output) if args.output else None
    path, frames = render_video(
        Path(args.run_dir), output, args.fps, args.back, args.stride, resolve_device(args.device)
    )
    print(f"wrote {path}: {frames} frames at {args.fps:g} frames/s")
    return 0
