"""The align iterations as AOTInductor packages: built once, loaded by later runs, equal to eager."""

from __future__ import annotations

import logging
import os
import pickle
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch
from torch.utils._pytree import tree_flatten, tree_leaves

from pipeline import package_builds
from pipeline.package_builds import BUILDS, BUILT_ELSEWHERE, BuildJob, ClaimedElsewhere, claim
from pipeline.slam.kernels import mapping_loss
from pipeline.slam.precompiled import Precompiled, describe, package_key, source_digest, source_modules
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


def _never_called(*args: object) -> Any:
    raise AssertionError("the fallback ran")


class Counted:
    """A fallback that counts its calls and returns the eager iteration's result."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, *args: Any) -> LmState:
        self.calls += 1
        return lm_iteration(*args)


def branching(state: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """A data-dependent branch: export refuses it."""
    return state + step if float(step.sum()) > 0 else state - step


def double(state: torch.Tensor) -> torch.Tensor:
    return state * 2


@pytest.mark.slow
def test_a_package_is_built_beside_the_run_and_loaded_by_a_later_one(tmp_path: Path) -> None:
    """The first instance runs its fallback while a child process builds the package (export and
    AOTInductor: tens of seconds on the CPU); a second, as a later run would, loads it and equals
    the eager iteration within float tolerance."""
    state, source, target = _level()
    eager = lm_iteration(state, source, target, PARAMS)
    fallback = Counted()
    first = Precompiled(lm_iteration, "lm_iteration", tmp_path, fallback=fallback)
    for _ in range(2):
        first(state, source, target, PARAMS)
    assert fallback.calls == 2 and BUILDS.pending() == 1  # one build for the one signature
    assert BUILDS.wait()
    later = Precompiled(lm_iteration, "lm_iteration", tmp_path, fallback=fallback)
    result = later(state, source, target, PARAMS)
    assert fallback.calls == 2, "the package ran"
    assert isinstance(result, LmState) and isinstance(result.fit.cost, torch.Tensor)
    for got, want in zip(tree_leaves(result), tree_leaves(eager)):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)  # fused float32 arithmetic
    assert (first.built, first.loaded, later.built, later.loaded) == (1, 0, 0, 1)
    assert [p.suffix for p in tmp_path.iterdir()] == [".pt2"]  # no partial file left beside it


def test_a_package_depends_on_shapes_constants_source_and_compiler(monkeypatch: pytest.MonkeyPatch) -> None:
    state, source, target = _level()
    digest = source_digest(lm_iteration)

    def key(*args: object, name: str = "lm_iteration", code: str = digest) -> str:
        leaves, spec = tree_flatten(args)
        return package_key(name, code, (spec, *map(describe, leaves)))

    same = key(state, source, target, PARAMS)
    assert same == key(*_level(), PARAMS)  # other values of the same shapes
    assert same != key(state, source, target, PARAMS._replace(depth_sigma=0.02))  # constants are baked in
    assert same != key(state, SourcePoints(*(field[:10] for field in source)), target, PARAMS)
    assert same != key(state, source, target, PARAMS, code="another source")
    assert same != key(state, source, target, PARAMS, name="lm_iterations")
    monkeypatch.setenv("CXX", os.environ.get("CXX", "g++") + "-13")
    assert same != key(state, source, target, PARAMS)
    assert {"pipeline.geometry", "pipeline.slam.tracking.rgbd_alignment"} <= set(source_modules(lm_iteration))


def test_a_function_export_refuses_runs_its_fallback_and_is_not_built_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A data-dependent branch cannot be exported: the fallback runs, the failure is said once
    with export's reason and noted beside where the package would be, and a later run reads the
    note rather than build it again."""
    ones = torch.ones(3)
    with caplog.at_level(logging.WARNING, logger="gsplatam"):
        for _ in range(2):
            precompiled = Precompiled(branching, "branching", tmp_path, fallback=lambda s, d: s * 0)
            assert torch.equal(precompiled(ones, ones), torch.zeros(3))
            assert BUILDS.wait()
            assert precompiled.failed
    assert caplog.text.count("could not be compiled ahead of time") == 2  # once per run
    assert "data-dependent" in caplog.text or "Could not guard" in caplog.text, caplog.text
    assert [p.suffix for p in tmp_path.iterdir()] == [".failed"]
    assert precompiled.built == 0


