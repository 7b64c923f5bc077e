"""Mapping's options: several views per optimiser step, and Adam on the visible Gaussians only."""

from __future__ import annotations

import random

import torch
from plane_scene import K, plane_scene

from pipeline.config import GaussianConfig, LossConfig, MappingConfig, RenderConfig
from pipeline.render import Camera, Gaussians, make_renderer
from pipeline.slam.mapping.optimizers import SelectiveAdamReference
from pipeline.slam.mapping.window import MapSettings, map_window

CPU = torch.device("cpu")


def test_selective_adam_moves_only_the_visible_rows_by_gsplats_rule() -> None:
    """The plain twin of gsplat's kernel: m, v and the parameter change only on visible rows;
    there, m = b1 m + (1 - b1) g, v = b2 v + (1 - b2) g^2, p -= lr m / (sqrt(v) + eps), no bias
    correction."""
    param = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], requires_grad=True)
    optimizer = SelectiveAdamReference([{"params": [param], "lr": 0.1}], eps=1e-8)
    visible = torch.tensor([True, False, True])
    expected, m, v = param.detach().clone(), torch.zeros(3, 2), torch.zeros(3, 2)
    for scale in (1.0, -2.0):
        grad = scale * torch.tensor([[0.5, -1.0], [2.0, 2.0], [0.1, 0.3]])
        param.grad = grad.clone()
        optimizer.step(visible)
        m[visible] = 0.9 * m[visible] + 0.1 * grad[visible]
        v[visible] = 0.999 * v[visible] + 0.001 * grad[visible] ** 2
        expected[visible] -= 0.1 * m[visible] / (v[visible].sqrt() + 1e-8)
    torch.testing.assert_close(param.detach(), expected)
    assert torch.equal(param.detach()[1], torch.tensor([3.0, 4.0]))
    state = optimizer.state[param]
    assert torch.equal(state["exp_avg"][1], torch.zeros(2)) and torch.equal(state["exp_avg_sq"][1], torch.zeros(2))


def _settings(config: MappingConfig, calls: list[int]) -> MapSettings:
    single = make_renderer(RenderConfig(), GaussianConfig(), CPU)

    def one(gaussians: Gaussians, camera: Camera):  # type: ignore[no-untyped-def]
        calls.append(1)
        return single(gaussians, camera)

    def several(gaussians: Gaussians, cameras: list[Camera]):  # type: ignore[no-untyped-def]
        calls.append(len(cameras))
        return [single(gaussians, camera) for camera in cameras]

    return MapSettings(one, several, config, LossConfig(), 0.01, 100.0)


def test_several_views_per_step_render_as_many_views_in_fewer_steps() -> None:
    gaussians, keyframes = plane_scene()
    for per_step, expected in ((1, [1] * 6), (2, [2, 2, 2]), (4, [4, 2])):
        calls: list[int] = []
        config = MappingConfig(iters=6, views_per_step=per_step, prune_at=())
        mapped = map_window(gaussians, keyframes, K, 10.0, random.Random(0), _settings(config, calls)).gaussians
        assert calls == expected  # the same 6 view renders, grouped per optimiser step
        assert torch.isfinite(mapped.colors).all() and not torch.equal(mapped.colors, gaussians.colors)


def test_mapping_with_selective_adam_leaves_unseen_gaussians_untouched() -> None:
    gaussians, keyframes = plane_scene()
    config = MappingConfig(iters=4, prune_at=(), optimizer="selective_adam")
    mapped = map_window(gaussians, keyframes, K, 10.0, random.Random(0), _settings(config, [])).gaussians
    assert torch.equal(mapped.colors[-1], gaussians.colors[-1]) and torch.equal(mapped.means[-1], gaussians.means[-1])
    assert not torch.equal(mapped.colors[:-1], gaussians.colors[:-1])
