"""One line of frames.csv: what a frame cost and how tracking and mapping judged it."""

from __future__ import annotations

from dataclasses import dataclass, fields

from pipeline.slam.handoff import FrameResult


@dataclass(frozen=True)
class FrameRow:
    """The columns of frames.csv, in order (seconds; ages None where the frame is not live)."""

    index: int
    timestamp: float  # seconds
    tracking_s: float
    densify_s: float
    mapping_s: float
    total_s: float
    gaussians: int
    added: int
    tracking_loss: float
    coverage: float  # fraction of the valid-depth pixels tracking used
    lost: str  # why the pose is not trusted; empty when it is
    warning: str
    mapped: bool
    map_version: int
    age_at_start_s: float | None  # live: arrival to the start of tracking
    age_s: float | None  # live: arrival to the result

    @staticmethod
    def of(result: FrameResult) -> FrameRow:
        s = result.seconds
        return FrameRow(
            result.index, result.timestamp, s["tracking"], s["densify"], s["mapping"], s["total"],
            result.gaussians, result.added, result.tracking_loss, result.coverage, result.lost, result.warning,
            result.mapped, result.map_version, result.age_at_start_s, result.age_s,
        )  # fmt: skip

    def cells(self) -> list[str | int]:
        """The line's cells as frames.csv writes them."""
        return [
            self.index, f"{self.timestamp:.6f}", f"{self.tracking_s:.6f}", f"{self.densify_s:.6f}",
            f"{self.mapping_s:.6f}", f"{self.total_s:.6f}", self.gaussians, self.added, f"{self.tracking_loss:.6g}",
            f"{self.coverage:.4f}", self.lost, self.warning, int(self.mapped), self.map_version,
            _seconds(self.age_at_start_s), _seconds(self.age_s),
        ]  # fmt: skip


COLUMNS = tuple(item.name for item in fields(FrameRow))


def _seconds(value: float | None) -> str:
    return "" if value is None else f"{value:.4f}"
