"""`gsplatam download`: a public RGB-D sequence (TUM RGB-D, Replica, 7-Scenes) from its publisher."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from pipeline.io.sources.datasets.catalogue import KINDS

HELP = "fetch a public sequence (TUM RGB-D, Replica, 7-Scenes) into a folder run reads"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("kind", choices=KINDS, help="the dataset")
    parser.add_argument(
        "name", nargs="?",
        help="the sequence: tum fr1/desk, replica room0, 7scenes chess/seq-01 (without it: the names)",
    )  # fmt: skip
    parser.add_argument("destination", nargs="?", default="data", help="where it goes (default: data)")


def run(args: argparse.Namespace) -> int:
    from pipeline.io.sources.datasets.catalogue import catalogue

    if args.name is None:
        names = list(catalogue()[args.kind])
        if args.kind == "7scenes":
            names = [f"{name}/seq-NN" for name in names]
        print(f"{args.kind} sequences: {', '.join(names)}")
        return 0
    from pipeline.app.download import download_sequence
    from pipeline.app.report import gsplatam_command

    folder = download_sequence(args.kind, args.name, Path(args.destination), progress=not args.quiet)
    print(f"{args.kind} {args.name} is in {folder}")
    print(f"next:\n  {gsplatam_command()} run {shlex.quote(str(folder))}")
    return 0
