"""`gsplatam export`: a run folder to nerfstudio, .splat, a full PLY, a mesh or a point cloud."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.outputs.exports import FORMATS

HELP = "a run folder to nerfstudio, .splat, a full PLY, a mesh or a point cloud"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", help="run folder")
    parser.add_argument("--to", required=True, choices=list(FORMATS), help="the format")
    parser.add_argument("--output", metavar="PATH", help="file (folder for nerfstudio); default: in the run folder")
    parser.add_argument("--voxel", type=float, default=0.02, help="mesh: TSDF voxel size, metres (default: 0.02)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="mesh: where to render")


def run(args: argparse.Namespace) -> int:
    from pipeline.app.export import export_run
    from pipeline.devices import resolve_device

    device = resolve_device(args.device) if args.to == "mesh" else None  # only a mesh is rendered
    output = Path(args.output) if args.output else None
    exported = export_run(Path(args.run_dir), args.to, output, args.voxel, device)
    print(f"wrote {exported.path}: {exported.summary}")
    return 0
