"""gsplat (CUDA) against the pure-PyTorch reference: images, gradients, finite differences, timings.

Run on a CUDA machine: `python bench/parity.py --out DIR`. Writes parity.json and parity.md.
Every scene is drawn fresh (seeded per case) inside the camera's frustum at a random pose.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.app.report import versions  # noqa: E402
from pipeline.geometry import invert_pose  # noqa: E402
from pipeline.io.files.atomic import atomic_write_text
from pipeline.render.reference import SMOOTH, render_reference  # noqa: E402
from pipeline.render.types import Camera, Gaussians  # noqa: E402
from tests.gpu.gpu_scenes import TOLERANCE, leaves, loss_of, random_pose, random_scene, rel  # noqa: E402

SMOOTH_FD_GAUSSIANS = 2_000


def twist(w2c: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """Left-perturb w2c by the small rigid motion exp(xi), xi = (rotation vector, translation)."""
    omega, t = xi[:3], xi[3:]
    angle = torch.linalg.norm(omega)
    k = torch.zeros(3, 3, dtype=w2c.dtype, device=w2c.device)
    k[0, 1], k[0, 2], k[1, 0], k[1, 2], k[2, 0], k[2, 1] = -omega[2], omega[1], omega[2], -omega[0], -omega[1], omega[0]
    rot = torch.eye(3, dtype=w2c.dtype, device=w2c.device) + k
    if angle > 0:
        rot = (
            torch.eye(3, dtype=w2c.dtype, device=w2c.device)
            + math.sin(angle) / angle * k
            + (1 - math.cos(angle)) / angle**2 * (k @ k)
        )
    delta = torch.eye(4, dtype=w2c.dtype, device=w2c.device)
    delta[:3, :3], delta[:3, 3] = rot, t
    return delta @ w2c


def compare_case(n: int, isotropic: bool, seed: int, width: int, height: int, device: torch.device) -> dict:
    from pipeline.render.gsplat_backend import render_gsplat_3d

    gen = torch.Generator().manual_seed(seed)
    k = torch.tensor([[0.8 * width, 0, width / 2], [0, 0.8 * width, height / 2], [0, 0, 1]], device=device)
    c2w = random_pose(gen, device)
    w2c = invert_pose(c2w)
    scene = random_scene(n, isotropic, c2w, k, width, height, gen)
    weights = tuple(
        torch.rand(*shape, generator=gen).to(device) for shape in ((height, width, 3), (height, width), (height, width))
    )

    results = {}
    grads = {}
    for name, fn in (("gsplat", render_gsplat_3d), ("reference", render_reference)):
        g = leaves(scene)
        view = w2c.clone().requires_grad_(True)
        out = fn(g, Camera(view, k, width, height))
        loss_of(out, weights).backward()
        results[name] = out
        grads[name] = {
            "means": g.means.grad, "colors": g.colors.grad, "opacities": g.opacity_logits.grad,
            "scales": g.log_scales.grad, "quats": g.quats.grad, "viewmat": view.grad[:3],
        }  # fmt: skip
    gs, ref = results["gsplat"], results["reference"]
    case = {
        "gaussians": n,
        "isotropic": isotropic,
        "seed": seed,
        "size": f"{width}x{height}",
        "visible": int(ref.visible.sum()),
        "radii_equal_fraction": float((gs.radii == ref.radii).float().mean()),
        "color": rel(gs.color, ref.color),
        "depth": rel(gs.depth, ref.depth),
        "silhouette": rel(gs.silhouette, ref.silhouette),
    }
    for key in grads["gsplat"]:
        case[f"grad_{key}"] = rel(grads["gsplat"][key], grads["reference"][key])
    if isotropic:
        # A sphere's image does not depend on its rotation: both backends return rounding noise
        # for these gradients, so their relative difference means nothing and is not judged.
        case["grad_quats_norm"] = float(torch.linalg.norm(grads["reference"]["quats"]))
        case["grad_quats"] = 0.0

    case["viewmat_fd_smooth"] = viewmat_fd_error(scene, w2c, k, width, height, weights, smooth=True)
    case["viewmat_fd_gsplat_raw"] = viewmat_fd_error(scene, w2c, k, width, height, weights, smooth=False)
    return case


def viewmat_fd_error(scene, w2c, k, width, height, weights, smooth: bool) -> float:
    """Relative L2 error of the loss's derivative along the six rigid-motion generators
    (three rotations, three translations) of the camera: analytic (through the view-matrix
    gradient) against central finite differences.

    smooth=True: the reference renderer without gsplat's cutoffs, in float64 (a continuous
    function, so the check is exact up to rounding). smooth=False: gsplat itself in float32;
    reported for information only, since its alpha and transmittance cutoffs make the image
    jump, which finite differences see and gradients (of either backend) do not.
    """
    from pipeline.render.gsplat_backend import render_gsplat_3d

    if smooth:
        # A subset keeps the 12-sigma footprints affordable; opacities stay under 0.98 so no
        # pixel reaches the 0.999 alpha clamp, a kink that finite differences would straddle.
        dtype, eps = torch.float64, 1e-5
        head = slice(0, SMOOTH_FD_GAUSSIANS)
        scene = Gaussians(
            scene.means[head].double(), scene.quats[head].double(), scene.log_scales[head].double(),
            scene.opacity_logits[head].clamp(max=4.0).double(), scene.colors[head].double(),
        )  # fmt: skip

        def render(g, cam):
            return render_reference(g, cam, cutoffs=SMOOTH)
    else:
        dtype, eps = torch.float32, 1e-3
        render = render_gsplat_3d
    w2c, k = w2c.to(dtype), k.to(dtype)
    weights = tuple(w.to(dtype) for w in weights)
    view = w2c.clone().requires_grad_(True)
    loss_of(render(scene, Camera(view, k, width, height)), weights).backward()
    numeric, analytic = [], []
    for axis in range(6):
        xi = torch.zeros(6, dtype=dtype, device=w2c.device)
        xi[axis] = 1.0
        step = eps
        # 3DGS composites in the order of the Gaussians' centre depths, so the image jumps where
        # two centres swap depth. For the smooth function, shrink the step until no pair swaps.
        while smooth and step > 1e-9 and not same_depth_order(scene, [twist(w2c, s * step * xi) for s in (1, -1)]):
            step /= 10
        with torch.no_grad():
            plus = loss_of(render(scene, Camera(twist(w2c, step * xi), k, width, height)), weights)
            minus = loss_of(render(scene, Camera(twist(w2c, -step * xi), k, width, height)), weights)
        numeric.append(float((plus - minus) / (2 * step)))
        direction = (twist(w2c.double(), 1e-7 * xi.double()) - w2c.double()) / 1e-7  # d w2c / dt along xi
        analytic.append(float((view.grad.double()[:3] * direction[:3]).sum()))
    return rel(torch.tensor(analytic), torch.tensor(numeric))


def same_depth_order(scene: Gaussians, views: list[torch.Tensor]) -> bool:
    orders = [torch.argsort((scene.means @ v[:3, :3].T + v[:3, 3])[:, 2]) for v in views]
    return all(torch.equal(orders[0], o) for o in orders[1:])


def time_ms(fn, repeats: int = 15) -> float:
    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn()
        end.record()
        torch.cuda.synchronize()
        times.append(start.elapsed_time(end))
    return statistics.median(times)


def timings(device: torch.device) -> list[dict]:
    from pipeline.render.gsplat_backend import render_gsplat_2d, render_gsplat_3d

    width, height = 1200, 680
    rows = []
    for n in (100_000, 1_000_000, 3_000_000):
        gen = torch.Generator().manual_seed(n)
        k = torch.tensor([[600.0, 0, 600], [0, 600, 340], [0, 0, 1]], device=device)
        c2w = torch.eye(4, device=device)
        scene = random_scene(n, True, c2w, k, width, height, gen)
        for kind, fn in (("3d", render_gsplat_3d), ("2d", render_gsplat_2d)):
            for packed in (False, True):
                if kind == "2d" and packed:
                    continue
                g = leaves(scene)
                view = torch.eye(4, device=device).requires_grad_(True)

                def step(fn=fn, g=g, view=view, k=k, packed=packed) -> None:
                    out = fn(g, Camera(view, k, width, height), packed=packed)
                    (out.color.sum() + out.depth.sum() + out.silhouette.sum()).backward()

                rows.append({"gaussians": n, "kind": kind, "packed": packed, "fwd_bwd_ms": time_ms(step)})
                print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--skip-timings", action="store_true")
    args = parser.parse_args()
    device = torch.device("cuda")
    args.out.mkdir(parents=True, exist_ok=True)
    cases = []
    seed = 0
    for n, width, height in ((200, 160, 120), (2_000, 320, 240), (20_000, 320, 240), (60_000, 640, 480)):
        for isotropic in (True, False):
            for _ in range(2):
                seed += 1
                cases.append(compare_case(n, isotropic, seed, width, height, device))
                torch.cuda.empty_cache()
                print({k: (f"{v:.2e}" if isinstance(v, float) else v) for k, v in cases[-1].items()}, flush=True)
    keys = ["color", "depth", "silhouette"] + [
        f"grad_{k}" for k in ("means", "colors", "opacities", "scales", "quats", "viewmat")
    ]
    worst = {key: max(c[key] for c in cases) for key in keys + ["viewmat_fd_smooth", "viewmat_fd_gsplat_raw"]}
    passed = all(worst[k] <= TOLERANCE["image"] for k in keys[:3])
    passed &= all(worst[k] <= TOLERANCE["grad"] for k in keys[3:])
    passed &= worst["viewmat_fd_smooth"] <= TOLERANCE["fd"]
    report = {
        "device": torch.cuda.get_device_name(device),
        "driver": torch.cuda.get_device_properties(device).name,
        "versions": versions(),
        "tolerance": TOLERANCE,
        "worst": worst,
        "passed": bool(passed),
        "cases": cases,
        "timings": [] if args.skip_timings else timings(device),
    }
    atomic_write_text(args.out / "parity.json", json.dumps(report, indent=2) + "\n")
    print(json.dumps({"worst": worst, "passed": passed}, indent=2))


if __name__ == "__main__":
    main()