@pytest.mark.parametrize(
    "builder, said, noted",
    [
        (
            "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)",
            "its build died of SIGSEGV; built with CXX=/opt/gcc/bin/g++",
            True,
        ),
        ("import time; time.sleep(60)", "its build did not finish within 1 s", True),
        ("import os, signal; os.kill(os.getpid(), signal.SIGTERM)", "its build died of SIGTERM", False),
    ],
    ids=["crashes", "hangs", "is-stopped"],
)
def test_a_build_that_crashes_or_hangs_leaves_no_package_and_the_fallback_runs(
    builder: str,
    said: str,
    noted: bool,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A package whose library does not fit the process's C++ runtime kills the process that loads
    it (SIGSEGV on the H200 at da7c30a): the build's child loads it first, so a crash or a hang
    there means the fallback, said once with why, no package, and a note that spares later runs
    the same build; a build stopped by a signal is not noted (a later run builds it)."""
    from pipeline import package_builds

    monkeypatch.setattr(package_builds, "BUILDER", builder)
    monkeypatch.setattr(package_builds, "BUILD_TIMEOUT_S", 1)
    monkeypatch.setenv("CXX", "/opt/gcc/bin/g++")
    precompiled = Precompiled(double, "double", tmp_path, fallback=lambda s: s * 3)
    with caplog.at_level(logging.WARNING, logger="gsplatam"):
        assert torch.equal(precompiled(torch.ones(3)), torch.full((3,), 3.0))
        assert BUILDS.wait()
        assert torch.equal(precompiled(torch.ones(3)), torch.full((3,), 3.0))
    assert caplog.text.count("could not be compiled ahead of time") == 1
    assert said in caplog.text
    assert [p.suffix for p in tmp_path.iterdir()] == ([".failed"] if noted else [])


def test_builds_run_at_most_max_builds_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each build holds a core: the others queue until one ends, and every one is run."""
    from pipeline import package_builds

    marks = tmp_path / "marks"
    marks.mkdir()
    builder = (  # marks itself running, counts those running, and says the count as its failure
        f"import os, time, pathlib; m = pathlib.Path({str(marks)!r}) / str(os.getpid()); m.touch(); "
        "time.sleep(0.5); n = len(list(m.parent.iterdir())); m.unlink(); raise SystemExit(f'running {n}')"
    )
    monkeypatch.setattr(package_builds, "BUILDER", builder)
    monkeypatch.setattr(package_builds, "MAX_BUILDS", 2)
    builds = package_builds.PackageBuilds()
    ended: list[str] = []
    for n in range(5):
        job = package_builds.BuildJob(double, "double", tmp_path / f"double-{n}.pt2", (), tree_flatten(())[1])
        builds.start(job, ended.append)
    assert builds.wait()
    assert len(ended) == 5 and all(why in ("running 1", "running 2") for why in ended), ended


def _job(path: Path, fn: Any = double, *args: Any) -> BuildJob:
    leaves, spec = tree_flatten(args)
    return BuildJob(fn, fn.__name__, path, tuple(package_builds.TensorMeta.of(leaf) for leaf in leaves), spec)


def test_a_package_another_process_is_building_is_left_to_it(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The loop search of the mapping process wants the tracking process's packages at once: a
    child that finds a living process's claim leaves the build to it, which is no failure (nothing noted, nothing
    said), and the claim stays its holder's."""
    job = _job(tmp_path / "double.pt2", double, torch.ones(3))
    job.claim.write_text(f"{os.getpid()}\n")  # (this process: alive)
    builds = package_builds.PackageBuilds()
    ended: list[str] = []
    builds.start(job, ended.append)
    assert builds.wait()
    assert ended == [BUILT_ELSEWHERE]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["double.building"]
    assert job.claim.read_text() == f"{os.getpid()}\n"
    precompiled = Precompiled(double, "double", tmp_path, fallback=lambda s: s * 3)
    with caplog.at_level(logging.DEBUG, logger="gsplatam"):
        precompiled._built(BUILT_ELSEWHERE)
    assert not precompiled.failed and precompiled.built == 0
    assert "could not be compiled ahead of time" not in caplog.text


@pytest.mark.parametrize("set_by_user", [None, "5"])
def test_each_build_compiles_with_its_share_of_the_cores(
    set_by_user: str | None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(
        package_builds, "BUILDER", "import os; raise SystemExit(os.environ['TORCHINDUCTOR_COMPILE_THREADS'])"
    )
    if set_by_user is None:
        monkeypatch.delenv("TORCHINDUCTOR_COMPILE_THREADS", raising=False)
    else:
        monkeypatch.setenv("TORCHINDUCTOR_COMPILE_THREADS", set_by_user)
    builds = package_builds.PackageBuilds()
    ended: list[str] = []
    builds.start(_job(tmp_path / "double.pt2"), ended.append)
    assert builds.wait()
    assert ended == [set_by_user or package_builds.BUILD_COMPILE_THREADS]


def _ended_process_id() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


@pytest.mark.parametrize("stale", ["ended", "too-old", "too-old-unwritten"])
def test_a_stale_claim_is_taken_over_and_a_live_one_is_not(stale: str, tmp_path: Path) -> None:
    job = _job(tmp_path / "double.pt2")
    job.claim.write_text(
        "" if stale == "too-old-unwritten" else f"{_ended_process_id() if stale == 'ended' else os.getpid()}\n"
    )
    if stale.startswith("too-old"):
        old = job.claim.stat().st_mtime - package_builds.BUILD_TIMEOUT_S - 1
        os.utime(job.claim, (old, old))
    claim(job)
    assert job.claim.read_text() == f"{os.getpid()}\n"
    for live in (f"{os.getpid()}\n", ""):  # a living holder, or one writing its claim now
        job.claim.write_text(live)
        with pytest.raises(ClaimedElsewhere):
            claim(job)


def test_a_build_notes_its_failure_itself_for_runs_after_its_own_has_ended(tmp_path: Path) -> None:
    """The mapping process may end before its builds do: the child, with no parent left to
    listen, writes the note that spares later runs the same failure, and releases its claim."""
    job = _job(tmp_path / "branching.pt2", branching, torch.ones(3), torch.ones(3))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    child = subprocess.run(
        [sys.executable, "-c", package_builds.BUILDER], input=pickle.dumps(job), capture_output=True, env=env
    )
    assert child.returncode == 1
    assert job.failed_note.read_text().strip() == child.stderr.decode().strip().splitlines()[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["branching.failed"]


@pytest.mark.parametrize("stopped", [False, True], ids=["waits", "is-interrupted"])
def test_the_end_of_a_run_waits_for_its_builds_unless_interrupted(
    stopped: bool, tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline import package_builds

    monkeypatch.setattr(package_builds, "BUILDER", "import time; time.sleep(0.5)")
    builds = package_builds.PackageBuilds()
    monkeypatch.setattr(package_builds, "BUILDS", builds)
    builds.start(package_builds.BuildJob(double, "double", tmp_path / "double.pt2", (), tree_flatten(())[1]), print)
    with caplog.at_level(logging.INFO, logger="gsplatam"):
        package_builds.wait_for_builds(lambda: stopped)
    assert "waiting for 1 ahead-of-time package(s)" in caplog.text
    assert builds.pending() == int(stopped)
    assert ("left 1 package build(s) to finish in the background" in caplog.text) == stopped
    builds.wait()


def test_a_cache_folder_that_cannot_be_made_means_the_fallback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    precompiled = Precompiled(double, "double", blocked / "aoti", fallback=lambda s: s * 3)
    with caplog.at_level(logging.WARNING, logger="gsplatam"):
        assert torch.equal(precompiled(torch.ones(3)), torch.full((3,), 3.0))
    assert BUILDS.pending() == 0
    assert "its cache folder cannot be made" in caplog.text


@pytest.mark.slow
def test_the_mapping_loss_package_equals_the_loss_in_value_and_gradient(tmp_path: Path) -> None:
    """The mapping loss (SSIM and L1) from its joint package, forward and backward in one call,
    against autograd on the plain function, where the observed images need no gradient."""
    generator = torch.Generator().manual_seed(1)
    images = [torch.rand(shape, generator=generator) for shape in ((12, 16, 3), (12, 16), (12, 16, 3), (12, 16))]
    images[3][images[3] < 0.2] = 0  # invalid depth
    weights = (0.2, 1.0, 0.5)

    def value_and_gradients(loss: Any) -> list[torch.Tensor]:
        color, depth = (image.clone().requires_grad_(True) for image in images[:2])
        value = loss(color, depth, *images[2:], *weights)
        (3.0 * value).backward()  # a gradient other than 1 flows into the loss
        return [value.detach(), color.grad, depth.grad]

    want = value_and_gradients(mapping_loss)
    building = Precompiled(mapping_loss, "mapping_loss", tmp_path, fallback=mapping_loss, joint=True)
    value_and_gradients(building)
    assert BUILDS.wait() and building.built == 1
    loaded = Precompiled(mapping_loss, "mapping_loss", tmp_path, fallback=_never_called, joint=True)
    for got, expected in zip(value_and_gradients(loaded), want):
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    assert loaded.loaded == 1
