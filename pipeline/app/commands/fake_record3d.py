"""`gsplatam fake-record3d`: a fake Record3D phone streaming a dataset, until Ctrl-C."""

from __future__ import annotations

import argparse
import asyncio
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.errors import UserError

if TYPE_CHECKING:
    from pipeline.io.sources.datasets.base import Dataset

HELP = "a fake Record3D phone streaming a dataset (for tests and demos)"
log = logging.getLogger("gsplatam")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dataset", help="dataset folder (default: the generated synthetic room)")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default: 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8000, help="HTTP port (the real app uses 80)")
    parser.add_argument("--fps", type=float, default=30.0, help="frame rate of the stream")
    parser.add_argument("--loop", action="store_true", help="start over at the end instead of ending the stream")
    parser.add_argument("--output", default="outputs", help="where the generated synthetic room is cached")


def run(args: argparse.Namespace) -> int:
    from pipeline.io.sources.live.fake_scene import fake_phone_dataset

    if not 0 <= args.port <= 65535:
        raise UserError(f"--port {args.port} is not a port (0 to 65535; 0: any free one)")
    dataset = fake_phone_dataset(args.dataset, Path(args.output), not args.quiet)
    asyncio.run(_stream(dataset, args.host, args.port, args.fps, args.loop))
    return 0


async def _stream(dataset: Dataset, host: str, port: int, fps: float, loop: bool) -> None:
    """Serve the phone's endpoints until cancelled (Ctrl-C)."""
    from pipeline.io.sources.live.fake_record3d import FakePhone

    phone = FakePhone(dataset, fps, loop)
    try:
        bound = await phone.start(host, port)
    except OSError as exc:
        await phone.stop()
        raise UserError(f"cannot serve on {host}:{port}: {exc.strerror or exc}") from None
    log.info(
        "fake Record3D phone: http://%s:%d (%s, %d frames at %g fps)", host, bound, dataset.name, len(dataset), fps
    )
    try:
        await asyncio.Event().wait()
    finally:
        await phone.stop()
