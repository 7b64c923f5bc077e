"""`gsplatam serve`: the live daemon, from a phone's stream until Ctrl-C (several, on Ray)."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from pipeline.app.commands.options import (
    add_config_options,
    add_run_folder_options,
    add_viewer_options,
    requested_config,
)
from pipeline.errors import UserError
from pipeline.io.sources.cameras import CAMERAS

if TYPE_CHECKING:
    from pipeline.app.serve import ServeResult

HELP = "live daemon: reconstruct from a phone or a RealSense camera until Ctrl-C"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    for scheme, camera in CAMERAS.items():  # --record3d URL, --nerfcapture [DOMAIN]: one option per camera
        optional: dict[str, Any] = {"nargs": "?", "const": ""} if camera.address_optional else {}
        parser.add_argument(
            f"--{scheme}", metavar=camera.metavar, action="append", default=[], help=camera.help, **optional
        )
    parser.add_argument(
        "--ray", nargs="?", const="", metavar="ADDRESS",
        help="every source a session on the Ray cluster at ADDRESS (host:port, or auto) or, without one, a local cluster",
    )  # fmt: skip
    parser.add_argument(
        "--gpus-per-session",
        type=float,
        default=1.0,
        help="with --ray: GPUs each session declares (fractions share one)",
    )
    add_config_options(parser)
    add_run_folder_options(parser, "live_<source>_<preset>-<date>-<time>")
    add_viewer_options(parser)


def run(args: argparse.Namespace) -> int:
    specs = [f"{scheme}:{address}" for scheme in CAMERAS for address in getattr(args, scheme)]
    if not specs:
        options = " or ".join(f"--{scheme} {camera.metavar}" for scheme, camera in CAMERAS.items())
        raise UserError(f"serve needs a source: {options}")
    config, device = requested_config(args, live=True)
    if args.ray is not None:
        from pipeline.app.ray_serve import serve_on_ray

        return serve_on_ray(specs, config, args.ray or None, args.gpus_per_session)
    if len(specs) > 1:
        raise UserError("several sources need --ray (each a session of its own)")
    from pipeline.app.serve import serve_live

    return ended(serve_live(specs[0], config, device, progress=not args.quiet, overwrite=args.overwrite))


def ended(result: ServeResult) -> int:
    """Print how a live session ended -> its exit code: 1 when the source ended by itself (a
    camera lost: what was processed is saved), else 0 (Ctrl-C, SIGTERM)."""
    from pipeline.app.report import live_outcome

    if result.metrics is None:
        return 0
    print(live_outcome(result.folder, result.metrics))
    if result.metrics.interrupted:
        return 0
    why = result.metrics.counters.get("last_error") or "its stream ended"
    print(f"gsplatam: error: the live source ended ({why}); what was processed is saved", file=sys.stderr)
    return 1
