"""What SLAM's two sides hand each other, and what SLAM reports per frame.

The tracking side hands each frame to the mapping side as a `TrackedFrame` (in one process as it
is; the process schedule sends it through its frame ring); `FrameResult` is what both sides fill
in for the outside world (frames.csv, the status endpoint, metrics)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from pipeline.frame import DeviceFrame

if TYPE_CHECKING:  # (the tracker's module, not loaded by those that only pass results on)
    from pipeline.slam.tracking.align_tracker import SolveReport


@dataclass
class FrameResult:
    index: int
    timestamp: float
    c2w: torch.Tensor  # [4, 4] estimated camera-to-world, on the host
    seconds: dict[str, float]  # tracking, densify (with keyframe selection), mapping, total (their sum)
    gaussians: int  # in the map after this frame's mapping (or the latest map, when not mapped)
    added: int
    tracking_loss: float  # per tracked pixel at the chosen pose (adam: its loss; align: squared point-to-plane, m^2)
    coverage: float  # fraction of valid-depth pixels used by tracking
    lost: str = ""  # why the pose is not to be trusted (the frame is then not mapped); empty when it is
    c2w_gt: torch.Tensor | None = None  # [4, 4] the frame's reference camera-to-world, on the host
    warning: str = ""  # why tracking looked weak though its pose is used and mapped (low map coverage)
    relocalised_from: int | None = None  # after a loss: the keyframe (frame index) whose pose tracking held from
    mapped: bool = True  # False: tracked only (lost, skipped by a live session's mapping, or not a keyframe)
    between_keyframes: bool = False  # mapping.rate=keyframe: not a keyframe, tracked only by design
    map_version: int = 0  # the map version published after this frame (the latest one when not mapped)
    received_at: float | None = None  # live: host clock (time.perf_counter, s) at the frame's arrival
    age_at_start_s: float | None = None  # live: seconds from the frame's arrival to the start of its tracking
    age_s: float | None = None  # live: seconds from the frame's arrival to its result (set by the sink)
    solve: SolveReport | None = None  # align: the statistics of the solve whose pose was taken


@dataclass(frozen=True)
class TrackedFrame:
    """What tracking hands to mapping: a frame and its pose."""

    frame: DeviceFrame
    c2w: torch.Tensor  # [4, 4] estimated camera-to-world, on the device
    position: int  # the frame's position among the run's poses
    ready: torch.cuda.Event | None = None  # recorded after tracking on its stream; None on the CPU
    keyframe: bool = False  # tracking chose it as a keyframe (mapping.rate=keyframe); else mapping's cadence says
    lost: bool = False  # tracking judged it lost: never mapped, only searched for a loop (loops on)
