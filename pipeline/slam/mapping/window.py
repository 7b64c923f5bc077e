"""Mapping: optimise the Gaussians against a window of keyframes (with their poses fixed, as
SplaTAM does, or optimised jointly)."""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass

import torch

from pipeline.config import LossConfig, MappingConfig
from pipeline.geometry import invert_pose, se3_exp
from pipeline.render import Camera, Gaussians, Renderer, ViewsRenderer
from pipeline.slam.gaussian_map import PARAMETER_NAMES, as_leaves, prune_mask
from pipeline.slam.kernels import EAGER, SlamKernels
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.mapping.captured import CapturedMapping
from pipeline.slam.mapping.optimizers import MapOptimizer, learning_rates, make_map_optimizer


def _prune(optimizer: MapOptimizer, keep: torch.Tensor) -> Gaussians:
    """Drop Gaussians (all but the positions `keep` [M]) from the parameters and Adam's moments alike."""
    kept = {}
    for group in optimizer.param_groups:
        old = group["params"][0]
        new = old.detach()[keep].requires_grad_(True)
        state = optimizer.state.pop(old, None)
        if state:
            optimizer.state[new] = {k: v[keep] if k in ("exp_avg", "exp_avg_sq") else v for k, v in state.items()}
        group["params"] = [new]
        kept[group["name"]] = new
    return Gaussians(**kept)


@dataclass(frozen=True)
class MapSettings:
    """What mapping needs besides the map, the views and the run's random state."""

    renderer: Renderer
    render_views: ViewsRenderer
    mapping: MappingConfig
    loss: LossConfig
    near: float  # metres
    far: float
    kernels: SlamKernels = EAGER
    captured: CapturedMapping | None = None  # passes with fixed poses and Adam at a fixed capacity (CUDA graphs)


@dataclass(frozen=True)
class WindowPlan:
    """How one pass of mapping optimises a window of views beyond SplaTAM's per-frame mapping:
    how many view renders, whether to stop early, and whether the views' poses move too."""

    iters: int  # view renders, `views_per_step` of them per optimiser step
    should_stop: Callable[[], bool] | None = None  # asked before each step: end the pass early (new work)
    pose_lr: float = 0.0  # > 0: each view's pose is optimised jointly, a twist per view, Adam at this step
    fixed: frozenset[int] = frozenset()  # positions in the views whose poses stay (the gauge: the first keyframe)
    on_step: Callable[[], None] | None = None  # called before each step (a mapping process's sign of life)


@dataclass(frozen=True)
class WindowResult:
    gaussians: Gaussians  # detached
    c2w: list[torch.Tensor]  # [4, 4] camera-to-world per view after the pass (moved only with pose_lr > 0)
    renders: int  # view renders done (fewer than planned when stopped early)
    kept: torch.Tensor | None  # [M] int64 positions in the input of the Gaussians kept by pruning (None: no pruning)


def map_window(
    gaussians: Gaussians,
    views: list[Keyframe],
    intrinsics: torch.Tensor,
    scene_radius: float,
    rng: random.Random,
    settings: MapSettings,
    on_step: Callable[[], None] | None = None,
) -> WindowResult:
    """SplaTAM's mapping of a frame: `config.iters` view renders at fixed poses (`optimise_window`)."""
    plan = WindowPlan(settings.mapping.iters, on_step=on_step)
    return optimise_window(gaussians, views, intrinsics, scene_radius, rng, settings, plan)


