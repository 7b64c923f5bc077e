"""The progress bar of a run: frames/s, Gaussians, lost frames, the ATE so far when the frames
bring a reference pose, and what a live daemon adds (its counters)."""

from __future__ import annotations

from typing import Any

from tqdm import tqdm

from pipeline.slam.handoff import FrameResult
from pipeline.stages.frame_log import FrameLog, ate_so_far_cm

ATE_EVERY_S = 1.0  # the ATE so far is recomputed at most this often (over all frames so far each time)


class ProgressBar:
    """A result consumer (after `log` has the result) that advances a tqdm bar over `total`
    frames (None: unknown), starting at `initial` (a resumed run's); `enabled` False draws nothing."""

    def __init__(self, log: FrameLog, total: int | None, initial: int = 0, enabled: bool = True) -> None:
        self.log = log
        self.bar = tqdm(
            total=total, initial=initial, unit="frame", desc="SLAM", disable=not enabled, dynamic_ncols=True
        )
        self._extra: dict[str, Any] = {}
        self._ate_cm: float | None = None
        self._ate_at = -float("inf")

    def __call__(self, result: FrameResult) -> None:
        arrived = self.log.arrivals[-1]
        due = self._ate_cm is None or arrived - self._ate_at >= ATE_EVERY_S
        if result.c2w_gt is not None and not self.bar.disable and due:
            self._ate_at = arrived
            self._ate_cm = ate_so_far_cm(self.log.results)
        self._set_postfix(refresh=False)
        self.bar.update(1)  # redraws (at most tqdm's mininterval apart)

    def show(self, fields: dict[str, Any]) -> None:
        """Add `fields` to the bar (kept until replaced)."""
        self._extra = fields
        self._set_postfix(refresh=True)

    def _set_postfix(self, refresh: bool) -> None:
        last, fps = self.log.last, self.log.recent_fps()
        fields: dict[str, Any] = {"fps": f"{fps:.1f}" if fps >= 1 else f"{fps:.2f}"}
        if last is not None:
            fields.update(gaussians=f"{last.gaussians:,}", lost=self.log.lost_frames)
        if self._ate_cm is not None:
            fields["ate"] = f"{self._ate_cm:.2f}cm"
        self.bar.set_postfix(fields | self._extra, refresh=refresh)

    def close(self) -> None:
        self.bar.close()
