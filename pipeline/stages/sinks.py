"""Sinks: consume per-frame results off the hot path (files, progress, log)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from tqdm import tqdm

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


class ResultSink:
    """Keeps every frame's result, hands its row to `write_rows` (the run folder's frames.csv)
    and advances the progress bar."""

    def __init__(self, write_rows: RowWriter, total: int | None, initial: int = 0, progress: bool = True) -> None:
        self.write_rows = write_rows
        self.results: list[FrameResult] = []
        self.arrivals: list[float] = []  # host clock (s) at which each result reached the sink
        self.lost_frames = 0
        self.weak_frames = 0  # tracked with a warning (low map coverage), still mapped
        self.unmapped_frames = 0  # tracked but not mapped: lost, or skipped by a live session's mapping
        self.bar = tqdm(
            total=total, initial=initial, unit="frame", desc="SLAM", disable=not progress, dynamic_ncols=True
        )

    def consume(self, result: FrameResult) -> None:
        now = time.perf_counter()
        self.arrivals.append(now)
        if result.received_at is not None:
            result.age_s = now - result.received_at
        self.results.append(result)
        self.write_rows([frame_row(result)])
        if result.lost:
            self.lost_frames += 1
            log.warning("frame %d: tracking lost: %s", result.index, result.lost)
        elif result.warning:
            self.weak_frames += 1
            previous = self.results[-2] if len(self.results) > 1 else None
            if previous is None or not previous.warning:  # said once per run of weak frames
                log.info("frame %d: tracking weak: %s", result.index, result.warning)
        self.unmapped_frames += not result.mapped
        self.bar.set_postfix(gaussians=result.gaussians, ms=f"{1000 * result.seconds['total']:.0f}", refresh=False)
        self.bar.update(1)

    async def drain(self, inbox: StageQueue[FrameResult]) -> None:
        while not isinstance(result := await inbox.get(), EndOfStream):
            self.consume(result)

    def close(self) -> None:
        self.bar.close()