def optimise_window(
    gaussians: Gaussians,
    views: list[Keyframe],
    intrinsics: torch.Tensor,
    scene_radius: float,
    rng: random.Random,
    settings: MapSettings,
    plan: WindowPlan,
) -> WindowResult:
    """`plan.iters` view renders, drawn at random from `views`, `config.views_per_step` of them
    rendered together for each optimiser step (1: SplaTAM's one view per Adam step); pruning
    before the steps whose renders include an index of `config.prune_at` (Gaussians larger than
    `prune_scale_factor` x `scene_radius` metres go too). With `plan.pose_lr` the views' poses
    are optimised with the Gaussians (the pose gradient through the view matrix, as in
    tracking), each as a twist applied to its camera-to-world: T = exp(twist) @ c2w."""
    config = settings.mapping
    if settings.captured is not None and plan.pose_lr == 0 and config.optimizer == "adam":
        mapped, renders_done, pruned = settings.captured.optimise(
            gaussians, views, intrinsics, scene_radius, rng, plan.iters, plan.on_step, plan.should_stop
        )
        return WindowResult(mapped, [view.c2w for view in views], renders_done, pruned)
    params = as_leaves(gaussians)
    rates = learning_rates(config)
    groups = [{"params": [getattr(params, n)], "lr": rates[n], "name": n} for n in PARAMETER_NAMES]
    optimizer = make_map_optimizer(groups, config.optimizer, params.means.is_cuda)
    poses = _ViewPoses(views, intrinsics, settings, plan)
    per_step, done = config.views_per_step, 0
    kept: torch.Tensor | None = None
    for first in range(0, plan.iters, per_step):
        if plan.on_step is not None:
            plan.on_step()
        if plan.should_stop is not None and plan.should_stop():
            break
        renders = range(first, min(first + per_step, plan.iters))
        if any(i in config.prune_at for i in renders):
            with torch.no_grad():
                keep = prune_mask(params, config.prune_opacity, config.prune_scale_factor * scene_radius)
                keep = keep.nonzero()[:, 0]  # positions: the count is read back once, not per gathered tensor
            params = _prune(optimizer, keep)
            kept = keep if kept is None else kept[keep]
        picks = [rng.randrange(len(views)) for _ in renders]
        loss, visible = _views_loss(params, [views[p] for p in picks], poses.cameras(picks), settings)
        optimizer.zero_grad(set_to_none=True)
        poses.zero_grad()
        loss.backward()
        optimizer.step(visible)
        poses.step()
        done += len(renders)
    detached = Gaussians(*(getattr(params, n).detach() for n in PARAMETER_NAMES))
    return WindowResult(detached, poses.c2w(), done, kept)


class _ViewPoses:
    """The views' cameras in a mapping pass: fixed (SplaTAM), or each moved by a twist that Adam
    optimises with the map (float64: the exponential map cancels badly in float32)."""

    def __init__(
        self, views: list[Keyframe], intrinsics: torch.Tensor, settings: MapSettings, plan: WindowPlan
    ) -> None:
        height, width = views[0].depth.shape
        self._frame = (intrinsics, width, height, settings.near, settings.far)
        self._c2w = [v.c2w for v in views]
        self._fixed = [Camera(invert_pose(c2w), *self._frame) for c2w in self._c2w]
        self._twists: torch.Tensor | None = None
        self._optimizer: torch.optim.Adam | None = None
        self._moving = [p for p in range(len(views)) if p not in plan.fixed]
        if plan.pose_lr > 0 and self._moving:
            self._twists = torch.zeros(len(views), 6, dtype=torch.float64, device=intrinsics.device, requires_grad=True)
            self._optimizer = torch.optim.Adam([self._twists], lr=plan.pose_lr)

    def _moved(self, position: int) -> torch.Tensor:
        assert self._twists is not None
        c2w = self._c2w[position]
        if position not in self._moving:
            return c2w
        return (se3_exp(self._twists[position]) @ c2w.double()).to(c2w.dtype)

    def cameras(self, picks: list[int]) -> list[Camera]:
        if self._twists is None:
            return [self._fixed[p] for p in picks]
        return [Camera(invert_pose(self._moved(p)), *self._frame) for p in picks]

    def zero_grad(self) -> None:
        if self._optimizer is not None:
            self._optimizer.zero_grad(set_to_none=True)

    def step(self) -> None:
        if self._optimizer is not None:
            self._optimizer.step()

    def c2w(self) -> list[torch.Tensor]:
        if self._twists is None:
            return list(self._c2w)
        with torch.no_grad():
            return [self._moved(p).detach() for p in range(len(self._c2w))]


def _views_loss(
    params: Gaussians, views: list[Keyframe], cameras: list[Camera], settings: MapSettings
) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean mapping loss over the views, and the Gaussians any of them saw ([N] bool)."""
    config, weights, kernels = settings.mapping, settings.loss, settings.kernels
    outs = [settings.renderer(params, cameras[0])] if len(cameras) == 1 else settings.render_views(params, cameras)
    losses = [
        kernels.mapping_loss(
            out.color, out.depth, view.color, view.depth, config.ssim_weight, weights.depth_weight, weights.color_weight
        )
        for out, view in zip(outs, views)
    ]
    visible = outs[0].visible
    for out in outs[1:]:
        visible = visible | out.visible
    return (losses[0] if len(losses) == 1 else torch.stack(losses).mean()), visible
