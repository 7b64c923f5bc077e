"""One line of frames.csv: what a frame cost and how tracking and mapping judged it."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

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
    # align's last solve (None with adam and on the first frame): which fit a wrong step, and how
    inlier_fraction: float | None = None  # of the frame's pixels on the map, those within the depth gate
    residual_cm: float | None = None  # RMS point-to-plane residual of the inliers
    intensity_rms: float | None = None  # RMS intensity residual of the inliers (intensities in [0, 1])
    conditioning: float | None = None  # smallest / largest eigenvalue of the scaled normal equations
    moved_cm: float | None = None  # how far the solve moved the camera from the pose the map was rendered at
    moved_deg: float | None = None  # and turned it, degrees
    renders: int | None = None  # renders of the map the frame took

    @staticmethod
    def of(result: FrameResult) -> FrameRow:
        s, solve = result.seconds, result.solve
        row = FrameRow(
            result.index, result.timestamp, s["tracking"], s["densify"], s["mapping"], s["total"],
            result.gaussians, result.added, result.tracking_loss, result.coverage, result.lost, result.warning,
            result.mapped, result.map_version, result.age_at_start_s, result.age_s,
        )  # fmt: skip
        if solve is None:
            return row
        return replace(
            row, inlier_fraction=solve.inliers / max(solve.associated, 1), residual_cm=100 * solve.rms_m,
            intensity_rms=solve.rms_intensity, conditioning=solve.conditioning, moved_cm=100 * solve.moved_m,
            moved_deg=solve.moved_deg, renders=solve.renders,
        )  # fmt: skip

    def cells(self) -> list[str | int]:
        """The line's cells as frames.csv writes them."""
        return [
            self.index, f"{self.timestamp:.6f}", f"{self.tracking_s:.6f}", f"{self.densify_s:.6f}",
            f"{self.mapping_s:.6f}", f"{self.total_s:.6f}", self.gaussians, self.added, f"{self.tracking_loss:.6g}",
            f"{self.coverage:.4f}", self.lost, self.warning, int(self.mapped), self.map_version,
            _cell(self.age_at_start_s, ".4f"), _cell(self.age_s, ".4f"), _cell(self.inlier_fraction, ".4f"),
            _cell(self.residual_cm, ".4f"), _cell(self.intensity_rms, ".4f"), _cell(self.conditioning, ".3e"),
            _cell(self.moved_cm, ".3f"), _cell(self.moved_deg, ".3f"), _cell(self.renders, "d"),
        ]  # fmt: skip


COLUMNS = tuple(item.name for item in fields(FrameRow))
EARLIER_WIDTH = COLUMNS.index("inlier_fraction")  # a line written before the solve's columns (gsplatam <= da7c30a)


def _cell(value: float | None, spec: str) -> str:
    return "" if value is None else format(value, spec)
