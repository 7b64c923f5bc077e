"""`gsplatam view`: a saved map (a run folder or a 3DGS PLY) in the browser or an Open3D window."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.app.commands.options import add_viewer_options
from pipeline.errors import UserError

HELP = "viewer for a saved map: a run folder or a 3DGS PLY"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="run folder (map.ply, trajectory.txt) or a .ply file")
    parser.add_argument("--open3d", action="store_true", help="in a desktop window (Open3D) instead of the browser")
    parser.add_argument("--rerun", action="store_true", help="in rerun's viewer, with the cameras and trajectories")
    parser.add_argument("--rerun-save", metavar="FILE", help="write what --rerun shows to this .rrd file instead")
    add_viewer_options(parser, always=True)


def run(args: argparse.Namespace) -> int:
    if args.rerun or args.rerun_save:
        from pipeline.ui.rerun_replay import replay_saved_run

        print(replay_saved_run(Path(args.path), Path(args.rerun_save) if args.rerun_save else None))
        return 0
    from pipeline.app.view import view_saved_map

    if args.viewer_port is not None and not 1 <= args.viewer_port <= 65535:
        raise UserError(f"--viewer-port {args.viewer_port} is not a port (1 to 65535)")
    view_saved_map(Path(args.path), args.open3d, args.viewer_host or "127.0.0.1", args.viewer_port or 8080)
    return 0
