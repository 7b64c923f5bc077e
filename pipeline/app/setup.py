"""The one step that finishes a config: what was asked for (preset, file, `--set`, options),
completed for the dataset's layout, the compute device and a live session, with the changes a
session makes to it (the generated room's sizes and folder, a Ray session's run folder).
Nothing changes the config after it: it is what the run folder's config.toml holds."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import torch

from pipeline.config import Config, validate, with_absolute_dataset_path, with_dataset_defaults, with_value
from pipeline.render import resolve_backend

LIVE_LAYOUT = "tum"  # a phone's depth is a real sensor's, as TUM's: its per-dataset values


@dataclass(frozen=True)
class Setup:
    """A finished config and the device it runs on."""

    config: Config
    device: torch.device


def finish_config(
    config: Config,
    device: torch.device,
    layout: str,
    *,
    live: bool = False,
    changes: Sequence[tuple[str, Any]] = (),
) -> Setup:
    """`config` with `changes` (dotted keys) made, the dataset's folder made absolute (not `live`), the values SplaTAM tunes per dataset layout
    (`layout`: replica or tum) filled in, the render backend chosen for `device` and, when `live`, the bounds of a session
    that runs for hours; UserError for a value out of range, ImportError when loop closure is
    on without GTSAM (the 'loops' extra)."""
    for key, value in changes:
        config = with_value(config, key, value)
    if not live:  # a live run's dataset.path names its camera (record3d:URL)
        config = with_absolute_dataset_path(config)
    config = with_dataset_defaults(config, layout)
    config = replace(config, render=replace(config.render, backend=resolve_backend(config.render, device)))
    if live:
        config = _with_live_bounds(config)
    validate(config)
    if config.loops.enabled:
        import gtsam  # noqa: F401  (the pose graph's solver: missing, one line now, not at the first loop found)
    return Setup(config, device)


def _with_live_bounds(config: Config) -> Config:
    """Keyframes and map bounded by `live.max_keyframes` and `live.max_gaussians`, unless
    keyframes.max_kept / mapping.max_gaussians are set."""
    if not config.keyframes.max_kept:
        config = replace(config, keyframes=replace(config.keyframes, max_kept=config.live.max_keyframes))
    if not config.mapping.max_gaussians:
        config = replace(config, mapping=replace(config.mapping, max_gaussians=config.live.max_gaussians))
    return config
