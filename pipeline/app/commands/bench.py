"""`gsplatam bench`: the benchmark matrix, presets x sequences x variants, one JSON and one table."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import Any

from pipeline.app.bench_matrix import ABLATIONS, SYNTHETIC_SEQUENCES, default_variants
from pipeline.config.choices import unknown_name
from pipeline.errors import UserError

HELP = "benchmark matrix: presets x sequences (x variants), JSON and a table"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "sequences", nargs="*",
        help=f"dataset folders, or generated: {', '.join(SYNTHETIC_SEQUENCES)} (default: synthetic)",
    )  # fmt: skip
    parser.add_argument("--presets", default="tiny", help="comma-separated presets (default: tiny)")
    parser.add_argument("--ablations", action="store_true", help="run every variant below (default: only 'default')")
    parser.add_argument(
        "--variants", metavar="NAME,...",
        help=f"comma-separated variants, the first the ratios' reference: {', '.join(ABLATIONS)} (default: default)",
    )  # fmt: skip
    parser.add_argument(
        "--out", metavar="DIR", default="outputs/bench", help="folder of the JSON and table (default: outputs/bench)"
    )
    parser.add_argument(
        "--stem", default="bench", help="file name of the JSON and table, less .json/.md (default: bench)"
    )
    parser.add_argument(
        "--runs",
        metavar="DIR",
        default="outputs/bench/runs",
        help="where the run folders go (default: outputs/bench/runs)",
    )
    parser.add_argument("--profile", action="store_true", help="profile every cell (trace and summary per run folder)")
    parser.add_argument(
        "--repeats", type=int, default=1, help="run every cell this many times, for the run-to-run spread (default: 1)"
    )
    parser.add_argument(
        "--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
        help="a setting applied to every cell (repeatable; every key: gsplatam config)",
    )  # fmt: skip
    parser.add_argument(
        "--ray", nargs="?", const="", metavar="ADDRESS",
        help="each cell a Ray task, on the cluster at ADDRESS (host:port, or auto) or, without one, a local cluster",
    )  # fmt: skip
    parser.add_argument(
        "--gpus-per-cell", type=float, default=1.0,
        help="with --ray: GPUs each cell declares (fractions share one; default: 1)",
    )  # fmt: skip


def run(args: argparse.Namespace) -> int:
    variants, presets = _checked(args)
    from pipeline.app.bench import cells_of, markdown, run_matrix, write_report
    from pipeline.app.bench_cell import bench_device

    cells = cells_of(args.sequences or ["synthetic"], presets, variants, args.repeats)
    if args.ray is None:
        _check_folders(args.sequences)  # on a cluster only the nodes need to see them: a cell reports it
        device = bench_device(args.overrides)

        def save(partial: dict[str, Any]) -> None:
            write_report(partial, Path(args.out), args.stem)

        report = run_matrix(cells, args.overrides, Path(args.runs), device, not args.quiet, args.profile, save)
    else:
        from pipeline.app.ray_bench import run_matrix_on_ray
        from pipeline.devices import resolve_device

        driver = resolve_device("auto")  # this machine, for the report: the cells run on their nodes' devices
        report = run_matrix_on_ray(
            cells, args.overrides, Path(args.runs), args.ray or None, args.gpus_per_cell, driver, args.profile
        )
    json_path, md_path = write_report(report, Path(args.out), args.stem)
    print(markdown(report))
    print(f"wrote {json_path} and {md_path}")
    if report["interrupted"]:
        print(f"stopped by a signal: {len(report['rows'])} of {len(cells)} cells in the table", file=sys.stderr)
        return 0
    failed = sum(bool(row["error"]) for row in report["rows"])
    if failed:
        print(f"{failed} of {len(cells)} cells failed (their error is in the table)", file=sys.stderr)
    return 1 if failed else 0


def _checked(args: argparse.Namespace) -> tuple[list[str], list[str]]:
    """Every option checked before any cell runs (before torch is imported) -> (variants,
    presets); UserError naming the option otherwise."""
    from pipeline.config import load_config

    variants = args.variants.split(",") if args.variants else default_variants(args.ablations)
    for variant in variants:
        if variant not in ABLATIONS:
            raise unknown_name("variant (--variants)", variant, ABLATIONS)
    if args.repeats < 1:
        raise UserError(f"--repeats must be at least 1, not {args.repeats}")
    if not (math.isfinite(args.gpus_per_cell) and args.gpus_per_cell > 0):
        raise UserError(f"--gpus-per-cell must be > 0, not {args.gpus_per_cell}")
    if not args.stem or "/" in args.stem or args.stem in (".", ".."):
        raise UserError(f"--stem must be a file name, without a folder, not '{args.stem}'")
    _check_output_folder("--out", Path(args.out), [f"{args.stem}.json", f"{args.stem}.md"])
    _check_output_folder("--runs", Path(args.runs), [])
    presets = args.presets.split(",")
    for preset in presets:
        load_config(preset, overrides=args.overrides)  # report bad presets and keys before any work
    return variants, presets


def _check_output_folder(option: str, folder: Path, files: list[str]) -> None:
    """A folder the bench writes into: a folder (or to be made in one) that can be written, its
    `files` not folders; UserError naming `option` otherwise."""
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{option} {folder} is a file: name a folder")
    for name in files:
        if (folder / name).is_dir():
            raise UserError(f"{option}: {folder / name} is a folder, where the bench writes a file")
    existing = next(p for p in (folder, *folder.absolute().parents) if p.exists())
    if not existing.is_dir():
        raise UserError(f"{option} {folder}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise UserError(f"{option} {folder}: cannot write into {existing} (permission denied)")


def _check_folders(sequences: list[str]) -> None:
    missing = [s for s in sequences if s not in SYNTHETIC_SEQUENCES and not Path(s).is_dir()]
    if missing:
        raise UserError(f"dataset folder not found: {missing[0]}")
