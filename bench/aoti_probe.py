"""Where loading an AOTInductor package crashes on this GPU (bench/NOTES.md, Change 36).

At da7c30a every `run.precompile` cell on the H200 died with SIGSEGV inside
`aoti_load_package`, right after building its first package. Each case below runs in its own
process (a crash ends that case only) and prints one line; the table goes to OUT/aoti_probe.md:
- `toy`: a float32 elementwise function, built and loaded (is AOTInductor on CUDA usable at all?);
- `build`: the align iteration (`lm_iteration`) at a 12x16 level, built (in a child, as a run builds it);
- `load`, `load-index-0`, `load-side-stream`: that package loaded and run in a fresh process,
  with the device index -1 or 0, or under a side stream as `cuda_graphs.record`'s warm-up calls.
Usage: python3 bench/aoti_probe.py --out OUT
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from torch.utils._pytree import tree_leaves

CASES = ("toy", "build", "load", "load-index-0", "load-side-stream")


def _level_on_cuda() -> tuple[object, ...]:
    from pipeline.slam.tracking.pyramid import rgbd_pyramid
    from pipeline.slam.tracking.rgbd_alignment import AlignParams, lm_start, source_points, target_maps

    generator = torch.Generator().manual_seed(0)
    gray = torch.rand(12, 16, generator=generator)
    depth = 1 + torch.rand(12, 16, generator=generator)
    intrinsics = torch.tensor([[10.0, 0, 8], [0, 10.0, 6], [0, 0, 1]])
    level = rgbd_pyramid(gray.cuda(), depth.cuda(), intrinsics.cuda(), 1)[0]
    pose = torch.eye(4, dtype=torch.float64, device="cuda")
    pose[0, 3] = 0.01
    return lm_start(pose), source_points(level), target_maps(level), AlignParams(0.01, 0.1, 0.1, 0.1)


def _toy(folder: Path) -> str:
    from torch._inductor import aoti_compile_and_package, aoti_load_package

    class Toy(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return (x * 2).sin() + 1

    x = torch.rand(64, device="cuda")
    path = aoti_compile_and_package(torch.export.export(Toy(), (x,)), package_path=str(folder / "toy.pt2"))
    got = aoti_load_package(path)(x)
    return f"max error {float((got - Toy()(x)).abs().max()):.1e}"


def _case(case: str, folder: Path) -> str:
    from pipeline.slam.precompiled import Precompiled
    from pipeline.slam.tracking.rgbd_alignment import lm_iteration

    if case == "toy":
        return _toy(folder)
    args = _level_on_cuda()
    precompiled = Precompiled(lm_iteration, "lm_iteration", folder, fallback=lm_iteration)
    if case == "build":  # in a child process of its own, as a run builds it
        from pipeline.package_builds import BUILDS

        precompiled(*args)
        BUILDS.wait()
        return f"built {precompiled.built} failed {precompiled.failed}"
    if case == "load-index-0":
        torch.cuda.set_device(0)
    side = torch.cuda.Stream()
    with torch.cuda.stream(side) if case == "load-side-stream" else torch.cuda.stream(torch.cuda.current_stream()):
        result = precompiled(*args)
    torch.cuda.synchronize()
    want = lm_iteration(*args)  # type: ignore[arg-type]
    # each output's largest difference from eager, as a fraction of that output's largest value
    pairs = zip(tree_leaves(result), tree_leaves(want))
    error = max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-12)) for a, b in pairs)
    return (
        f"built {precompiled.built} loaded {precompiled.loaded} failed {precompiled.failed} error {error:.1e} of scale"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--case", choices=CASES, help=argparse.SUPPRESS)
    parser.add_argument("--folder", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.case:
        print(_case(args.case, args.folder), flush=True)
        return
    args.out.mkdir(parents=True, exist_ok=True)
    folder = args.folder or Path(tempfile.mkdtemp())
    folder.mkdir(parents=True, exist_ok=True)
    rows = ["| case | exit | seconds | result |", "|---|---|---|---|"]
    for case in CASES:
        started = time.perf_counter()
        done = subprocess.run(
            [sys.executable, __file__, "--out", str(args.out), "--case", case, "--folder", str(folder)],
            capture_output=True,
            text=True,
            check=False,
        )
        said = (done.stdout.strip().splitlines() or done.stderr.strip().splitlines()[-1:] or [""])[-1]
        rows.append(f"| {case} | {done.returncode} | {time.perf_counter() - started:.1f} | {said} |")
        print(rows[-1], flush=True)
        (args.out / f"aoti_probe_{case}.log").write_text(done.stdout + done.stderr)
    (args.out / "aoti_probe.md").write_text("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
