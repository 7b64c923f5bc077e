"""What observers of SLAM (periodic saves, viewers, recorders) may read at a frame boundary, and
what the SLAM stage and the commands use of a SLAM schedule."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import torch

from pipeline.config import Config
from pipeline.frame import DeviceFrame
from pipeline.render import Renderer
from pipeline.render.types import Gaussians
from pipeline.slam.handoff import FrameResult
from pipeline.slam.state import Checkpoint
from pipeline.slam.tracking.frontend import TrackingFrontend


class PublishedSlam(Protocol):
    """The state a SLAM schedule publishes; `SlamView` shows it to observers."""

    @property
    def frames_done(self) -> int: ...

    @property
    def gaussians(self) -> Gaussians | None: ...

    @property
    def poses(self) -> list[torch.Tensor]: ...

    def checkpoint(self) -> Checkpoint: ...


class SlamView:
    """A read-only view of a published SLAM state: observers see the frames done, the latest map
    version, the poses and a checkpoint on request, never the object that runs SLAM (which may
    live in another thread or, in part, another process)."""

    __slots__ = ("_slam",)

    def __init__(self, slam: PublishedSlam) -> None:
        self._slam = slam

    @property
    def frames_done(self) -> int:
        """Frames the published state holds (those mapping has passed)."""
        return self._slam.frames_done

    @property
    def gaussians(self) -> Gaussians | None:
        """The latest published map (None before the first frame); never modified once published."""
        return self._slam.gaussians

    @property
    def poses(self) -> list[torch.Tensor]:
        """[4, 4] camera-to-world per frame done."""
        return self._slam.poses

    def checkpoint(self) -> Checkpoint:
        """A host copy of everything needed to continue the run from here."""
        return self._slam.checkpoint()


class SteppedSlam(PublishedSlam, Protocol):
    """What the SLAM stage and the commands use of a SLAM schedule that takes one frame at a
    time: SplaTAM (tracking and mapping in this process) or ProcessSplaTAM (mapping in its own)."""

    config: Config
    renderer: Renderer
    device: torch.device
    frontend: TrackingFrontend

    def step(self, frame: DeviceFrame, is_last: bool = False) -> FrameResult: ...

    def warm_up(self, frame: DeviceFrame) -> None: ...

    def restore(self, saved: Checkpoint) -> None: ...

    def finish(self, final_renders: int, should_stop: Callable[[], bool] | None = None) -> int: ...

    @property
    def failure(self) -> str:
        """Why a part of SLAM running elsewhere failed; empty while it works."""
        ...

    def unmapped(self) -> list[int]:
        """The frames tracked and handed to mapping that the map lacks (mapping failed first)."""
        ...

    def stop_waiting(self) -> None:
        """Wait no more for a part of SLAM running elsewhere (a second signal); safe in a
        signal handler."""
        ...

    def mapping_summary(self) -> dict[str, Any] | None: ...

    def sample_kernels(self, step: str) -> float: ...

    def close(self) -> None: ...
