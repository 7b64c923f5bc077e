"""`gsplatam fake-nerfcapture`: a dataset published over DDS as the NeRFCapture app would."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

HELP = "publish a dataset as the NeRFCapture app would (DDS)"
log = logging.getLogger("gsplatam")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dataset", help="dataset folder (default: the generated synthetic room)")
    parser.add_argument("--fps", type=float, default=10.0, help="frame rate")
    parser.add_argument("--wait", type=float, default=60.0, help="seconds to wait for a receiver")
    parser.add_argument("--domain", type=int, default=0, help="DDS domain id (default: 0, the app's)")
    parser.add_argument("--loop", action="store_true", help="start over at the end instead of ending the stream")
    parser.add_argument("--output", default="outputs", help="where the generated synthetic room is cached")


def run(args: argparse.Namespace) -> int:
    from pipeline.io.sources.live.fake_nerfcapture import publish_dataset
    from pipeline.io.sources.live.fake_scene import fake_phone_dataset

    dataset = fake_phone_dataset(args.dataset, Path(args.output), not args.quiet)
    log.info(
        "fake NeRFCapture: publishing %s (%d frames at %g fps) once a receiver matches",
        dataset.name, len(dataset), args.fps,
    )  # fmt: skip
    sent = publish_dataset(dataset, args.fps, args.wait, domain_id=args.domain, loop=args.loop)
    print(f"published {sent} frames")
    return 0 if sent else 1
