"""Mapping passes at a fixed capacity (the steps a CUDA graph replays) against the eager passes:
the same map, pruning included, when the capacity holds, when it overflows and grows, and when
the map outgrows its rows. On the CPU the same steps run without a graph."""

from __future__ import annotations

import random

import pytest
import torch
from plane_scene import K, plane_scene

from pipeline.config import GaussianConfig, LossConfig, MappingConfig, RenderConfig
from pipeline.render import Gaussians, make_capacity_renderer, make_renderer, make_views_renderer
from pipeline.slam.gaussian_map import concatenate
from pipeline.slam.kernels import EAGER
from pipeline.slam.mapping import captured
from pipeline.slam.mapping.captured import CapturedMapping
from pipeline.slam.mapping.window import MapSettings, map_window

CPU = torch.device("cpu")


def _settings(config: MappingConfig, graphed: bool) -> MapSettings:
    render, gaussians = RenderConfig(), GaussianConfig()
    single = make_renderer(render, gaussians, CPU)
    views = make_views_renderer(render, gaussians, CPU)
    fixed = None
    if graphed:
        capacity_renderer = make_capacity_renderer(render, gaussians, CPU)
        assert capacity_renderer is not None
        fixed = CapturedMapping(capacity_renderer, config, LossConfig(), EAGER, 0.01, 100.0, CPU)
    return MapSettings(single, views, config, LossConfig(), 0.01, 100.0, EAGER, fixed)


def _map(gaussians: Gaussians, settings: MapSettings) -> tuple[Gaussians, torch.Tensor | None, int]:
    _, keyframes = plane_scene()
    result = map_window(gaussians, keyframes, K, 2.0, random.Random(4), settings)
    return result.gaussians, result.kept, result.renders


def _assert_same(a: Gaussians, b: Gaussians) -> None:
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-5, atol=1e-7, msg=name)


@pytest.mark.parametrize("per_step", [1, 2])
def test_fixed_capacity_passes_equal_the_eager_ones_with_pruning(per_step: int) -> None:
    gaussians, _ = plane_scene()
    gaussians.opacity_logits[::7] = -6.0  # opacity 0.0025: under the pruning threshold
    config = MappingConfig(iters=5, views_per_step=per_step, prune_at=(0, 3))
    eager, eager_kept, eager_renders = _map(gaussians, _settings(config, graphed=False))
    fixed, fixed_kept, fixed_renders = _map(gaussians, _settings(config, graphed=True))
    assert eager_kept is not None and fixed_kept is not None and torch.equal(eager_kept, fixed_kept)
    assert len(eager) < len(gaussians)  # the faint ones went
    assert fixed_renders == eager_renders == 5
    _assert_same(fixed, eager)


def test_an_overflowing_pass_runs_again_with_a_grown_capacity_and_the_same_picks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    gaussians, _ = plane_scene()
    config = MappingConfig(iters=4, prune_at=())
    eager, _, _ = _map(gaussians, _settings(config, graphed=False))
    monkeypatch.setattr(captured, "INTERSECTION_QUANTUM", 64)  # far below this scene's ~800 intersections
    settings = _settings(config, graphed=True)
    assert settings.captured is not None and settings.captured.capacity == 64
    fixed, _, _ = _map(gaussians, settings)
    assert settings.captured.capacity > 64
    _assert_same(fixed, eager)


def test_the_buffers_grow_with_the_map_and_inert_rows_never_show(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(captured, "ROW_QUANTUM", 256)
    gaussians, _ = plane_scene()
    config = MappingConfig(iters=3, prune_at=())
    settings = _settings(config, graphed=True)
    assert settings.captured is not None
    first, _, _ = _map(gaussians, settings)
    grown_input = concatenate(gaussians, gaussians)  # past the 1024 rows the first pass had
    grown, _, _ = _map(grown_input, settings)
    eager, _, _ = _map(grown_input, _settings(config, graphed=False))
    assert len(first) == len(gaussians) and len(grown) == 2 * len(gaussians)
    _assert_same(grown, eager)
