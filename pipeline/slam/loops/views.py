"""What loop closure keeps of each keyframe, made once when the keyframe is kept: its global
descriptor (`candidates.descriptor`) and its image pyramid as an alignment target.

A target's coarse levels (1 and up) are kept for every keyframe: verification aligns to them
first and refuses most wrong candidates there, at a quarter of the pixels or fewer. The finest
level, three quarters of the pyramid's memory (at 640x480, 12 MB of a keyframe's 16), is kept
only for the newest two keyframes (the newest's odometry edge aligns to the one before); an old
keyframe's is made again for a candidate that passes its coarse levels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pipeline.slam.keyframes import Keyframe
from pipeline.slam.loops.candidates import descriptor
from pipeline.slam.tracking.align_tracker import target_pyramid
from pipeline.slam.tracking.rgbd_alignment import TargetMaps


@dataclass
class KeyframeView:
    """One keyframe as loop closure sees it."""

    descriptor: torch.Tensor  # [D] (`candidates.descriptor`)
    coarse: list[TargetMaps]  # its pyramid's levels 1 and up as an alignment target, finest first
    finest: TargetMaps | None  # level 0 (None: not kept, made again when needed)


def target_levels(keyframe: Keyframe, intrinsics: torch.Tensor, levels: int, min_silhouette: float) -> list[TargetMaps]:
    """A stored keyframe as an alignment target (its silhouette 1 where its depth is valid),
    `levels` pyramid levels, finest first."""
    silhouette = (keyframe.depth > 0).to(keyframe.depth.dtype)
    return target_pyramid(keyframe.color, keyframe.depth, intrinsics, silhouette, levels, min_silhouette)


class KeyframeViews:
    """The views of the stored keyframes, by their frame's position (stable while keyframes
    leave the store)."""

    def __init__(self, levels: int, min_silhouette: float) -> None:
        self.levels = levels  # pyramid levels of a verification (loops.verify_iters)
        self.min_silhouette = min_silhouette
        self._views: dict[int, KeyframeView] = {}

    def update(self, keyframes: list[Keyframe], intrinsics: torch.Tensor) -> None:
        """After a keyframe was kept (the newest of `keyframes`, the store oldest first): its view
        made; those of keyframes no longer stored forgotten; only the newest two keep their finest
        level (the newest's odometry edge aligns it to the one before)."""
        known, self._views = self._views, {}
        for keyframe in keyframes:
            position = keyframe.pose.position
            view = known.get(position)
            if view is None:
                levels = target_levels(keyframe, intrinsics, self.levels, self.min_silhouette)
                view = KeyframeView(descriptor(keyframe.color), levels[1:], levels[0])
            elif all(keyframe is not newer for newer in keyframes[-2:]):
                view.finest = None
            self._views[position] = view

    def descriptors(self, keyframes: list[Keyframe]) -> torch.Tensor:
        """[K, D]: the descriptors of `keyframes` (all stored, `update` done)."""
        return torch.stack([self._views[keyframe.pose.position].descriptor for keyframe in keyframes])

    def coarse(self, keyframe: Keyframe) -> list[TargetMaps]:
        """A stored keyframe's coarse target levels (1 and up), finest first."""
        return self._views[keyframe.pose.position].coarse

    def finest(self, keyframe: Keyframe, intrinsics: torch.Tensor) -> TargetMaps:
        """A stored keyframe's finest target level: kept for the newest, made again otherwise."""
        kept = self._views[keyframe.pose.position].finest
        return kept if kept is not None else target_levels(keyframe, intrinsics, 1, self.min_silhouette)[0]
