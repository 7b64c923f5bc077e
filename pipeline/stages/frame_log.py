"""What reached the end of the graph: every frame's result, when it arrived, and the counts
of lost, weak, relocalised and unmapped frames that metrics, status and the bar report."""

from __future__ import annotations

import logging
import time

import numpy as np

from pipeline.metrics import absolute_trajectory_error
from pipeline.slam.handoff import FrameResult

log = logging.getLogger("gsplatam")

FPS_WINDOW = 10  # frames over which the recent frames/s is measured


class FrameLog:
    """Every result in order with its arrival time (host clock, s); lost and weak frames are
    logged as they come (a run of weak frames once)."""

    def __init__(self) -> None:
        self.started_at = time.perf_counter()  # host clock (s): the pipeline starts taking frames
        self.results: list[FrameResult] = []
        self.arrivals: list[float] = []
        self.lost_frames = 0
        self.weak_frames = 0  # tracked with a warning (low map coverage, or relocalised), still mapped
        self.relocalised_frames = 0  # tracked after a loss from a keyframe's pose
        self.unmapped_frames = (
            0  # tracked but not mapped: lost, or skipped by a live session's mapping (not by design between keyframes)
        )
        self.between_keyframes = 0  # tracked only, by design (mapping.rate=keyframe)

    def add(self, result: FrameResult, arrived_at: float) -> None:
        previous = self.results[-1] if self.results else None
        self.results.append(result)
        self.arrivals.append(arrived_at)
        if result.lost:
            self.lost_frames += 1
            log.warning("frame %d: tracking lost: %s", result.index, result.lost)
        elif result.warning:
            self.weak_frames += 1
            if previous is None or not previous.warning:
                log.info("frame %d: tracking weak: %s", result.index, result.warning)
        self.relocalised_frames += result.relocalised_from is not None
        self.unmapped_frames += not result.mapped and not result.between_keyframes
        self.between_keyframes += result.between_keyframes
        if log.isEnabledFor(logging.DEBUG):  # per frame: the line is built only behind -v
            log.debug("frame %d: %s; tracker: %s", result.index, _stage_times(result), _verdict(result))

    @property
    def last(self) -> FrameResult | None:
        return self.results[-1] if self.results else None

    def recent_fps(self) -> float:
        """Frames per second over the last FPS_WINDOW arrivals."""
        recent = self.arrivals[-FPS_WINDOW:]
        return (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and recent[-1] > recent[0] else 0.0

    def seconds_since_last(self) -> float | None:
        return time.perf_counter() - self.arrivals[-1] if self.arrivals else None


def _stage_times(result: FrameResult) -> str:
    return ", ".join(f"{stage} {1000 * seconds:.1f} ms" for stage, seconds in result.seconds.items())


def _verdict(result: FrameResult) -> str:
    """The tracker's verdict on a frame, its loss and coverage, and what mapping did with it."""
    verdict = f"lost ({result.lost})" if result.lost else f"weak ({result.warning})" if result.warning else "ok"
    if result.relocalised_from is not None:
        verdict += f", relocalised from keyframe {result.relocalised_from}"
    mapped = f"mapped into version {result.map_version}" if result.mapped else "not mapped"
    if result.between_keyframes:
        mapped = "not a keyframe"
    return f"{verdict}, loss {result.tracking_loss:.4g}, coverage {result.coverage:.0%}; {mapped}, {result.gaussians:,} Gaussians"


def referenced_poses(results: list[FrameResult]) -> tuple[np.ndarray, np.ndarray] | None:
    """(estimated, reference) camera-to-world [N, 4, 4] float64 of the frames that came with a
    reference pose; None with fewer than 3."""
    pairs = [(r.c2w, r.c2w_gt) for r in results if r.c2w_gt is not None]
    if len(pairs) < 3:
        return None
    return np.stack([e.double().numpy() for e, _ in pairs]), np.stack([g.double().numpy() for _, g in pairs])


def ate_so_far_cm(results: list[FrameResult]) -> float | None:
    """ATE RMSE (cm, rigid alignment) of the frames that came with a reference pose; None with fewer than 3."""
    poses = referenced_poses(results)
    return None if poses is None else 100 * absolute_trajectory_error(*poses).rmse_m
