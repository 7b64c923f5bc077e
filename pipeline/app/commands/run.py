"""`gsplatam run`: SLAM on a dataset (by default the generated room), or live from a camera."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from pipeline.app.commands.options import (
    LIVE_SPECS,
    SETTINGS_EPILOG,
    add_config_options,
    add_run_folder_options,
    add_viewer_options,
    requested_config,
)
from pipeline.errors import UserError
from pipeline.io.sources.cameras import camera_of

HELP = "SLAM on a dataset (default: a generated synthetic room)"
RUN_CONFIG = "config.toml"  # a run folder's config (RunFolder.config), checked before that module (torch) loads
log = logging.getLogger("gsplatam")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dataset", nargs="?",
        help="dataset folder (Replica, TUM) or bag (ROS 1 .bag, RealSense .bag, ROS 2 folder, .db3, .mcap; default: "
        f"synthetic room); or live, without recording: {LIVE_SPECS}",
    )  # fmt: skip
    add_config_options(parser)
    add_run_folder_options(parser, "<dataset>_<preset>-<date>-<time>")
    parser.add_argument("--resume", metavar="RUN_DIR", help="continue the run in RUN_DIR from its checkpoint")
    parser.add_argument("--loader", choices=["pipelined", "sync"], help="asyncio pipeline (default) or a plain loop")
    parser.add_argument("--profile", action="store_true", help="write a torch-profiler trace into the run folder")
    add_viewer_options(parser)
    parser.epilog = SETTINGS_EPILOG


def run(args: argparse.Namespace) -> int:
    if args.dataset and camera_of(args.dataset):
        return _live(args)
    if args.resume and args.overwrite:
        raise UserError("--resume continues a run, --overwrite replaces one: give one of them")
    resume_config = Path(args.resume) / RUN_CONFIG if args.resume else None
    if resume_config is not None and not args.config and not resume_config.exists():
        raise UserError(f"no {RUN_CONFIG} in {args.resume}: is it a run folder?")
    config, device = requested_config(args, live=False, config_file=resume_config)
    from pipeline.app.report import files_and_next_steps, format_table, resume_command
    from pipeline.app.resume import refuse_a_live_run
    from pipeline.app.run import run_slam
    from pipeline.io.outputs.run_folder import RunFolder

    resume = RunFolder(Path(args.resume)) if args.resume else None
    if resume is not None:
        refuse_a_live_run(resume)
    if not config.dataset.path:
        log.info("no dataset given: running on the generated synthetic room (preset '%s')", config.preset)
    result = run_slam(config, device, resume, args.profile, progress=not args.quiet, overwrite=args.overwrite)
    if result.metrics is not None:
        print(format_table(result.metrics))
        print(files_and_next_steps(result.folder))
        if result.metrics.interrupted:
            print(f"interrupted: continue with  {resume_command(result.folder.path)}")
    return 0


def _live(args: argparse.Namespace) -> int:
    """`run record3d:URL`, `run nerfcapture:`: the live daemon's session, without the `serve` wording."""
    from pipeline.app.commands.serve import ended
    from pipeline.app.serve import serve_live

    config, device = requested_config(args, live=True)
    if args.resume or args.profile or config.run.loader == "sync":
        raise UserError("a live input takes none of --resume, --profile, --loader sync")
    return ended(serve_live(args.dataset, config, device, progress=not args.quiet, overwrite=args.overwrite))
