"""Mapping's optimiser: Adam, or Adam that updates only the Gaussians a step's views saw.

`selective_adam` is gsplat's SelectiveAdam on CUDA (one fused kernel over the visible rows) and
its plain twin here on the CPU. Both follow gsplat's kernel exactly: the moments and parameters
of invisible Gaussians stay as they are, and there is no bias correction (so the first steps are
larger than Adam's: the options are not the same algorithm, and bench/ compares them).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, Protocol

import torch

from pipeline.config import MapOptimizerKind, MappingConfig

BETAS = (0.9, 0.999)
EPS = 1e-15


def learning_rates(config: MappingConfig) -> dict[str, float]:
    """Adam's step per Gaussian parameter (by `gaussian_map.PARAMETER_NAMES`)."""
    return {
        "means": config.lr_means,
        "quats": config.lr_rotations,
        "log_scales": config.lr_scales,
        "opacity_logits": config.lr_opacities,
        "colors": config.lr_colors,
    }


class MapOptimizer(Protocol):
    """What mapping uses of an optimiser: its groups and state (for pruning) and a step that is
    told which Gaussians ([N] bool) the step's views saw."""

    param_groups: list[dict[str, Any]]
    state: Any

    def zero_grad(self, set_to_none: bool = True) -> None: ...

    def step(self, visible: torch.Tensor) -> None: ...


class _Adam(torch.optim.Adam):
    """torch's Adam (fused on CUDA); every Gaussian is updated, seen or not."""

    def step(self, visible: torch.Tensor) -> None:  # type: ignore[override]
        super().step()


class SelectiveAdamReference(torch.optim.Optimizer):
    """The plain twin of gsplat's SelectiveAdam: each group one [N, ...] parameter."""

    def __init__(self, groups: Iterable[dict[str, Any]], eps: float = EPS, betas: tuple[float, float] = BETAS) -> None:
        super().__init__(list(groups), {"lr": 1e-3, "eps": eps, "betas": betas})

    @torch.no_grad()
    def step(self, visible: torch.Tensor) -> None:  # type: ignore[override]
        for group in self.param_groups:
            (param,) = group["params"]
            if param.grad is None:
                continue
            state = self.state[param]
            if not state:
                state["step"] = torch.tensor(0.0)
                state["exp_avg"] = torch.zeros_like(param)
                state["exp_avg_sq"] = torch.zeros_like(param)
            beta1, beta2 = group["betas"]
            rows = visible.reshape(-1, *([1] * (param.dim() - 1)))
            grad, m, v = param.grad, state["exp_avg"], state["exp_avg_sq"]
            m.copy_(torch.where(rows, beta1 * m + (1 - beta1) * grad, m))
            v.copy_(torch.where(rows, beta2 * v + (1 - beta2) * grad * grad, v))
            update = group["lr"] * m / (v.sqrt() + group["eps"])
            param.sub_(torch.where(rows, update, torch.zeros_like(update)))


def make_map_optimizer(groups: list[dict[str, Any]], kind: MapOptimizerKind, cuda: bool) -> MapOptimizer:
    """`groups`: one dict per parameter ({"params": [tensor], "lr": ..., "name": ...})."""
    if kind == "adam":
        return _Adam(groups, eps=EPS, fused=cuda)
    if cuda:
        from gsplat.optimizers import SelectiveAdam

        return SelectiveAdam(groups, eps=EPS, betas=BETAS)
    return SelectiveAdamReference(groups)
