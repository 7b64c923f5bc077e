"""Mapping's options: several views per optimiser step, and Adam on the visible Gaussians only."""

from __future__ import annotations

import random

import torch

from pipeline.config import GaussianConfig, LossConfig, MappingConfig, RenderConfig
from pipeline.geometry import invert_pose
from pipeline.render import Camera, Gaussians, make_renderer
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.mapping.optimizers import SelectiveAdamReference
from pipeline.slam.mapping.window import MapSettings, map_window

CPU = torch.device("cpu")
K = torch.tensor([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])


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


def _scene() -> tuple[Gaussians, list[Keyframe]]:
    """A textured plane 2 m ahead and one Gaussian behind the cameras, which no view sees."""
    v, u = torch.meshgrid(torch.arange(24) + 0.5, torch.arange(32) + 0.5, indexing="ij")
    z = torch.full_like(u, 2.0)
    means = torch.stack([(u - 16) / 40 * z, (v - 12) / 40 * z, z], -1).reshape(-1, 3)
    means = torch.cat([means, torch.tensor([[0.0, 0.0, -3.0]])])
    n = len(means)
    colors = 0.5 + 0.4 * torch.sin(means[:, :1] * 9 + torch.tensor([0.0, 1.0, 2.0]))
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    gaussians = Gaussians(means, quats, torch.full((n, 1), -3.6), torch.full((n,), 2.0), colors)
    renderer = make_renderer(RenderConfig(), GaussianConfig(), CPU)
    keyframes = []
    for i, dx in enumerate((0.0, 0.05, -0.05)):
        c2w = torch.eye(4)
        c2w[0, 3] = dx
        out = renderer(gaussians, Camera(invert_pose(c2w), K, 32, 24))
        keyframes.append(Keyframe.of(i, (out.color * 0.8).clamp(0, 1), out.depth * 1.02, c2w))
    return gaussians, keyframes


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
    gaussians, keyframes = _scene()
    for per_step, expected in ((1, [1] * 6), (2, [2, 2, 2]), (4, [4, 2])):
        calls: list[int] = []
        config = MappingConfig(iters=6, views_per_step=per_step, prune_at=())
        mapped = map_window(gaussians, keyframes, K, 10.0, random.Random(0), _settings(config, calls)).gaussians
        assert calls == expected  # the same 6 view renders, grouped per optimiser step
        assert torch.isfinite(mapped.colors).all() and not torch.equal(mapped.colors, gaussians.colors)


def test_mapping_with_selective_adam_leaves_unseen_gaussians_untouched() -> None:
    gaussians, keyframes = _scene()
    config = MappingConfig(iters=4, prune_at=(), optimizer="selective_adam")
    mapped = map_window(gaussians, keyframes, K, 10.0, random.Random(0), _settings(config, [])).gaussians
    assert torch.equal(mapped.colors[-1], gaussians.colors[-1]) and torch.equal(mapped.means[-1], gaussians.means[-1])
    assert not torch.equal(mapped.colors[:-1], gaussians.colors[:-1])
