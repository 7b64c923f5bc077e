"""Sinks: consume per-frame results off the hot path (files, progress, log)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from tqdm import tqdm

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


RowWriter = Callable[[list[dict[str, Any]]], None]
WriteFailure = Callable[[str, OSError], None]  # (what could not be written, why)


class ResultSink:
    """Keeps every frame's result, hands its row to `write_rows` (the run folder's frames.csv)
    and advances the progress bar. A row that cannot be written is reported to `on_write_error`
    and SLAM goes on (without one, the OSError ends the run)."""

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
        self.bar = tqdm(
            total=total, initial=initial, unit="frame", desc="SLAM", disable=not progress, dynamic_ncols=True
        )

    def consume(self, result: FrameResult) -> None:
        self.arrivals.append(time.perf_counter())
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
        self.bar.set_postfix(gaussians=result.gaussians, ms=f"{1000 * result.seconds['total']:.0f}", refresh=False)
        self.bar.update(1)

    async def drain(self, inbox: StageQueue[FrameResult]) -> None:
        while not isinstance(result := await inbox.get(), EndOfStream):
            self.consume(result)

    def close(self) -> None:
        self.bar.close()
