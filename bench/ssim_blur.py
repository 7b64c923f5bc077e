"""The mapping loss with SSIM's blur as shifted sums (now) against depthwise convolutions (before).

Both forms are compiled as the SLAM loop compiles them and run forward + backward on one
1200x680 image pair: GPU time per call from CUDA events (median), host time per call from the
clock around the launches (median, with the GPU kept busy so the host never waits).

    python bench/ssim_blur.py --out bench/results
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from pipeline.app.report import versions
from pipeline.io.files.atomic import atomic_write_text
from pipeline.slam import losses
from pipeline.slam.kernels import mapping_loss


def conv_ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The previous form (commit 739fbba): two depthwise convolutions over the five statistics."""
    channels = a.shape[-1]
    x, y = a.permute(2, 0, 1), b.permute(2, 0, 1)
    stack = torch.cat([x, y, x * x, y * y, x * y])[None]
    g = torch.tensor(losses.SSIM_TAPS, device=a.device, dtype=a.dtype)
    groups, pad = 5 * channels, losses.SSIM_WINDOW // 2
    blurred = F.conv2d(F.pad(stack, (pad, pad, 0, 0)), g.view(1, 1, 1, -1).expand(groups, 1, 1, -1), groups=groups)
    blurred = F.conv2d(F.pad(blurred, (0, 0, pad, pad)), g.view(1, 1, -1, 1).expand(groups, 1, -1, 1), groups=groups)
    mu_a, mu_b, a2, b2, ab = blurred[0].split(channels)
    sigma_a, sigma_b, sigma_ab = a2 - mu_a**2, b2 - mu_b**2, ab - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    value = ((2 * mu_a * mu_b + c1) * (2 * sigma_ab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (sigma_a + sigma_b + c2))
    return value.mean(0)


def time_loss(loss_fn, inputs: tuple[torch.Tensor, ...], repeats: int) -> dict[str, float]:
    render_color, render_depth, color, depth = inputs
    gpu_ms, host_ms = [], []
    for i in range(repeats + 5):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        torch.cuda._sleep(2_000_000)  # keep the GPU busy so the host-side clock sees launches only
        t0 = time.perf_counter()
        start.record()
        loss = loss_fn(render_color, render_depth, color, depth, 0.2, 1.0, 0.5)
        loss.backward()
        end.record()
        t1 = time.perf_counter()
        torch.cuda.synchronize()
        if i >= 5:
            gpu_ms.append(start.elapsed_time(end))
            host_ms.append(1000 * (t1 - t0))
    return {"gpu_ms": statistics.median(gpu_ms), "host_ms": statistics.median(host_ms)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=50)
    args = parser.parse_args()
    gen = torch.Generator(device="cuda").manual_seed(0)
    shape = (680, 1200)
    color = torch.rand(*shape, 3, device="cuda", generator=gen)
    depth = 1 + torch.rand(shape, device="cuda", generator=gen)
    render_color = (color + 0.05 * torch.randn(*shape, 3, device="cuda", generator=gen)).requires_grad_(True)
    render_depth = (depth + 0.01 * torch.randn(shape, device="cuda", generator=gen)).requires_grad_(True)
    inputs = (render_color, render_depth, color, depth)

    results, current = {}, losses.ssim_map
    try:
        for name, ssim_map in (("shifted_sums", current), ("depthwise_conv", conv_ssim_map)):
            losses.ssim_map = ssim_map  # mapping_loss reaches it through `losses.ssim` when traced
            compiled = torch.compile(mapping_loss, dynamic=False)
            results[name] = time_loss(compiled, inputs, args.repeats)
            torch._dynamo.reset()
    finally:
        losses.ssim_map = current
    report = {"device": torch.cuda.get_device_name(), "versions": versions(), "size": shape, "results": results}
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "ssim_blur.json", json.dumps(report, indent=1) + "\n")
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
