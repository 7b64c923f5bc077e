"""Sinks: consume per-frame results off the hot path (files, progress, log)."""

from __future__ import annotations

import logging
import time
from typing import Any

from tqdm import tqdm

from pipeline.io.run_folder import RunFolder
from pipeline.slam.splatam import FrameResult
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
    }


class ResultSink:
    """Keeps every frame's result, appends it to frames.csv and advances the progress bar."""

    def __init__(self, folder: RunFolder, total: int | None, initial: int = 0, progress: bool = True) -> None:
        self.folder = folder
        self.results: list[FrameResult] = []
        self.arrivals: list[float] = []  # host clock (s) at which each result reached the sink
        self.lost_frames = 0
        self.bar = tqdm(
            total=total, initial=initial, unit="frame", desc="SLAM", disable=not progress, dynamic_ncols=True
        )

    def consume(self, result: FrameResult) -> None:
        self.arrivals.append(time.perf_counter())
        self.results.append(result)
        self.folder.append_frames([frame_row(result)])
        if result.lost:
            self.lost_frames += 1
            log.warning("frame %d: tracking lost: %s", result.index, result.lost)
        self.bar.set_postfix(gaussians=result.gaussians, ms=f"{1000 * result.seconds['total']:.0f}", refresh=False)
        self.bar.update(1)

    async def drain(self, inbox: StageQueue[FrameResult]) -> None:
        while not isinstance(result := await inbox.get(), EndOfStream):
            self.consume(result)

    def close(self) -> None:
        self.bar.close()
