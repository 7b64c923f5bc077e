"""Sinks: consume per-frame results off the hot path (files, progress, log)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from tqdm import tqdm

from pipeline.metrics import absolute_trajectory_error
from pipeline.slam.results import FrameResult
from pipeline.stages.queues import EndOfStream, StageQueue

log = logging.getLogger("gsplatam")


def frame_row(result: FrameResult) -> dict[str, Any]:
    s = result.seconds
    return {
        "index": result.index,
        "timestamp": f"{result.timestamp:.6f}",
        "tracking_s": f"{s['tracking']:.6f}",
        "densify_s": f"{s['densify']:.6f}",
        "mapping_s": f"{s['mapping']:.6f}",
        "total_s": f"{s['total']:.6f}",
        "gaussians": result.gaussians,
        "added": result.added,
        "tracking_loss": f"{result.tracking_loss:.6g}",
        "coverage": f"{result.coverage:.4f}",
        "lost": result.lost,
        "warning": result.warning,
        "mapped": int(result.mapped),
        "map_version": result.map_version,
        "age_at_start_s": "" if result.age_at_start_s is None else f"{result.age_at_start_s:.4f}",
        "age_s": "" if result.age_s is None else f"{result.age_s:.4f}",
    }


RowWriter = Callable[[list[dict[str, Any]]], None]
WriteFailure = Callable[[str, OSError], None]  # (what could not be written, why)

FPS_WINDOW = 10  # frames over which the bar's frames/s is measured
ATE_EVERY_S = 1.0  # the bar's ATE so far is recomputed at most this often (all frames so far each time)


def ate_so_far_cm(results: list[FrameResult]) -> float | None:
    """ATE RMSE (cm, rigid alignment) of the frames that came with a reference pose; None with fewer than 3."""
    pairs = [(r.c2w, r.c2w_gt) for r in results if r.c2w_gt is not None]
    if len(pairs) < 3:
        return None
    estimated = np.stack([e.double().numpy() for e, _ in pairs])
    reference = np.stack([g.double().numpy() for _, g in pairs])
    return 100 * absolute_trajectory_error(estimated, reference).rmse_m


def recent_fps(arrivals: list[float]) -> float:
    """Frames per second over the last FPS_WINDOW arrivals (host clock, seconds)."""
    recent = arrivals[-FPS_WINDOW:]
    return (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 and recent[-1] > recent[0] else 0.0


class ResultSink:
    """Keeps every frame's result, hands its row to `write_rows` (the run folder's frames.csv)
    and advances the progress bar: frames/s, Gaussians, lost frames, the ATE so far when the
    frames bring a reference pose, and what `show` adds (a live daemon's counters). A row that cannot be written is reported to
    `on_write_error` and SLAM goes on (without one, the OSError ends the run)."""

    def __init__(
        self,
        write_rows: RowWriter,
        total: int | None,
        initial: int = 0,
        progress: bool = True,
        on_write_error: WriteFailure | None = None,
    ) -> None:
        self.write_rows = write_rows
        self.on_write_error = on_write_error
        self.results: list[FrameResult] = []
        self.arrivals: list[float] = []  # host clock (s) at which each result reached the sink
        self.lost_frames = 0
        self.weak_frames = 0  # tracked with a warning (low map coverage, or relocalised), still mapped
        self.relocalised_frames = 0  # tracked after a loss from a keyframe's pose
        self.unmapped_frames = 0  # tracked but not mapped: lost, or skipped by a live session's mapping
        self.bar = tqdm(
            total=total, initial=initial, unit="frame", desc="SLAM", disable=not progress, dynamic_ncols=True
        )
        self._extra: dict[str, Any] = {}
        self._ate_cm: float | None = None
        self._ate_at = -float("inf")

    def consume(self, result: FrameResult) -> None:
        now = time.perf_counter()
        self.arrivals.append(now)
        if result.received_at is not None:
            result.age_s = now - result.received_at
        self.results.append(result)
        try:
            self.write_rows([frame_row(result)])
        except OSError as exc:
            if self.on_write_error is None:
                raise
            self.on_write_error(f"the row of frame {result.index} in frames.csv", exc)
        if result.lost:
            self.lost_frames += 1
            log.warning("frame %d: tracking lost: %s", result.index, result.lost)
        elif result.warning:
            self.weak_frames += 1
            previous = self.results[-2] if len(self.results) > 1 else None
            if previous is None or not previous.warning:  # said once per run of weak frames
                log.info("frame %d: tracking weak: %s", result.index, result.warning)
        self.relocalised_frames += result.relocalised_from is not None
        self.unmapped_frames += not result.mapped
        due = self._ate_cm is None or self.arrivals[-1] - self._ate_at >= ATE_EVERY_S
        if result.c2w_gt is not None and not self.bar.disable and due:
            self._ate_at = self.arrivals[-1]
            self._ate_cm = ate_so_far_cm(self.results)
        self._set_postfix(refresh=False)
        self.bar.update(1)  # redraws (at most tqdm's mininterval apart)

    def show(self, fields: dict[str, Any]) -> None:
        """Add `fields` to the bar (kept until replaced)."""
        self._extra = fields
        self._set_postfix(refresh=True)

    def _set_postfix(self, refresh: bool) -> None:
        last = self.results[-1] if self.results else None
        fps = recent_fps(self.arrivals)
        fields: dict[str, Any] = {"fps": f"{fps:.1f}" if fps >= 1 else f"{fps:.2f}"}
        if last is not None:
            fields.update(gaussians=f"{last.gaussians:,}", lost=self.lost_frames)
        if self._ate_cm is not None:
            fields["ate"] = f"{self._ate_cm:.2f}cm"
        self.bar.set_postfix(fields | self._extra, refresh=refresh)

    async def drain(self, inbox: StageQueue[FrameResult]) -> None:
        while not isinstance(result := await inbox.get(), EndOfStream):
            self.consume(result)

    def close(self) -> None:
        self.bar.close()
