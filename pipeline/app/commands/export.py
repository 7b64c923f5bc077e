"""`gsplatam export`: a run folder to another format; the formats are the registry's (EXPORTERS)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.extras import EXTRA_OF_MODULE

HELP = "a run folder in another format (nerfstudio, splat, PLY, a mesh, ...: export --help lists them)"


def _formats_help() -> str:
    """Each format, what it is for and the extra it needs (% doubled: argparse formats help)."""
    from pipeline.io.outputs.exports import EXPORTERS

    described = [
        f"{name}: {exporter.FOR}" + (f" [the '{EXTRA_OF_MODULE[exporter.NEEDS]}' extra]" if exporter.NEEDS else "")
        for name, exporter in EXPORTERS.items()
    ]
    return ("; ".join(described)).replace("%", "%%")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The registry (its writers bring torch) is read here: the command line builds a command's
    arguments only when that command runs (cli.build_parser)."""
    from pipeline.io.outputs.exports import EXPORTERS

    parser.add_argument("run_dir", help="run folder")
    parser.add_argument("--to", required=True, choices=list(EXPORTERS), metavar="FORMAT", help=_formats_help())
    parser.add_argument("--output", metavar="PATH", help="file (folder for nerfstudio); default: in the run folder")
    parser.add_argument("--voxel", type=float, default=0.02, help="mesh: TSDF voxel size, metres (default: 0.02)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="mesh: where to render")
    parser.add_argument(
        "--frames", choices=["keyframes", "all"], default="keyframes",
        help="nerfstudio: the keyframes (default) or every frame tracked well (decoded again from the dataset)",
    )  # fmt: skip
    parser.add_argument(
        "--size", choices=["working", "native"], default="working",
        help="nerfstudio: SLAM's working size (default) or the dataset's own images, depth and intrinsics",
    )  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from pipeline.app.export import NerfstudioOptions, export_run
    from pipeline.devices import resolve_device
    from pipeline.errors import UserError

    if args.to != "nerfstudio" and (args.frames, args.size) != ("keyframes", "working"):
        raise UserError("--frames and --size apply to --to nerfstudio only")
    device = resolve_device(args.device) if args.to == "mesh" else None  # only a mesh is rendered
    output = Path(args.output) if args.output else None
    nerfstudio = NerfstudioOptions(args.frames, args.size)
    exported = export_run(Path(args.run_dir), args.to, output, args.voxel, device, nerfstudio)
    print(f"wrote {exported.path}: {exported.summary}")
    return 0
