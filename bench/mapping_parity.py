"""GPU checks of mapping's fast paths against their plain twins (run on the device machine).

1. Several cameras in one batched gsplat rasterisation against one call per camera: images and
   the gradient of the means.
2. gsplat's SelectiveAdam (fused CUDA kernel) against SelectiveAdamReference, step by step.

Writes mapping_parity.json under --out; prints the worst differences.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from pipeline.app.report import versions
from pipeline.config import GaussianConfig, RenderConfig
from pipeline.geometry import invert_pose
from pipeline.io.files.atomic import atomic_write_text
from pipeline.render import Camera, Gaussians, make_renderer, make_views_renderer
from pipeline.slam.mapping.optimizers import SelectiveAdamReference, make_map_optimizer


def random_scene(n: int, device: torch.device) -> Gaussians:
    g = torch.Generator(device="cpu").manual_seed(0)
    means = torch.randn(n, 3, generator=g) * torch.tensor([1.0, 0.6, 0.5]) + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    return Gaussians(
        means.to(device),
        quats.to(device),
        (torch.rand(n, 1, generator=g) * -2 - 3.5).to(device),
        torch.randn(n, generator=g).to(device),
        torch.rand(n, 3, generator=g).to(device),
    )


def cameras(device: torch.device, count: int) -> list[Camera]:
    k = torch.tensor([[600.0, 0, 599.5], [0, 600.0, 339.5], [0, 0, 1]], device=device)
    out = []
    for i in range(count):
        c2w = torch.eye(4, device=device)
        c2w[0, 3] = 0.05 * i
        out.append(Camera(invert_pose(c2w), k, 1200, 680))
    return out


def batched_against_single(device: torch.device) -> dict[str, float]:
    scene = random_scene(200_000, device)
    single = make_renderer(RenderConfig(backend="gsplat"), GaussianConfig(), device)
    views = make_views_renderer(RenderConfig(backend="gsplat"), GaussianConfig(), device)
    cams = cameras(device, 3)
    worst = {"color": 0.0, "depth": 0.0, "silhouette": 0.0, "means_grad": 0.0}
    grads = []
    for render in ("single", "batched"):
        means = scene.means.clone().requires_grad_(True)
        g = Gaussians(means, scene.quats, scene.log_scales, scene.opacity_logits, scene.colors)
        outs = [single(g, c) for c in cams] if render == "single" else views(g, cams)
        sum(o.color.sum() + o.depth.sum() for o in outs).backward()
        grads.append((outs, means.grad))
    (a, ga), (b, gb) = grads
    for x, y in zip(a, b):
        worst["color"] = max(worst["color"], float((x.color - y.color).abs().max()))
        worst["depth"] = max(worst["depth"], float((x.depth - y.depth).abs().max()))
        worst["silhouette"] = max(worst["silhouette"], float((x.silhouette - y.silhouette).abs().max()))
    worst["means_grad"] = float((ga - gb).abs().max() / gb.abs().max())
    return worst


def selective_adam_against_twin(device: torch.device) -> dict[str, float]:
    g = torch.Generator(device="cpu").manual_seed(1)
    start = torch.randn(100_000, 3, generator=g).to(device)
    params = [start.clone().requires_grad_(True), start.clone().requires_grad_(True)]
    fused = make_map_optimizer([{"params": [params[0]], "lr": 0.01, "name": "x"}], "selective_adam", cuda=True)
    twin = SelectiveAdamReference([{"params": [params[1]], "lr": 0.01, "name": "x"}])
    for _ in range(5):
        grad = torch.randn(100_000, 3, generator=g).to(device)
        visible = (torch.rand(100_000, generator=g) > 0.4).to(device)
        for p, optimizer in zip(params, (fused, twin)):
            p.grad = grad.clone()
            optimizer.step(visible)
    return {"param_max_abs": float((params[0] - params[1]).abs().max()), "steps": 5.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="bench/results")
    args = parser.parse_args()
    device = torch.device("cuda")
    result = {
        "device": torch.cuda.get_device_name(device),
        "versions": versions(),
        "batched_views_vs_single": batched_against_single(device),
        "selective_adam_vs_twin": selective_adam_against_twin(device),
    }
    print(json.dumps(result, indent=2))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "mapping_parity.json", json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
