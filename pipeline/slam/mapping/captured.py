"""Mapping steps at a fixed capacity, recorded once as a CUDA graph and replayed.

One mapping step (render the step's views, the mapping loss, backward, Adam) is a few hundred
kernels. Eagerly, gsplat reads the tile-intersection count back before every rasterisation, so
the host and the GPU take turns (bench/results/capture_cost_h200_30e0a44.json: 3.5 ms of wall
time for 1.8 ms of kernels at 100k Gaussians). Here every size in a step is fixed:
- the Gaussians sit in buffers of `rows` rows; the rows past the map are inert (opacity under
  gsplat's 1/255 cut: never drawn, zero gradient, so Adam leaves them be);
- the tile intersections have a capacity (`render.intersections`), and the largest count of
  the pass is kept on the device and read once at its end: past the capacity the pass is run
  again with a larger one (its input map is untouched until it succeeds).
Both grow in steps, and a graph is recorded again only when a size changes. On the CPU the same
steps run without a graph (the tests' path). The results equal `window.optimise_window`'s for
fixed poses and Adam (same picks, same pruning, same steps), up to float rounding.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass

import torch

from pipeline.config import LossConfig, MappingConfig
from pipeline.geometry import invert_pose
from pipeline.render import Camera, CapacityRenderer, Gaussians
from pipeline.render.intersections import INTERSECTION_QUANTUM, grown_capacity
from pipeline.slam.cuda_graphs import record
from pipeline.slam.gaussian_map import PARAMETER_NAMES, prune_mask
from pipeline.slam.kernels import SlamKernels
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.mapping.optimizers import EPS, learning_rates

ROW_QUANTUM = 1 << 16  # Gaussian rows grow in steps of this many
INERT_OPACITY_LOGIT = -20.0  # opacity 2e-9: under gsplat's 1/255, never drawn


def _rounded_up(count: float, quantum: int) -> int:
    return max(quantum, math.ceil(count / quantum) * quantum)


@dataclass(frozen=True)
class _Shape:
    """What a recorded step depends on besides tensor contents."""

    rows: int
    scale_axes: int  # 1 isotropic, 3 anisotropic
    views: int
    height: int
    width: int
    capacity: int  # tile intersections


class CapturedMapping:
    """Mapping passes with fixed poses and Adam, each step replayed from a CUDA graph (on CUDA)."""

    def __init__(
        self,
        render: CapacityRenderer,
        config: MappingConfig,
        loss: LossConfig,
        kernels: SlamKernels,
        near: float,
        far: float,
        device: torch.device,
    ) -> None:
        self.render, self.config, self.loss, self.kernels = render, config, loss, kernels
        self.near, self.far, self.device = near, far, device
        self.capacity = INTERSECTION_QUANTUM
        self.rerecorded = 0  # graphs recorded so far (a size changed)
        self._shape: _Shape | None = None
        self._graph: torch.cuda.CUDAGraph | None = None

    def optimise(
        self,
        gaussians: Gaussians,
        views: list[Keyframe],
        intrinsics: torch.Tensor,
        scene_radius: float,
        rng: random.Random,
        iters: int,
        on_step: Callable[[], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
    ) -> tuple[Gaussians, int, torch.Tensor | None]:
        """`window.optimise_window` with fixed poses and Adam -> (the map after the pass,
        detached; view renders done; positions in the input of the Gaussians pruning kept, or
        None). A pass whose intersections overflowed runs again with the capacity grown (the
        random state is restored, so the picks are the same)."""
        state = rng.getstate()
        while True:
            result, peak = self._pass(gaussians, views, intrinsics, scene_radius, rng, iters, on_step, should_stop)
            if peak <= self.capacity:
                return result
            self.capacity = grown_capacity(peak, INTERSECTION_QUANTUM)
            rng.setstate(state)

    def _pass(
        self,
        gaussians: Gaussians,
        views: list[Keyframe],
        intrinsics: torch.Tensor,
        scene_radius: float,
        rng: random.Random,
        iters: int,
        on_step: Callable[[], None] | None,
        should_stop: Callable[[], bool] | None,
    ) -> tuple[tuple[Gaussians, int, torch.Tensor | None], int]:
        per_step = self.config.views_per_step
        height, width = views[0].depth.shape
        shape = _Shape(
            _rounded_up(len(gaussians), ROW_QUANTUM),
            gaussians.log_scales.shape[1],
            per_step,
            height,
            width,
            self.capacity,
        )
        self._prepare(shape, gaussians, views[0], intrinsics)
        w2c = [invert_pose(view.c2w) for view in views]
        n, done = len(gaussians), 0
        kept: torch.Tensor | None = None
        for first in range(0, iters, per_step):
            if on_step is not None:
                on_step()
            if should_stop is not None and should_stop():
                break
            renders = range(first, min(first + per_step, iters))
            if any(i in self.config.prune_at for i in renders):
                keep = self._prune(n, scene_radius)
                n = len(keep)
                kept = keep if kept is None else kept[keep]
            picks = [rng.randrange(len(views)) for _ in renders]
            self._load_views([views[p] for p in picks], [w2c[p] for p in picks])
            if len(picks) == per_step and self._graph is not None:
                self._graph.replay()
            else:
                self._step(len(picks))
            done += len(renders)
        peak = int(self._peak)  # the pass's one read of the intersection count
        mapped = Gaussians(*(getattr(self._params, name).detach()[:n].clone() for name in PARAMETER_NAMES))
        return (mapped, done, kept), peak

    def _prepare(self, shape: _Shape, gaussians: Gaussians, view: Keyframe, intrinsics: torch.Tensor) -> None:
        """Buffers and graph for `shape` (made again when it changed), then the map loaded."""
        if shape != self._shape:
            self._allocate(shape, view, intrinsics)
            if self.device.type == "cuda":
                self._record()
        self._intrinsics.copy_(intrinsics)
        self._load(gaussians)

    def _allocate(self, shape: _Shape, view: Keyframe, intrinsics: torch.Tensor) -> None:
        device, rows = self.device, shape.rows
        self._shape, self._graph = shape, None
        self._params = Gaussians(
            means=torch.zeros(rows, 3, device=device, requires_grad=True),
            quats=torch.zeros(rows, 4, device=device, requires_grad=True),
            log_scales=torch.zeros(rows, shape.scale_axes, device=device, requires_grad=True),
            opacity_logits=torch.zeros(rows, device=device, requires_grad=True),
            colors=torch.zeros(rows, 3, device=device, requires_grad=True),
        )
        rates = learning_rates(self.config)
        groups = [{"params": [getattr(self._params, name)], "lr": rates[name]} for name in PARAMETER_NAMES]
        cuda = device.type == "cuda"
        self._optimizer = torch.optim.Adam(groups, eps=EPS, fused=cuda, capturable=cuda)
        self._w2c = torch.eye(4, device=device).repeat(shape.views, 1, 1)
        self._intrinsics = intrinsics.detach().clone()
        self._colors = view.color.new_zeros(shape.views, shape.height, shape.width, 3)
        self._depths = view.depth.new_zeros(shape.views, shape.height, shape.width)
        self._peak = torch.zeros((), dtype=torch.long, device=device)

    def _record(self) -> None:
        """Warm up (compiled code settles, Adam's state is made), then record one step. The
        warm-up steps move the buffers' contents; the pass loads its map afterwards."""
        assert self._shape is not None
        views = self._shape.views
        self._graph, _ = record(lambda: self._step(views))
        self.rerecorded += 1

    @torch.no_grad()
    def _load(self, gaussians: Gaussians) -> None:
        """The map into the first rows, the rest inert; Adam starts afresh (as each eager pass's
        new optimiser does); the peak count is reset. The gradients stay where they are: a
        recorded step writes into them."""
        n = len(gaussians)
        for name in PARAMETER_NAMES:
            getattr(self._params, name)[:n] = getattr(gaussians, name)
        self._make_inert(n)
        for state in self._optimizer.state.values():
            for value in state.values():
                value.zero_()
        self._peak.zero_()

    @torch.no_grad()
    def _make_inert(self, n: int) -> None:
        params = self._params
        params.means[n:] = 0.0
        params.quats[n:] = 0.0
        params.quats[n:, 0] = 1.0
        params.log_scales[n:] = -10.0
        params.opacity_logits[n:] = INERT_OPACITY_LOGIT
        params.colors[n:] = 0.0

    @torch.no_grad()
    def _prune(self, n: int, scene_radius: float) -> torch.Tensor:
        """Drop Gaussians from the first `n` rows (and Adam's moments alike), the kept moved to the
        front -> the kept positions [M] among those rows (one host read of the count)."""
        head = Gaussians(*(getattr(self._params, name)[:n] for name in PARAMETER_NAMES))
        keep = prune_mask(head, self.config.prune_opacity, self.config.prune_scale_factor * scene_radius).nonzero()[
            :, 0
        ]
        m = len(keep)
        for name in PARAMETER_NAMES:
            buffer = getattr(self._params, name)
            buffer[:m] = buffer[keep].clone()
            for key in ("exp_avg", "exp_avg_sq"):
                moment = self._optimizer.state.get(buffer, {}).get(key)
                if moment is not None:
                    moment[:m] = moment[keep].clone()
                    moment[m:] = 0.0
        self._make_inert(m)
        return keep

    @torch.no_grad()
    def _load_views(self, views: list[Keyframe], w2c: list[torch.Tensor]) -> None:
        for slot, (view, pose) in enumerate(zip(views, w2c)):
            self._colors[slot].copy_(view.color)
            self._depths[slot].copy_(view.depth)
            self._w2c[slot].copy_(pose)

    def _step(self, views: int) -> None:
        """One optimiser step over the first `views` loaded views (no host read)."""
        assert self._shape is not None
        shape = self._shape
        cameras = [
            Camera(self._w2c[v], self._intrinsics, shape.width, shape.height, self.near, self.far) for v in range(views)
        ]
        outputs, hits = self.render(self._params, cameras, shape.capacity)
        config, weights = self.config, self.loss
        losses = [
            self.kernels.mapping_loss(
                out.color, out.depth, self._colors[v], self._depths[v], config.ssim_weight, weights.depth_weight,
                weights.color_weight,
            )
            for v, out in enumerate(outputs)
        ]  # fmt: skip
        loss = losses[0] if views == 1 else torch.stack(losses).mean()
        self._optimizer.zero_grad(set_to_none=False)
        loss.backward()
        self._optimizer.step()
        torch.maximum(self._peak, hits.count, out=self._peak)
