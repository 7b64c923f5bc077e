"""The typed messages between the tracking process and the mapping process.

Big tensors never travel in them: frames go through the frame ring, map versions through the
shared map (both allocated once). What does travel is small, or rare: a checkpoint's mapping
state (keyframe images stacked into a few tensors, so that it crosses as a few shared-memory
blocks rather than three per keyframe).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from pipeline.render.types import Gaussians
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.loops.detection import ClosedLoop
from pipeline.slam.process.frame_ring import FrameSlot
from pipeline.slam.process.shared_map import MapGeneration
from pipeline.slam.state import BackendState, LoopState


@dataclass(frozen=True)
class PackedBackendState:
    """A BackendState on the host with its keyframes stacked."""

    gaussians: Gaussians
    keyframe_indices: tuple[int, ...]
    keyframe_positions: tuple[int, ...]
    colors_u8: torch.Tensor  # [K, H, W, 3] uint8
    depths: torch.Tensor  # [K, H, W] metres
    c2w: torch.Tensor  # [K, 4, 4] camera-to-world
    scene_radius: float
    rng_state: tuple[Any, ...]
    generator_state: torch.Tensor
    frames_seen: int
    loops: LoopState | None  # on the host
    intrinsics: torch.Tensor | None  # [3, 3]

    @staticmethod
    def of(state: BackendState) -> PackedBackendState:
        keyframes = state.keyframes

        def stacked(name: str, empty: torch.Tensor) -> torch.Tensor:
            return torch.stack([getattr(k, name) for k in keyframes]) if keyframes else empty

        return PackedBackendState(
            state.gaussians,
            tuple(k.index for k in keyframes),
            tuple(k.position for k in keyframes),
            stacked("color_u8", torch.zeros(0, 0, 0, 3, dtype=torch.uint8)),
            stacked("depth", torch.zeros(0, 0, 0)),
            stacked("c2w", torch.zeros(0, 4, 4)),
            state.scene_radius,
            state.rng_state,
            state.generator_state,
            state.frames_seen,
            state.loops,
            state.intrinsics,
        )

    def unpacked(self) -> BackendState:
        keyframes = [
            Keyframe(index, self.colors_u8[i], self.depths[i], self.c2w[i], position)
            for i, (index, position) in enumerate(zip(self.keyframe_indices, self.keyframe_positions))
        ]
        return BackendState(
            self.gaussians, keyframes, self.scene_radius, self.rng_state, self.generator_state, self.frames_seen,
            self.loops, self.intrinsics,
        )  # fmt: skip


# Tracking side -> mapping side.


@dataclass(frozen=True)
class UseFrameRing:
    slots: tuple[FrameSlot, ...]  # sent once, before the first frame


@dataclass(frozen=True)
class MapFrame:
    """A tracked frame waits in the ring's `slot`."""

    slot: int
    index: int
    position: int  # among the run's poses
    timestamp: float
    is_last: bool  # the last frame of a dataset: kept as a keyframe
    keyframe: bool = False  # chosen as a keyframe by the tracking side (mapping.rate=keyframe)
    lost: bool = False  # judged lost by tracking: searched for a loop (loops on), never mapped


@dataclass(frozen=True)
class UseGeneration:
    generation: MapGeneration  # the answer to a GrowMap


@dataclass(frozen=True)
class SendState:
    request: int  # answered by a StateSent of the same number


@dataclass(frozen=True)
class RestoreState:
    state: PackedBackendState  # continue from it (answered by a Done)


@dataclass(frozen=True)
class StartAfresh:
    """After a warm-up: an empty map and keyframe store around the compiled kernels (a Done)."""


@dataclass(frozen=True)
class Finish:
    """Map the frames still waiting, then `final_renders` of refinement over every keyframe (a Done)."""

    final_renders: int


@dataclass(frozen=True)
class SampleKernels:
    """Start, stop or read ("read": answered by KernelsSampled) the recording of this process's kernels."""

    step: str


@dataclass(frozen=True)
class Shutdown:
    """End the process once everything before it is done."""


# Mapping side -> tracking side.


@dataclass(frozen=True)
class GrowMap:
    capacity: int  # Gaussians per slot needed
    keyframe_capacity: int


@dataclass(frozen=True)
class StateSent:
    request: int
    state: PackedBackendState | None  # None before the first frame
    version: int  # the map version the state belongs to


@dataclass(frozen=True)
class StartedUp:
    """The mapping process's start-up, sent once its loop is ready (monotonic-clock seconds)."""

    interpreter_s: float  # from the spawn to its target running: the interpreter and the imports
    setup_s: float  # from there to the loop ready: CUDA, the renderers, the backend


@dataclass(frozen=True)
class FrameMapped:
    """What mapping did with a frame handed to it."""

    index: int
    mapped: bool  # False: passed over (live: a newer frame was waiting), or lost (only searched for a loop)
    added: int  # Gaussians added by its densification
    densify_s: float
    mapping_s: float
    closed: tuple[ClosedLoop, ...] = ()  # loops closed at this frame (loops.enabled)


@dataclass(frozen=True)
class Refined:
    renders: int  # view renders of one refinement pass
    seconds: float


@dataclass(frozen=True)
class KernelsSampled:
    busy_ms: float  # the union of the mapping process's kernel intervals over the window


@dataclass(frozen=True)
class Done:
    """A RestoreState, StartAfresh or Finish is carried out."""

    renders: int = 0  # of a Finish: the final refinement's view renders


@dataclass(frozen=True)
class MappingFailed:
    error: str  # the exception and its traceback, as text
