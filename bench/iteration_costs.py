"""Host time of each call in a tracking and a mapping iteration, on a map SLAM built.

The SLAM loop is host-bound: the GPU idles while Python and the libraries queue the next
kernels. This splits one iteration into its calls and times each on the host clock (no
profiler, which inflates host time ~2x), plus gsplat's rasterisation taken apart into its four
steps. The device is synchronised before each iteration, so the one call that waits for the
GPU (gsplat's intersection count) waits only for its own kernels. GPU time of the whole
iteration comes from CUDA events.

    python bench/iteration_costs.py --out bench/results [--frames 60] [--repeats 30]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch

from pipeline.app.report import versions
from pipeline.app.run import run_slam
from pipeline.config import load_config, with_value
from pipeline.devices import resolve_device
from pipeline.geometry import invert_pose, pose_matrix, rotmat_to_quat
from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.sources.datasets.synthetic import default_intrinsics
from pipeline.render import Camera, Gaussians, make_renderer
from pipeline.slam.gaussian_map import PARAMETER_NAMES, as_leaves, copied
from pipeline.slam.kernels import EAGER, make_kernels
from pipeline.slam.keyframes import Keyframe

WARMUP = 5  # iterations run before timing: compilation, allocator and cache warm-up


class DeviceSpan:
    """GPU milliseconds between `start()` and `stop()` (CUDA events; host time on the CPU)."""

    def __init__(self, cuda: bool) -> None:
        self.cuda, self.samples = cuda, []

    def start(self) -> None:
        self._sync()
        if self.cuda:
            self._start, self._end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            self._start.record()
        else:
            self._t0 = time.perf_counter()

    def stop(self) -> None:
        if self.cuda:
            self._end.record()
        self._sync()
        self.samples.append(
            self._start.elapsed_time(self._end) if self.cuda else 1000 * (time.perf_counter() - self._t0)
        )

    def _sync(self) -> None:
        if self.cuda:
            torch.cuda.synchronize()


class HostClock:
    """Host milliseconds per named block, medians over repeats."""

    def __init__(self) -> None:
        self.samples: dict[str, list[float]] = defaultdict(list)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        yield
        self.samples[name].append(1000 * (time.perf_counter() - start))

    def medians(self) -> dict[str, float]:
        return {name: statistics.median(values) for name, values in self.samples.items()}


def timed_iterations(
    forward: Callable[[HostClock], torch.Tensor], optimizer: torch.optim.Optimizer, repeats: int, cuda: bool
) -> dict[str, Any]:
    """`WARMUP` untimed, then `repeats` timed optimiser iterations: `forward(clock)` -> loss (it times
    its own calls), then backward and the Adam step. -> median host ms per call, median GPU span."""
    clock, span = HostClock(), DeviceSpan(cuda)
    for i in range(WARMUP + repeats):
        if i == WARMUP:
            clock, span = HostClock(), DeviceSpan(cuda)
        span.start()
        value = forward(clock)
        with clock("zero_grad + backward"):
            optimizer.zero_grad(set_to_none=True)
            value.backward()
        with clock("Adam step (fused)"):
            optimizer.step()
        span.stop()
    return {"host_ms": clock.medians(), "gpu_span_ms": statistics.median(span.samples)}


def built_map(frames: int) -> tuple[Gaussians, Keyframe, Any]:
    config = load_config("tiny", overrides=[f"synthetic.frames={frames}"])
    config = with_value(config, "run.output", "/tmp/iteration_costs")
    result = run_slam(config, resolve_device(config.run.device), progress=False)
    saved, _ = result.folder.read_checkpoint()
    device = "cuda" if torch.cuda.is_available() else "cpu"  # the CPU only to try the script out
    return copied(saved.gaussians, device), saved.keyframes[-1], config


def gsplat_steps(gaussians: Gaussians, camera: Camera, clock: HostClock) -> torch.Tensor:
    """gsplat.rasterization's work for one camera, colour + expected depth, step by step."""
    from gsplat.cuda._wrapper import fully_fused_projection, isect_offset_encode, isect_tiles, rasterize_to_pixels

    width, height, tile = camera.width, camera.height, 16
    tiles_w, tiles_h = math.ceil(width / tile), math.ceil(height / tile)
    with clock("activations"):
        scales = gaussians.scales().contiguous()
        opacities = torch.sigmoid(gaussians.opacity_logits)
    with clock("projection"):
        radii, means2d, depths, conics, _ = fully_fused_projection(
            gaussians.means, None, gaussians.quats, scales, camera.w2c[None], camera.intrinsics[None],
            width, height, eps2d=0.3, near_plane=camera.near, far_plane=camera.far, opacities=opacities,
        )  # fmt: skip
    with clock("intersect (waits for its count)"):
        _, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, tile, tiles_w, tiles_h)
    with clock("offsets"):
        offsets = isect_offset_encode(isect_ids, 1, tiles_w, tiles_h).reshape(1, tiles_h, tiles_w)
    with clock("colour+depth features"):
        features = torch.cat([gaussians.colors[None], depths[..., None]], -1)
    with clock("rasterise"):
        colors, alphas = rasterize_to_pixels(
            means2d, conics, features, opacities[None], width, height, tile, offsets, flatten_ids
        )
    return colors[0, ..., 0].sum() + alphas.sum()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    gaussians, keyframe, config = built_map(args.frames)
    device = gaussians.means.device
    cuda = device.type == "cuda"
    renderer = make_renderer(config.render, config.gaussians, device)
    kernels = make_kernels(compiled=cuda)
    color = keyframe.color_u8.to(device).float() / 255.0
    depth = keyframe.depth.to(device)
    intrinsics = torch.tensor(default_intrinsics(*depth.shape[::-1]), dtype=torch.float32, device=device)
    w2c = invert_pose(keyframe.c2w.to(device))
    height, width = depth.shape
    near, far, loss = config.render.near, config.render.far, config.loss
    threshold = config.tracking.silhouette_threshold
    results: dict[str, Any] = {}

    # Tracking: the map frozen, gradients to the pose only; the loss compiled (as SLAM runs it) and eager.
    for label, tracking_loss in (("tracking", kernels.tracking_loss), ("tracking, eager loss", EAGER.tracking_loss)):
        quat = rotmat_to_quat(w2c[:3, :3]).clone().requires_grad_(True)
        trans = w2c[:3, 3].clone().requires_grad_(True)

        def tracking_forward(clock: HostClock, quat=quat, trans=trans, tracking_loss=tracking_loss) -> torch.Tensor:
            with clock("pose matrix"):
                camera = Camera(pose_matrix(quat, trans), intrinsics, width, height, near, far)
            with clock("render (gsplat.rasterization)"):
                out = renderer(gaussians, camera)
            with clock("tracking loss"):
                return tracking_loss(
                    out.color, out.depth, out.silhouette, color, depth, threshold, loss.depth_weight, loss.color_weight
                )[0]

        optimizer = torch.optim.Adam([quat, trans], lr=1e-3, eps=1e-15, fused=cuda)
        results[label] = timed_iterations(tracking_forward, optimizer, args.repeats, cuda)

    # Mapping: gradients to every Gaussian parameter.
    params = as_leaves(gaussians)
    camera = Camera(w2c, intrinsics, width, height, near, far)

    def mapping_forward(clock: HostClock) -> torch.Tensor:
        with clock("render (gsplat.rasterization)"):
            out = renderer(params, camera)
        with clock("mapping loss (compiled)"):
            return kernels.mapping_loss(
                out.color, out.depth, color, depth, config.mapping.ssim_weight, loss.depth_weight, loss.color_weight
            )

    optimizer = torch.optim.Adam([getattr(params, n) for n in PARAMETER_NAMES], lr=1e-4, eps=1e-15, fused=cuda)
    results["mapping"] = timed_iterations(mapping_forward, optimizer, args.repeats, cuda)

    # gsplat's rasterisation in its steps (mapping case: gradients to the Gaussians).
    clock = HostClock()
    for i in range(WARMUP + args.repeats if cuda else 0):
        if i == WARMUP:
            clock = HostClock()
        torch.cuda.synchronize()
        with clock("all steps"):
            total = gsplat_steps(params, camera, clock)
        with clock("backward"):
            total.backward()
    results["gsplat_steps"] = {"host_ms": clock.medians()}

    report = {
        "device": torch.cuda.get_device_name() if cuda else "cpu",
        "versions": versions(),
        "map_gaussians": len(gaussians),
        "frames_before": args.frames,
        "repeats": args.repeats,
        **results,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "iteration_costs.json", json.dumps(report, indent=1) + "\n")
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
