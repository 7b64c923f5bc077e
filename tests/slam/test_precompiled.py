"""The align iterations as AOTInductor packages: built once, loaded by later runs, equal to eager."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch
from torch.utils._pytree import tree_flatten, tree_leaves

from pipeline.slam.precompiled import Precompiled, package_key, source_digest, source_modules
from pipeline.slam.tracking.pyramid import rgbd_pyramid
from pipeline.slam.tracking.rgbd_alignment import (
    AlignParams,
    LmState,
    SourcePoints,
    TargetMaps,
    lm_iteration,
    lm_start,
    source_points,
    target_maps,
)

PARAMS = AlignParams(0.01, 0.1, 0.1, 0.1)


def _level() -> tuple[LmState, SourcePoints, TargetMaps]:
    """An iteration's inputs at a 12x16 level: a frame against itself, moved 1 cm."""
    generator = torch.Generator().manual_seed(0)
    gray = torch.rand(12, 16, generator=generator)
    depth = 1 + torch.rand(12, 16, generator=generator)
    level = rgbd_pyramid(gray, depth, torch.tensor([[10.0, 0, 8], [0, 10.0, 6], [0, 0, 1]]), 1)[0]
    pose = torch.eye(4, dtype=torch.float64)
    pose[0, 3] = 0.01
    return lm_start(pose), source_points(level), target_maps(level)


def _never_called(*args: object) -> LmState:
    raise AssertionError("the fallback ran")


@pytest.mark.slow
def test_a_package_is_built_once_and_loaded_by_a_later_run(tmp_path: Path) -> None:
    """The first instance builds the package (export and AOTInductor: tens of seconds on the CPU);
    a second, as a later process would, loads it; both equal the eager iteration within float tolerance."""
    state, source, target = _level()
    eager = lm_iteration(state, source, target, PARAMS)
    first = Precompiled(lm_iteration, "lm_iteration", tmp_path, fallback=_never_called)
    later = Precompiled(lm_iteration, "lm_iteration", tmp_path, fallback=_never_called)
    for precompiled in (first, later):
        result = precompiled(state, source, target, PARAMS)
        assert isinstance(result, LmState) and isinstance(result.fit.cost, torch.Tensor)
        for got, want in zip(tree_leaves(result), tree_leaves(eager)):
            torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)  # fused float32 arithmetic
    assert (first.built, first.loaded, later.built, later.loaded) == (1, 0, 0, 1)
    assert [p.suffix for p in tmp_path.iterdir()] == [".pt2"]  # no partial file left beside it


def test_a_package_depends_on_shapes_constants_and_source() -> None:
    state, source, target = _level()
    digest = source_digest(lm_iteration)

    def key(*args: object, name: str = "lm_iteration", code: str = digest) -> str:
        return package_key(name, code, *tree_flatten(args))

    same = key(state, source, target, PARAMS)
    assert same == key(*_level(), PARAMS)  # other values of the same shapes
    assert same != key(state, source, target, PARAMS._replace(depth_sigma=0.02))  # constants are baked in
    assert same != key(state, SourcePoints(*(field[:10] for field in source)), target, PARAMS)
    assert same != key(state, source, target, PARAMS, code="another source")
    assert same != key(state, source, target, PARAMS, name="lm_iteration_batched")
    assert {"pipeline.geometry", "pipeline.slam.tracking.rgbd_alignment"} <= set(source_modules(lm_iteration))


def test_a_function_export_refuses_runs_its_fallback(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A data-dependent branch cannot be exported: the fallback runs, said once, and no package is
    written."""

    def branching(state: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
        return state + step if float(step.sum()) > 0 else state - step

    precompiled = Precompiled(branching, "branching", tmp_path, fallback=lambda s, d: s * 0)
    with caplog.at_level(logging.WARNING, logger="gsplatam"):
        for _ in range(2):
            assert torch.equal(precompiled(torch.ones(3), torch.ones(3)), torch.zeros(3))
    assert precompiled.failed and caplog.text.count("could not be compiled ahead of time") == 1
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "loader, said",
    [
        (
            "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)",
            "(signal SIGSEGV; built with CXX=/opt/gcc/bin/g++)",
        ),
        ("import time; time.sleep(60)", "did not load in a child process within 1 s"),
    ],
    ids=["crashes", "hangs"],
)
def test_a_package_that_crashes_its_loader_is_not_kept_and_the_fallback_runs(
    loader: str, said: str, tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A package whose library does not fit the process's C++ runtime kills the process that loads
    it (SIGSEGV on the H200 at da7c30a): it is loaded in a child first, and a crash or a hang there
    means the fallback, said once with why, and no package left to crash a later run."""
    import torch._inductor

    from pipeline.slam import precompiled as module

    monkeypatch.setattr(
        torch._inductor,
        "aoti_compile_and_package",
        lambda program, package_path: Path(package_path).write_bytes(b"built"),
    )
    monkeypatch.setattr(module, "TRIAL_LOAD", loader)
    monkeypatch.setattr(module, "TRIAL_TIMEOUT_S", 1)
    monkeypatch.setenv("CXX", "/opt/gcc/bin/g++")

    def double(state: torch.Tensor) -> torch.Tensor:
        return state * 2

    precompiled = Precompiled(double, "double", tmp_path, fallback=lambda s: s * 3)
    with caplog.at_level(logging.WARNING, logger="gsplatam"):
        for _ in range(2):
            assert torch.equal(precompiled(torch.ones(3)), torch.full((3,), 3.0))
    assert caplog.text.count("could not be compiled ahead of time") == 1
    assert said in caplog.text
    assert not any(tmp_path.iterdir())
