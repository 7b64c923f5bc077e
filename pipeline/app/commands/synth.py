"""`gsplatam synth`: a synthetic RGB-D sequence with exact poses, written in a dataset layout."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.config import SYNTHETIC_CPU, SYNTHETIC_GPU, SyntheticConfig
from pipeline.config.loading import MAX_SYNTHETIC_FRAMES, synthetic_problem
from pipeline.errors import UserError

HELP = "write a synthetic RGB-D sequence with exact poses"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = SyntheticConfig()
    parser.add_argument("out", help="output folder (absent or empty; or an earlier sequence with --overwrite)")
    parser.add_argument(
        "--layout", choices=["replica", "tum"], default="replica", help="the folder's layout (default: replica)"
    )
    for i, name in enumerate(("width", "height", "frames")):
        default = f"default: {SYNTHETIC_GPU[i]} with CUDA, {SYNTHETIC_CPU[i]} on the CPU"
        parser.add_argument(f"--{name}", type=int, help=default)
    parser.add_argument(
        "--seed", type=int, default=defaults.seed, help="chooses the room's objects, textures and path (default: 0)"
    )
    parser.add_argument("--speed", type=float, default=defaults.speed, help="camera speed, m/s (default: 0.3)")
    parser.add_argument("--jitter", type=float, default=defaults.jitter, help="hand-held shake, metres (default: 0.01)")
    parser.add_argument("--fps", type=float, default=defaults.fps, help="frame rate of the timestamps (default: 30)")
    parser.add_argument(
        "--depth-noise", type=float, default=0.0, help="TUM only: depth noise std = k x depth^2, metres (default: 0)"
    )
    parser.add_argument(
        "--holes", type=float, default=0.0, help="TUM only: fraction of depth pixels zeroed, in blobs (default: 0)"
    )
    parser.add_argument(
        "--time-jitter",
        type=float,
        default=0.0,
        help="TUM only: depth/pose timestamp offsets up to this, s (default: 0)",
    )
    parser.add_argument(
        "--loops", type=int, default=0, help="a closed path, back at its start N times; frames: all of it (default: 0)"
    )
    parser.add_argument("--trap", action="store_true", help="the room's halves twins: look-alike places, no loop")
    parser.add_argument("--overwrite", action="store_true", help="replace an earlier sequence of synth in the folder")


def run(args: argparse.Namespace) -> int:
    for name in ("width", "height", "frames"):
        if getattr(args, name) is not None and getattr(args, name) <= 0:
            raise UserError(f"--{name} must be positive, not {getattr(args, name)} (leave it out for the default)")
    asked = SyntheticConfig(
        frames=args.frames or 0, width=args.width or 0, height=args.height or 0, seed=args.seed, speed=args.speed,
        jitter=args.jitter, fps=args.fps, layout=args.layout, depth_noise=args.depth_noise, holes=args.holes,
        time_jitter=args.time_jitter, loops=args.loops, trap=args.trap,
    )  # fmt: skip
    problem = synthetic_problem(asked)
    if problem is not None:
        name, value, requirement = problem
        raise UserError(f"--{name.replace('_', '-')} {requirement}, not {value}")
    from pipeline.devices import resolve_device
    from pipeline.io.sources.datasets.synthetic import closed_path_frames, path_turns, synthetic_for
    from pipeline.io.sources.datasets.synthetic_writer import write_synthetic_folder

    if path_turns(asked) and (frames := closed_path_frames(asked)) > MAX_SYNTHETIC_FRAMES:
        raise UserError(
            f"--loops {args.loops} at --speed {args.speed:g} and --fps {args.fps:g} makes {frames:,} frames "
            f"(at most {MAX_SYNTHETIC_FRAMES:,}): fewer loops, or a faster speed"
        )
    device = resolve_device("auto")
    config = synthetic_for(asked, device)  # sizes left at 0 by device (a closed path's frames: all of it)
    count = write_synthetic_folder(Path(args.out), config, args.overwrite, not args.quiet, device)
    print(f"wrote {count} frames ({config.width}x{config.height}, {args.layout} layout) to {args.out}")
    return 0
