"""`gsplatam bench`: the benchmark matrix, presets x sequences x variants, one JSON and one table."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.errors import UserError

HELP = "benchmark matrix: presets x sequences (x ablations), JSON and a table"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sequences", nargs="*", help="dataset folders (default: the synthetic room)")
    parser.add_argument("--presets", default="tiny", help="comma-separated presets (default: tiny)")
    parser.add_argument("--ablations", action="store_true", help="also run each side-by-side switch")
    parser.add_argument("--variants", help="comma-separated variants instead of --ablations' full set")
    parser.add_argument("--out", default="bench/results", help="where the JSON and table go")
    parser.add_argument("--stem", default="bench", help="file name stem of the JSON and table")
    parser.add_argument("--runs", default="outputs/bench", help="where the run folders go")
    parser.add_argument("--profile", action="store_true", help="profile every cell (trace and summary per run folder)")
    parser.add_argument("--repeats", type=int, default=1, help="run every cell this many times (run-to-run spread)")
    parser.add_argument(
        "--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[], help="applied to every cell"
    )
    parser.add_argument(
        "--ray", nargs="?", const="", metavar="ADDRESS",
        help="each cell a Ray task, on the cluster at ADDRESS (host:port, or auto) or, without one, a local cluster",
    )  # fmt: skip
    parser.add_argument(
        "--gpus-per-cell", type=float, default=1.0, help="with --ray: GPUs each cell declares (fractions share one)"
    )


def run(args: argparse.Namespace) -> int:
    from pipeline.app.bench import (
        ABLATIONS,
        bench_device,
        cells_of,
        default_variants,
        markdown,
        run_matrix,
        write_report,
    )
    from pipeline.config import load_config

    variants = args.variants.split(",") if args.variants else default_variants(args.ablations)
    unknown = [v for v in variants if v not in ABLATIONS]
    if unknown:
        raise UserError(f"unknown variant '{unknown[0]}' (choose from {', '.join(ABLATIONS)})")
    presets = args.presets.split(",")
    if args.repeats < 1:
        raise UserError("--repeats must be at least 1")
    for preset in presets:
        load_config(preset, overrides=args.overrides)  # report bad presets and keys before any work
    cells = cells_of(args.sequences or ["synthetic"], presets, variants, args.repeats)
    if args.ray is None:
        _check_folders(args.sequences)  # on a cluster only the nodes need to see them: a cell reports it
        device = bench_device(args.overrides)
        report = run_matrix(cells, args.overrides, Path(args.runs), device, not args.quiet, args.profile)
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
    failed = sum(bool(row["error"]) for row in report["rows"])
    if failed:
        print(f"{failed} of {len(cells)} cells failed (their error is in the table)", file=sys.stderr)
    return 1 if failed else 0


def _check_folders(sequences: list[str]) -> None:
    from pipeline.app.bench import SYNTHETIC_SEQUENCES

    missing = [s for s in sequences if s not in SYNTHETIC_SEQUENCES and not Path(s).is_dir()]
    if missing:
        raise UserError(f"dataset folder not found: {missing[0]}")
