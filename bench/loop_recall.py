"""Loop verification's recall on real revisits, and what it says of look-alike places.

A sequence's revisits are the pairs of frames at least `--gap` frames apart whose reference
poses put the cameras within `--radius` metres and `--angle` degrees of each other with at least
`--overlap` of the later frame's sampled pixels inside the earlier one's image (by the
reference, not by any estimate). Each pair is verified (`detection.verify`, the `loops.*`
settings of `--set`) from its reference relative pose moved by a drift of `--drift` metres and
degrees (a random direction per pair), as the estimates of a drifted run would start it; the
recall is the fraction verified, and each pair's statistics (inlier fraction, RMS residuals,
conditioning, coverage, where it ended against the reference) are written, so that the
thresholds can be set from them. `--trap` adds the generated trap room's twin places (2 m
apart, alike by appearance) started from the relative pose the twins' estimates would give a
camera that took one for the other: what a verification must refuse.

    python bench/loop_recall.py --out bench/results --data ../shared/data/tum_fr3_cabinet_kf57 \\
        --size 80x60 [--data ../shared/data/tum_fr1_xyz_37 --gap 15] [--trap] [--set loops.max_residual_m=0.02]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from pipeline.app.report import versions
from pipeline.config import DatasetConfig, SyntheticConfig, load_config
from pipeline.geometry import invert_pose, se3_exp
from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic import synthetic_for
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.slam.keyframes import Keyframe, overlap_fractions, sample_valid_pixels
from pipeline.slam.loops.detection import verify
from pipeline.slam.loops.pose_graph import motion_size
from pipeline.slam.loops.search import LoopSearch
from pipeline.stages.upload import host_frame_tensors


def frames_of(path: Path, width: int, height: int) -> tuple[list[Keyframe], torch.Tensor, torch.Tensor]:
    """Every frame of a sequence as a keyframe at its reference pose -> (keyframes, reference
    poses [N, 4, 4] float64, intrinsics [3, 3])."""
    dataset = open_dataset(DatasetConfig(path=str(path), width=width, height=height))
    frames = [host_frame_tensors(frame) for frame in dataset.frames()]
    assert all(frame.c2w_gt is not None for frame in frames), f"{path} has no reference pose for every frame"
    truth = torch.stack([frame.c2w_gt.double() for frame in frames])  # type: ignore[union-attr]
    keyframes = [Keyframe.of(f.index, f.color, f.depth, c2w.float()) for f, c2w in zip(frames, truth)]
    return keyframes, truth, frames[0].intrinsics


def revisits(
    keyframes: list[Keyframe], truth: torch.Tensor, intrinsics: torch.Tensor, args: argparse.Namespace
) -> list[tuple[int, int]]:
    """(earlier, later) frame pairs that see the same place again, by the reference poses."""
    generator = torch.Generator().manual_seed(0)
    pairs = []
    for later in range(len(keyframes)):
        pixels = sample_valid_pixels(keyframes[later].depth, 1600, generator)
        overlap = overlap_fractions(keyframes[later].depth, intrinsics, truth[later].float(), truth.float(), pixels)
        for earlier in range(later - args.gap + 1):
            size = motion_size(invert_pose(truth[earlier]) @ truth[later])
            near = size.translation_m <= args.radius and size.rotation_deg <= args.angle
            if near and float(overlap[earlier]) >= args.overlap:
                pairs.append((earlier, later))
    return pairs


def drift(size: float, seed: int) -> torch.Tensor:
    """A rigid motion [4, 4] float64 of `size` metres along and `size` x DEG_PER_M degrees about
    random directions."""
    generator = torch.Generator().manual_seed(seed)
    axes = torch.nn.functional.normalize(torch.randn(2, 3, generator=generator, dtype=torch.float64), dim=-1)
    return se3_exp(torch.cat([math.radians(size * DEG_PER_M) * axes[0], size * axes[1]]))


DEG_PER_M = 40.0  # drifted runs turn about 4 degrees per 10 cm they slip (as in the cabinet's tracking)


def check(
    keyframes: list[Keyframe],
    truth: torch.Tensor,
    intrinsics: torch.Tensor,
    pairs: list[tuple[int, int]],
    starts: list[torch.Tensor],
    search: LoopSearch,
) -> list[dict[str, Any]]:
    """Each pair verified from its start (the later camera in the earlier one's, [4, 4] float64)."""
    rows = []
    for (earlier, later), start in zip(pairs, starts):
        sources = search.kept([keyframes[earlier], keyframes[later]], intrinsics)
        began = time.perf_counter()
        result = verify(sources, search.views, keyframes[earlier], start, intrinsics, search.config, search.tracking)
        seconds = time.perf_counter() - began
        error = motion_size(invert_pose(invert_pose(truth[earlier]) @ truth[later]) @ result.relative)
        report = result.report
        rows.append(
            {
                "pair": [earlier, later],
                "verified": not result.failure,
                "failure": result.failure,
                "inlier_fraction": report.inliers / max(report.associated, 1),
                "coverage": result.coverage,
                "rms_cm": 100 * report.rms_m,
                "rms_intensity": report.rms_intensity,
                "conditioning": report.conditioning,
                "error_cm": 100 * error.translation_m,
                "error_deg": error.rotation_deg,
                "seconds": seconds,
            }
        )
    return rows


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The recall and each statistic's range over the pairs verified."""
    verified = [row for row in rows if row["verified"]]
    keys = ("inlier_fraction", "coverage", "rms_cm", "rms_intensity", "conditioning", "error_cm", "error_deg")
    ranges = {key: [min(r[key] for r in verified), max(r[key] for r in verified)] for key in keys} if verified else {}
    failures: dict[str, int] = {}
    for row in rows:
        if row["failure"]:
            reason = row["failure"].split(" (")[0].split(":")[0]
            failures[reason] = failures.get(reason, 0) + 1
    return {
        "pairs": len(rows),
        "verified": len(verified),
        "recall": len(verified) / len(rows) if rows else None,
        "verified_ranges": ranges,
        "failures": failures,
        "median_seconds": statistics.median(r["seconds"] for r in rows) if rows else None,
    }


def trap_rows(args: argparse.Namespace, search: LoopSearch, work: Path) -> list[dict[str, Any]]:
    """The trap room's twin places: a frame and the frame of the other half that looks most like it."""
    config = SyntheticConfig(trap=True, width=args.width, height=args.height, speed=1.0, fps=6.0, layout="tum")
    write_synthetic(work / "trap", synthetic_for(config, torch.device("cpu")), progress=False)
    keyframes, truth, intrinsics = frames_of(work / "trap", args.width, args.height)
    half = len(keyframes) // 2
    pairs = [(k, k + half) for k in range(0, half, max(1, half // 12))]  # the twins sit half the path apart
    starts = [torch.eye(4, dtype=torch.float64)] * len(pairs)  # one that took a twin for the other: "right there"
    return check(keyframes, truth, intrinsics, pairs, starts, search)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--data", action="append", required=True, help="a TUM-layout sequence (repeatable)")
    parser.add_argument("--size", default="80x60", help="working size WIDTHxHEIGHT")
    parser.add_argument("--gap", type=int, default=10, help="frames apart at least")
    parser.add_argument("--radius", type=float, default=0.6, help="metres between the cameras at most")
    parser.add_argument("--angle", type=float, default=45.0, help="degrees between the views at most")
    parser.add_argument("--overlap", type=float, default=0.3, help="share of the later frame in the earlier's image")
    parser.add_argument("--drift", type=float, default=0.1, help="metres of drift the verification starts from")
    parser.add_argument("--max-pairs", type=int, default=40, help="pairs verified per sequence at most (evenly spread)")
    parser.add_argument("--trap", action="store_true", help="also the generated trap room's twin places")
    parser.add_argument("--set", action="append", default=[], help="config overrides (loops.*, tracking.*)")
    args = parser.parse_args()
    args.width, args.height = (int(v) for v in args.size.split("x"))
    config = load_config("tiny", overrides=args.set)
    search = LoopSearch(config.loops, config.tracking)
    out = Path(args.out)
    report: dict[str, Any] = {"versions": versions(), "args": {k: v for k, v in vars(args).items()}, "sequences": {}}
    for path in args.data:
        keyframes, truth, intrinsics = frames_of(Path(path), args.width, args.height)
        pairs = revisits(keyframes, truth, intrinsics, args)
        pairs = pairs[:: max(1, math.ceil(len(pairs) / args.max_pairs))]
        starts = [invert_pose(truth[a]) @ truth[b] @ drift(args.drift, seed) for seed, (a, b) in enumerate(pairs)]
        rows = check(keyframes, truth, intrinsics, pairs, starts, search)
        report["sequences"][Path(path).name] = {"summary": summary(rows), "rows": rows}
        print(f"{Path(path).name}: {json.dumps(summary(rows))}", flush=True)
    if args.trap:
        with tempfile.TemporaryDirectory() as work:  # the generated room: not a result
            rows = trap_rows(args, search, Path(work))
        report["sequences"]["trap_twins"] = {"summary": summary(rows), "rows": rows}
        print(f"trap twins: {json.dumps(summary(rows))}", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / f"loop_recall_{args.size}.json", json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
