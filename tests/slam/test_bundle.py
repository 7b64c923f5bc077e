"""Local bundle adjustment (`mapping/bundle.py`): a drifted window's keyframe poses come back to
where the map says they are, the oldest stays, and the window is the keyframes that see the
newest one."""

from __future__ import annotations

import random
from dataclasses import replace

import numpy as np
import pytest
import torch

from pipeline.config import SyntheticConfig, load_config, with_dataset_defaults
from pipeline.geometry import invert_pose, se3_exp
from pipeline.io.sources.datasets.synthetic import default_intrinsics, make_scene, render_view, trajectory
from pipeline.render import Camera, Gaussians, make_renderer
from pipeline.slam.gaussian_map import concatenate, seed_gaussians
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.loops.closer import NoLoopCloser
from pipeline.slam.mapping.backend import MappingBackend
from pipeline.slam.mapping.bundle import adjust, covisible
from pipeline.slam.mapping.window import MapSettings
from pipeline.slam.sides import backend_settings
from pipeline.slam.state import BackendState

WIDTH, HEIGHT = 64, 48
CONFIG = with_dataset_defaults(load_config("tiny", overrides=["mapping.adjust_window=5"]), "replica")
CPU = torch.device("cpu")
RENDERER = make_renderer(CONFIG.render, CONFIG.gaussians, CPU)
INTRINSICS = torch.from_numpy(default_intrinsics(WIDTH, HEIGHT)).float()
SCENE = make_scene(0)


def render(gaussians: Gaussians, c2w: torch.Tensor):
    return RENDERER(gaussians, Camera(invert_pose(c2w), INTRINSICS, WIDTH, HEIGHT, 0.01, 100.0))


def world_of(truth: list[torch.Tensor]) -> Gaussians:
    """The room as a map grown as SLAM grows one: seeded from the first exact view, then where
    the map so far covers less than half of each next view."""
    world: Gaussians | None = None
    for c2w in truth:
        color, depth = render_view(SCENE, c2w.double().numpy(), default_intrinsics(WIDTH, HEIGHT), WIDTH, HEIGHT, 1)
        color_t, depth_t = torch.from_numpy(color).float() / 255, torch.from_numpy(depth)
        mask = depth_t > 0
        if world is not None:
            mask &= render(world, c2w).silhouette < 0.5
        seeds = seed_gaussians(color_t, depth_t, INTRINSICS, c2w, mask, CONFIG.gaussians)
        world = seeds if world is None else concatenate(world, seeds)
    assert world is not None
    return world


Window = tuple[
    Gaussians, list[Keyframe], list[torch.Tensor]
]  # the map, the keyframes at drifted poses, their true poses


@pytest.fixture(scope="module")
def window() -> Window:
    """Five keyframes 20 cm apart whose images are the map's own renders at the true poses (a
    map the frames agree with), at poses that drift 1 cm and 0.5 degrees more per keyframe."""
    truth = [torch.from_numpy(c2w).float() for c2w in trajectory(SyntheticConfig(seed=0, speed=1.0), 30)[::6]]
    world = world_of(truth)
    generator = torch.Generator().manual_seed(0)
    keyframes = []
    for k, c2w in enumerate(truth):
        out = render(world, c2w)
        covered = out.silhouette > 0.9
        color = (out.color / out.silhouette.clamp(min=0.9)[..., None]).clamp(0, 1)
        depth = torch.where(covered, out.depth, torch.zeros_like(out.depth))
        axis = torch.nn.functional.normalize(torch.randn(2, 3, generator=generator, dtype=torch.float64), dim=-1)
        error = se3_exp(torch.cat([np.radians(0.5 * k) * axis[0], 0.01 * k * axis[1]]))
        keyframes.append(Keyframe.of(k, color, depth, (c2w.double() @ error).float()))
    return world, keyframes, truth


def centre_errors_mm(c2w: list[torch.Tensor], truth: list[torch.Tensor]) -> list[float]:
    return [1000 * float((a[:3, 3] - b[:3, 3]).norm()) for a, b in zip(c2w, truth)]


def test_adjustment_lowers_the_pose_error_of_a_drifted_window_and_keeps_the_oldest(window: Window) -> None:
    """Measured: keyframe centres 10, 20, 30, 40 mm off -> 3.1, 2.8, 12.6, 5.8 mm after 140 renders
    (converged: a round of five moved no twist more than 0.5 mm)."""
    world, keyframes, truth = window
    settings = MapSettings(RENDERER, RENDERER, CONFIG.mapping, CONFIG.loss, 0.01, 100.0)
    before = centre_errors_mm([k.c2w for k in keyframes], truth)
    result = adjust(world, keyframes, INTRINSICS, 1.5, random.Random(0), settings)
    after = centre_errors_mm(result.c2w, truth)
    assert result.c2w[0] is keyframes[0].c2w  # the gauge: the very tensor, untouched
    assert result.renders < CONFIG.mapping.adjust_iters  # it stopped because it converged
    assert max(after[1:]) < 0.5 * max(before[1:])
    assert sum(after[1:]) < 0.3 * sum(before[1:])


def test_the_window_is_the_newest_and_the_keyframes_that_see_most_of_it(window: Window) -> None:
    _, keyframes, _ = window
    turned = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))  # half a turn about the camera's vertical axis
    far = Keyframe.of(9, keyframes[0].color, keyframes[0].depth, keyframes[-1].c2w @ turned)  # sees none of it
    store = [far, *keyframes]
    picks = covisible(store, 3, INTRINSICS, 400, torch.Generator().manual_seed(0))
    assert picks[-1] == len(store) - 1 and len(picks) == 3 and 0 not in picks
    assert picks == sorted(picks)
    assert covisible(store, 10, INTRINSICS, 400, torch.Generator().manual_seed(0)) == list(range(1, len(store)))


@pytest.mark.parametrize("pose_lr", [0.0, 2e-3], ids=["fixed", "moving"])
def test_the_final_refinement_moves_every_keyframe_but_the_first_at_its_own_pose_step(
    window: Window, pose_lr: float
) -> None:
    """`mapping.final_pose_lr`, not the refinement passes' `refine_pose_lr` (0 here): 0 keeps every
    pose; 2e-3 makes the final pass a global adjustment that brings the drifted poses back, the
    first keyframe (the gauge) the very tensor it was."""
    world, keyframes, truth = window
    mapping = replace(CONFIG.mapping, refine_pose_lr=0.0, final_pose_lr=pose_lr)
    config = replace(CONFIG, mapping=mapping)
    backend = MappingBackend(backend_settings(config, RENDERER, CPU), NoLoopCloser(), CPU)
    state = random.Random(0).getstate(), torch.Generator().get_state()
    backend.restore(BackendState(world, list(keyframes), 1.5, *state, len(keyframes), None, INTRINSICS))
    assert backend.finish(100) == 100
    before = centre_errors_mm([k.c2w for k in keyframes], truth)
    after = centre_errors_mm([k.c2w for k in backend.keyframes], truth)
    assert backend.keyframes[0].c2w is keyframes[0].c2w
    if pose_lr == 0:
        assert all(torch.equal(a.c2w, b.c2w) for a, b in zip(backend.keyframes, keyframes))
    else:
        assert sum(after[1:]) < 0.5 * sum(before[1:]), (before, after)
