"""How far a map seeded from one frame pulls that frame off its pose, per renderer and seed
size (#35, bench/NOTES.md Change 40): on the CPU's reference renderer smaller, nearly opaque
seeds cut the pull; on the H200 at 640x480 they tracked a real loop worse. This separates the
renderer from the resolution.

For each frame (the generator's room, and a dataset's frame where --dataset is given), size,
renderer (the reference; gsplat too on CUDA) and seed setting (scale in pixel footprints,
opacity, eps2d in pixels^2): seeds a map from the frame at its true pose, renders it there and
aligns the frame to it with `tiny`'s tracker from the true pose. Columns: the render's depth
error relative to the frame's (median, where the silhouette passes 0.99, SplaTAM's mask), the
share of valid pixels under that mask, and how far the solve moved the camera (cm; 0 is right).
Usage: python3 bench/seed_bias.py --out DIR [--dataset FOLDER --index 10] [--sizes 160x120,640x480]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.app.report import versions  # noqa: E402
from pipeline.config import DatasetConfig, RenderBackend, SyntheticConfig, load_config  # noqa: E402
from pipeline.frame import DeviceFrame, Frame  # noqa: E402
from pipeline.geometry import invert_pose  # noqa: E402
from pipeline.io.files.atomic import atomic_write_text  # noqa: E402
from pipeline.io.sources.datasets.loader import open_dataset  # noqa: E402
from pipeline.io.sources.datasets.synthetic import default_intrinsics, make_scene, render_view, trajectory  # noqa: E402
from pipeline.render import Camera, make_renderer  # noqa: E402
from pipeline.slam.gaussian_map import seed_gaussians  # noqa: E402
from pipeline.slam.tracking.align_tracker import AlignTracker  # noqa: E402
from pipeline.stages.upload import make_uploader  # noqa: E402

SEEDS = {"splatam (1, 0.5, 0.3)": (1.0, 0.5, 0.3), "small (0.35, 0.99, 0.1)": (0.35, 0.99, 0.1)}


def generated_frame(width: int, height: int) -> tuple[Frame, torch.Tensor]:
    """The generator's room seen from its fast loop's 11th pose, as in tests/slam/test_slam.py
    -> (frame, c2w [4, 4])."""
    synthetic = SyntheticConfig(width=width, height=height, speed=1.0, fps=8.0, loops=1)
    c2w = trajectory(synthetic, 11)[10]
    intrinsics = default_intrinsics(width, height)
    color, depth = render_view(make_scene(0), c2w, intrinsics, width, height)
    return Frame(0, 0.0, color, depth, intrinsics, None), torch.from_numpy(c2w).float()


def dataset_frame(folder: str, index: int, width: int, height: int) -> tuple[Frame, torch.Tensor]:
    """Frame `index` of a dataset at width x height -> (frame, c2w [4, 4]: the identity, since
    the map is seeded and tracked in the frame's own coordinates)."""
    dataset = open_dataset(DatasetConfig(path=folder, width=width, height=height))
    return dataset.decode(dataset.refs[index]), torch.eye(4)


def measure(frame: DeviceFrame, c2w: torch.Tensor, backend: RenderBackend, seeds: tuple[float, float, float]) -> dict:
    scale, opacity, eps2d = seeds
    config = load_config("tiny", overrides=[f"render.backend={backend}", f"render.eps2d={eps2d}"])
    gaussian_config = replace(config.gaussians, seed_scale=scale, seed_opacity=opacity)
    device = frame.depth.device
    renderer = make_renderer(config.render, gaussian_config, device)
    gaussians = seed_gaussians(frame.color, frame.depth, frame.intrinsics, c2w, frame.depth > 0, gaussian_config)
    height, width = frame.depth.shape
    with torch.no_grad():
        out = renderer(gaussians, Camera(invert_pose(c2w), frame.intrinsics, width, height))
    valid = frame.depth > 0
    covered = valid & (out.silhouette > 0.99)
    relative = (out.depth[covered] - frame.depth[covered]) / frame.depth[covered]
    tracker = AlignTracker(renderer, config.tracking, 0.01, 100.0)
    moved = tracker(gaussians, frame, c2w).c2w[:3, 3] - c2w[:3, 3]
    return {
        "depth_error_median_pct": 100 * float(relative.median()) if relative.numel() else None,
        "covered_pct": 100 * float(covered.sum() / valid.sum().clamp(min=1)),
        "moved_cm": 100 * float(moved.norm()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--dataset", help="a TUM or Replica folder with reference poses")
    parser.add_argument("--index", type=int, default=10, help="the dataset frame seeded and tracked")
    parser.add_argument("--sizes", default="160x120,640x480")
    args = parser.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    backends: list[RenderBackend] = ["reference", "gsplat"] if device.type == "cuda" else ["reference"]
    rows = []
    for size in args.sizes.split(","):
        width, height = (int(n) for n in size.split("x"))
        frames = {"generated room": generated_frame(width, height)}
        if args.dataset:
            frames[f"{Path(args.dataset).name}[{args.index}]"] = dataset_frame(args.dataset, args.index, width, height)
        for name, (host, c2w_host) in frames.items():
            frame, c2w = make_uploader(device, slots=1)(host).wait(), c2w_host.to(device)
            for backend in backends:
                for seeds_name, seeds in SEEDS.items():
                    row = {"frame": name, "size": size, "renderer": backend, "seeds": seeds_name}
                    row |= measure(frame, c2w, backend, seeds)
                    rows.append(row)
                    print(json.dumps(row), flush=True)
                    write(args.out, rows)


def write(out: Path, rows: list[dict]) -> None:
    """seed_bias.json and seed_bias.md in `out`, rewritten after every row."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "seed_bias.json", json.dumps({"versions": versions(), "rows": rows}, indent=1))
    lines = [
        "| frame | size | renderer | seeds | depth error (median) | covered | moved |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        depth = "-" if r["depth_error_median_pct"] is None else f"{r['depth_error_median_pct']:+.2f}%"
        lines.append(
            f"| {r['frame']} | {r['size']} | {r['renderer']} | {r['seeds']} | {depth} | {r['covered_pct']:.1f}% | {r['moved_cm']:.2f} cm |"
        )
    atomic_write_text(out / "seed_bias.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
