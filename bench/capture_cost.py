"""What one mapping step costs the host and the GPU: gsplat's rasterisation (which reads the
intersection count back), the fixed-capacity render (no host read), and that render's step
recorded once as a CUDA graph and replayed.

A step is what mapping runs per optimiser step: render the views (colour, depth, silhouette),
the mapping loss (compiled, as on CUDA), backward, Adam (fused). Run on a CUDA machine:
`python bench/capture_cost.py --out DIR` (writes capture_cost.json).
Columns: wall ms per step (host-timed over `--steps` steps, one synchronisation at the end),
kernel ms per step (CUPTI, the union of kernel intervals), and their ratio (1.0: the GPU never
waits for the host).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.app.report import versions  # noqa: E402
from pipeline.geometry import se3_exp  # noqa: E402
from pipeline.io.files.atomic import atomic_write_text
from pipeline.render.types import Camera, Gaussians  # noqa: E402
from pipeline.slam.cuda_graphs import record  # noqa: E402
from pipeline.slam.kernel_time import union_ms  # noqa: E402
from pipeline.slam.kernels import make_kernels  # noqa: E402
from pipeline.slam.mapping.optimizers import EPS  # noqa: E402
from tests.gpu.gpu_scenes import leaves, random_pose, random_scene  # noqa: E402

WIDTH, HEIGHT = 640, 480
HEADROOM = 1.5  # capacity over the intersections of the first render


def _targets(views: int, generator: torch.Generator, device: torch.device) -> list[tuple[torch.Tensor, torch.Tensor]]:
    return [
        (
            torch.rand(HEIGHT, WIDTH, 3, generator=generator).to(device),
            1 + 3 * torch.rand(HEIGHT, WIDTH, generator=generator).to(device),
        )
        for _ in range(views)
    ]


def _step_fn(
    params: Gaussians, cameras: list[Camera], targets, render: Callable, optimizer: torch.optim.Optimizer
) -> Callable[[], None]:
    loss_fn = make_kernels(compiled=True).mapping_loss

    def step() -> None:
        outputs = render(params, cameras)
        loss = torch.stack(
            [
                loss_fn(out.color, out.depth, color, depth, 0.2, 1.0, 0.5)
                for out, (color, depth) in zip(outputs, targets)
            ]
        ).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    return step


def _measure(run: Callable[[], None], steps: int) -> dict[str, float]:
    """Wall and kernel ms per step of `steps` calls of `run` (after warming up)."""
    for _ in range(5):
        run()
    torch.cuda.synchronize()
    started = time.perf_counter()
    for _ in range(steps):
        run()
    host_ms = (time.perf_counter() - started) * 1000 / steps  # launching alone, before the final wait
    torch.cuda.synchronize()
    wall_ms = (time.perf_counter() - started) * 1000 / steps
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            run()
        torch.cuda.synchronize()
    kernels = [(e.time_range.start, e.time_range.end) for e in prof.events() if e.device_type == DeviceType.CUDA]
    kernel_ms = union_ms(kernels) / 1000 / steps
    return {"wall_ms": wall_ms, "host_ms": host_ms, "kernel_ms": kernel_ms, "wall_over_kernel": wall_ms / kernel_ms}


def case(n: int, views: int, steps: int, device: torch.device) -> dict:
    from pipeline.render.gsplat_backend import render_gsplat_3d_capacity, render_gsplat_3d_views

    generator = torch.Generator().manual_seed(n + views)
    k = torch.tensor([[525.0, 0, WIDTH / 2], [0, 525.0, HEIGHT / 2], [0, 0, 1]], device=device)
    c2w = random_pose(generator, device)
    scene = random_scene(n, True, c2w, k, WIDTH, HEIGHT, generator)
    nudges = [
        se3_exp(0.02 * torch.randn(6, generator=generator, dtype=torch.float64)).float().to(device)
        for _ in range(views)
    ]
    poses = [c2w @ nudge for nudge in nudges]  # views a few centimetres and degrees apart
    cameras = [Camera(torch.linalg.inv(p), k, WIDTH, HEIGHT) for p in poses]
    targets = _targets(views, generator, device)
    with torch.no_grad():
        count = int(render_gsplat_3d_capacity(scene, cameras, 1)[1].count)
    capacity = int(HEADROOM * count)

    def adam(params: Gaussians, capturable: bool) -> torch.optim.Adam:
        groups = [{"params": [t], "lr": 1e-3} for t in vars(params).values()]
        return torch.optim.Adam(groups, eps=EPS, fused=True, capturable=capturable)

    def capacity_render(params: Gaussians, cams: list[Camera]):
        return render_gsplat_3d_capacity(params, cams, capacity)[0]

    row: dict = {"gaussians": n, "views": views, "intersections": count, "capacity": capacity}
    params = leaves(scene)
    row["gsplat_eager"] = _measure(
        _step_fn(params, cameras, targets, render_gsplat_3d_views, adam(params, False)), steps
    )
    params = leaves(scene)
    row["capacity_eager"] = _measure(_step_fn(params, cameras, targets, capacity_render, adam(params, True)), steps)
    params = leaves(scene)
    graphed, _ = record(_step_fn(params, cameras, targets, capacity_render, adam(params, True)))
    row["capacity_graphed"] = _measure(graphed.replay, steps)
    print(json.dumps(row), flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=100)
    args = parser.parse_args()
    device = torch.device("cuda")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [case(n, views, args.steps, device) for n in (100_000, 300_000) for views in (1, 2)]
    report = {
        "device": torch.cuda.get_device_name(device),
        "versions": versions(),
        "size": f"{WIDTH}x{HEIGHT}",
        "rows": rows,
    }
    atomic_write_text(args.out / "capture_cost.json", json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
