"""`gsplatam synth`: a synthetic RGB-D sequence with exact poses, written in a dataset layout."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.config import SYNTHETIC_CPU, SYNTHETIC_GPU
from pipeline.errors import UserError

HELP = "write a synthetic RGB-D sequence with exact poses"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", help="output folder")
    parser.add_argument("--layout", choices=["replica", "tum"], default="replica")
    for i, name in enumerate(("width", "height", "frames")):
        default = f"default: {SYNTHETIC_GPU[i]} with CUDA, {SYNTHETIC_CPU[i]} on the CPU"
        parser.add_argument(f"--{name}", type=int, help=default)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--speed", type=float, default=0.3, help="camera speed, m/s")
    parser.add_argument("--jitter", type=float, default=0.01, help="hand-held shake, metres")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--depth-noise", type=float, default=0.0, help="TUM only: depth noise std = k x depth^2")
    parser.add_argument("--holes", type=float, default=0.0, help="TUM only: fraction of depth pixels zeroed")
    parser.add_argument("--time-jitter", type=float, default=0.0, help="TUM only: depth/pose timestamp offsets, s")
    parser.add_argument("--loops", type=int, default=0, help="a closed path, back at its start N times (frames: all)")
    parser.add_argument("--trap", action="store_true", help="the room's halves twins: look-alike places, no loop")
    parser.add_argument("--overwrite", action="store_true", help="replace an earlier sequence of synth in the folder")


def run(args: argparse.Namespace) -> int:
    from pipeline.config import SyntheticConfig
    from pipeline.devices import resolve_device
    from pipeline.io.sources.datasets.synthetic import synthetic_for
    from pipeline.io.sources.datasets.synthetic_writer import write_synthetic_folder

    for name in ("width", "height", "frames"):
        if getattr(args, name) is not None and getattr(args, name) <= 0:
            raise UserError(f"--{name} must be positive, not {getattr(args, name)} (leave it out for the default)")
    device = resolve_device("auto")
    asked = SyntheticConfig(
        frames=args.frames or 0, width=args.width or 0, height=args.height or 0, seed=args.seed, speed=args.speed,
        jitter=args.jitter, fps=args.fps, layout=args.layout, depth_noise=args.depth_noise, holes=args.holes,
        time_jitter=args.time_jitter, loops=args.loops, trap=args.trap,
    )  # fmt: skip
    config = synthetic_for(asked, device)  # sizes left at 0 by device (a closed path's frames: all of it)
    count = write_synthetic_folder(Path(args.out), config, args.overwrite, not args.quiet, device)
    print(f"wrote {count} frames ({config.width}x{config.height}, {args.layout} layout) to {args.out}")
    return 0
