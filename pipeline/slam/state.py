"""What a checkpoint holds: a host copy of everything SLAM carries from frame to frame, in the
two parts the two sides of SLAM own (`TrackingFrontend.state`, `MappingBackend.state`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from pipeline.render.types import Gaussians
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.loops.detection import ClosedLoop, LoopTally
from pipeline.slam.loops.pose_graph import Edge


@dataclass
class FrontendState:
    """The tracking side's part: one pose per frame tracked and how tracking judged them."""

    poses: torch.Tensor  # [F, 4, 4] estimated camera-to-world per frame
    loss_history: list[float]
    last_prior: torch.Tensor | None  # [4, 4] the device's camera-to-world at the last good frame
    lost_frames: list[int] = field(default_factory=list)  # positions in `poses` of the frames judged lost
    relocalised_frames: list[int] = field(default_factory=list)  # and of those relocalised
    tracked_poses: torch.Tensor | None = None  # [F, 4, 4] as tracked, before keyframe corrections (None: `poses`)

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
    loops: LoopState | None = None  # loop closure's part (loops.enabled)
    intrinsics: torch.Tensor | None = None  # [3, 3] the frames' camera, once a frame was mapped (refinement needs it)


@dataclass
class LoopState:
    """Loop closure's part of the mapping side: the keyframe pose graph, which node created each
    Gaussian, and what loop closure did so far."""

    creator: torch.Tensor  # [N] int64: per Gaussian, the node of the keyframe that created it (-1: none)
    node_c2w: torch.Tensor  # [K, 4, 4] float64: every keyframe ever kept, camera-to-world as last known
    node_positions: list[int]  # per node, its frame's position among the run's poses
    odometry_information: torch.Tensor  # [K, 6, 6] float64: of the edge from node k-1 to node k (row 0 unused)
    loops: list[Edge] = field(default_factory=list)  # loop edges (between nodes) the pose graph kept
    tally: LoopTally = field(default_factory=LoopTally)
    closed: list[ClosedLoop] = field(default_factory=list)

    def node_of(self) -> dict[int, int]:
        """Frame position among the run's poses -> its keyframe's node."""
        return {position: node for node, position in enumerate(self.node_positions)}

    @staticmethod
    def empty() -> LoopState:
        f64 = torch.float64
        return LoopState(
            torch.zeros(0, dtype=torch.int64), torch.zeros(0, 4, 4, dtype=f64), [], torch.zeros(0, 6, 6, dtype=f64)
        )


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
