"""A published map: what tracking reads while mapping builds the next one.

Mapping never changes a published version's tensors: every mapping pass optimises fresh copies
(`gaussian_map.as_leaves`) and densification concatenates into new tensors, so a version stays
valid for as long as tracking holds it, and two are alive at once (the one tracking reads, the one
mapping writes): a double buffer without copies.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.render.types import Gaussians
from pipeline.slam.gaussian_map import PARAMETER_NAMES
from pipeline.slam.keyframes import KeyframePose


@dataclass(frozen=True)
class MapVersion:
    number: int  # increases by one with every mapped frame
    gaussians: Gaussians  # detached; never modified after publishing
    ready: torch.cuda.Event | None  # recorded on mapping's stream when the version was complete
    keyframes: tuple[KeyframePose, ...] = ()  # the keyframe store's poses as of this version, oldest first

    def for_current_stream(self) -> Gaussians:
        """The Gaussians, safe to use on the calling thread's CUDA stream: it waits (on the GPU,
        not the host) for mapping's work, and the allocator keeps the memory until this stream's
        work on it is done."""
        if self.ready is not None:
            stream = torch.cuda.current_stream()
            stream.wait_event(self.ready)
            for name in PARAMETER_NAMES:
                getattr(self.gaussians, name).record_stream(stream)
        return self.gaussians
