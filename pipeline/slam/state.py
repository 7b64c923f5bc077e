"""What a checkpoint holds: a host copy of everything SLAM carries from frame to frame, in the
two parts the two sides of SLAM own (`TrackingFrontend.state`, `MappingBackend.state`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from pipeline.render.types import Gaussians
from pipeline.slam.keyframes import Keyframe


@dataclass
class FrontendState:
    """The tracking side's part: one pose per frame tracked and how tracking judged them."""

    poses: torch.Tensor  # [F, 4, 4] estimated camera-to-world per frame
    loss_history: list[float]
    last_prior: torch.Tensor | None  # [4, 4] the device's camera-to-world at the last good frame
    lost_frames: list[int] = field(default_factory=list)  # positions in `poses` of the frames judged lost
    relocalised_frames: list[int] = field(default_factory=list)  # and of those relocalised

    @property
    def frames_done(self) -> int:
        return int(self.poses.shape[0])


@dataclass
class BackendState:
    """The mapping side's part: the map, the keyframes and mapping's random state."""

    gaussians: Gaussians
    keyframes: list[Keyframe]
    scene_radius: float  # metres
    rng_state: tuple[Any, ...]  # random.Random.getstate(): mapping's view picks
    generator_state: torch.Tensor  # torch.Generator.get_state() (uint8): keyframe sampling
    frames_seen: int  # frames passed to mapping, mapped or not


@dataclass
class Checkpoint:
    """Everything needed to continue a run, on the host: a copy SLAM's later updates do not
    touch (safe to write from another thread while SLAM goes on). Mapping may have seen fewer
    frames than tracking (`mapping.frames_seen` <= `frames_done`): the frames between were
    tracked, not mapped."""

    tracking: FrontendState
    mapping: BackendState

    @property
    def frames_done(self) -> int:
        return self.tracking.frames_done

    @property
    def poses(self) -> torch.Tensor:
        """[F, 4, 4] camera-to-world per frame."""
        return self.tracking.poses

    @property
    def gaussians(self) -> Gaussians:
        return self.mapping.gaussians

    @property
    def keyframes(self) -> list[Keyframe]:
        return self.mapping.keyframes
