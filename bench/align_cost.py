"""GPU time of one `align` solve: eager, compiled, and captured as a CUDA graph.

The solve is what the align tracker does after its one render: the two image pyramids, the
coarse-to-fine Levenberg-Marquardt iterations (tracking.align_iters) and nothing read back.
The frame and the "render" are exact ray casts of the synthetic room (the solve's cost does not
depend on the map), the frame 3 cm and 2 degrees from the render's pose, a hand-held frame-to-
frame motion at 1 m/s. Each variant is timed with CUDA events after warm-up; the median and the
90th percentile over `--repeats` solves, and the host time of the call (the launch cost: on the
GPU an eager solve is bound by it), are written to OUT/align_cost.json.

    python bench/align_cost.py --out bench/results [--sizes 640x480,1200x680] [--repeats 50]

On a machine without CUDA it runs on the CPU (host clock) without the graph variants.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pipeline.app.report import versions
from pipeline.config import SyntheticConfig, load_config
from pipeline.frame import DeviceFrame
from pipeline.geometry import se3_exp
from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.sources.datasets.synthetic import default_intrinsics, make_scene, render_view, trajectory
from pipeline.render import Camera, Gaussians, RenderOutput
from pipeline.slam.cuda_graphs import record
from pipeline.slam.kernels import make_kernels
from pipeline.slam.tracking.align_tracker import AlignTracker
from pipeline.slam.tracking.rgbd_alignment import LmState

WARMUP = 5
MOTION = np.r_[np.radians([1.2, -1.0, 1.2]), [0.02, -0.015, 0.015]]  # ~2 degrees, ~3 cm


def views(width: int, height: int, device: torch.device) -> tuple[DeviceFrame, RenderOutput, np.ndarray]:
    """(the frame at the moved camera, the room seen from the render's pose, the true motion)."""
    scene = make_scene(0).to(device)
    start = trajectory(SyntheticConfig(seed=0), 1)[0]
    moved = se3_exp(torch.from_numpy(MOTION)).numpy()
    k = default_intrinsics(width, height)

    def cast(c2w: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        color, depth = render_view(scene, c2w, k, width, height)
        return torch.from_numpy(color).to(device).float() / 255, torch.from_numpy(depth).to(device)

    color, depth = cast(start @ moved)
    frame = DeviceFrame(1, 0.0, color, depth, torch.tensor(k, dtype=torch.float32, device=device), None)
    render_color, render_depth = cast(start)
    none = torch.zeros(0, device=device)
    rendered = RenderOutput(render_color, render_depth, (render_depth > 0).float(), none, none.bool())
    return frame, rendered, moved


def solver(tracker: AlignTracker, frame: DeviceFrame, rendered: RenderOutput) -> Callable[[], LmState]:
    def solve() -> LmState:
        sources, targets = tracker.prepare(frame, rendered)
        return tracker.solve(sources, targets)

    return solve


def captured(solve: Callable[[], LmState]) -> Callable[[], LmState]:
    """`solve` recorded once as a CUDA graph; calling the result replays it (same inputs' memory)."""
    graph, out = record(solve)

    def replay() -> LmState:
        graph.replay()
        return out

    return replay


def timed(solve: Callable[[], LmState], repeats: int, cuda: bool) -> dict[str, Any]:
    for _ in range(WARMUP):
        state = solve()
    device_ms, host_ms = [], []
    for _ in range(repeats):
        if cuda:
            torch.cuda.synchronize()
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
        t0 = time.perf_counter()
        state = solve()
        host_ms.append(1000 * (time.perf_counter() - t0))
        if cuda:
            end.record()
            torch.cuda.synchronize()
            device_ms.append(start.elapsed_time(end))
        else:
            device_ms.append(host_ms[-1])
    ordered = sorted(device_ms)
    return {
        "median_ms": statistics.median(device_ms),
        "p90_ms": ordered[min(len(ordered) - 1, math.ceil(0.9 * len(ordered)) - 1)],
        "host_median_ms": statistics.median(host_ms),
        "pose": state.pose.cpu().tolist(),
    }


def error_of(pose: list[list[float]], moved: np.ndarray) -> dict[str, float]:
    error = np.linalg.inv(moved) @ np.asarray(pose)
    r = error[:3, :3]
    sine = np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2
    return {
        "mm": 1000 * float(np.linalg.norm(error[:3, 3])),
        "deg": math.degrees(math.atan2(sine, (np.trace(r) - 1) / 2)),
    }


def measure(width: int, height: int, repeats: int, device: torch.device) -> dict[str, Any]:
    config = load_config("tiny").tracking
    frame, rendered, moved = views(width, height, device)
    cuda = device.type == "cuda"

    def shows_the_view(gaussians: Gaussians, camera: Camera) -> RenderOutput:
        return rendered  # never called: prepare() takes the render itself

    eager = solver(AlignTracker(shows_the_view, config, 0.01, 100.0), frame, rendered)
    compiled_kernels = make_kernels(compiled=True).align
    compiled = solver(AlignTracker(shows_the_view, config, 0.01, 100.0, compiled_kernels), frame, rendered)
    variants = {"eager": eager, "compiled": compiled}
    if cuda:
        variants.update({"graph": eager, "compiled+graph": compiled})
    row: dict[str, Any] = {"size": f"{width}x{height}", "align_iters": list(config.align_iters)}
    for name, solve in variants.items():
        try:
            result = timed(captured(solve) if name.endswith("graph") else solve, repeats, cuda)
        except Exception as exc:  # a variant that cannot run here is reported, not fatal
            row[name] = {"error": f"{type(exc).__name__}: {exc}"[:300]}
            print(f"{width}x{height} {name}: {row[name]['error']}", flush=True)
            continue
        result["error_vs_truth"] = error_of(result.pop("pose"), moved)
        row[name] = result
        print(
            f"{width}x{height} {name}: {result['median_ms']:.2f} ms (host {result['host_median_ms']:.2f} ms)",
            flush=True,
        )
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--sizes", default="640x480,1200x680")
    parser.add_argument("--repeats", type=int, default=50)
    args = parser.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    sizes = [tuple(int(x) for x in size.split("x")) for size in args.sizes.split(",")]
    rows = [measure(width, height, args.repeats, device) for width, height in sizes]
    report = {
        "device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
        "versions": versions(),
        "rows": rows,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "align_cost.json", json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
