"""The typed records of a run folder: metrics.json in one shape (read in any earlier one), the
run description a checkpoint keeps, and a frames.csv line."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from pipeline.io.outputs.frame_row import COLUMNS, EARLIER_WIDTH, FrameRow
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_metrics import AteRecord, ClosedLoopRow, LoopRecord, RunMetrics, TimingRecord
from pipeline.slam.handoff import FrameResult
from pipeline.slam.loops.detection import ClosedLoop, LoopDetection, LoopTally
from pipeline.slam.loops.pose_graph import MotionSize
from pipeline.slam.tracking.align_tracker import SolveReport

TIME = {"tracking_s": 0.01, "densify_s": 0.0, "mapping_s": 0.02, "total_s": 0.03, "frames_timed": 4,
        "warmup_frames_excluded": 2, "fps_wall": 30.0, "fps_steady": 33.0}  # fmt: skip


def test_metrics_round_trip_through_json() -> None:
    metrics = RunMetrics(
        "room", frames=6, gaussians=900, time=TimingRecord(**TIME), ate=AteRecord(0.5, 0.4, 0.3, 0.9, 6),
        evaluation="complete", counters={"received": 6}, runtime={"wall_s": 1.0},
    )  # fmt: skip
    assert RunMetrics.from_json(metrics.to_json()) == metrics and metrics.evaluation_complete


@pytest.mark.parametrize(
    "earlier, source, ate_cm, complete",
    [
        ({"dataset": "room", "ate": {"rmse_cm": 0.5, "mean_cm": 0.4}, "evaluation": "complete"}, "room", 0.5, True),
        ({"source": "record3d", "ate_rmse_cm": 1.5, "counters": {"received": 3}}, "record3d", 1.5, False),
        ({"dataset": "room", "ate": None, "render": {"psnr_db": 30.0, "ssim": 0.9, "depth_l1_cm": 1.0,
          "frames_evaluated": 2, "every": 5}}, "room", None, True),  # gsplatam 0.2: no `evaluation`
    ],
)  # fmt: skip
def test_metrics_of_earlier_versions_are_read(earlier: dict, source: str, ate_cm: float | None, complete: bool) -> None:
    metrics = RunMetrics.from_json({**earlier, "frames": 6, "time": TIME})
    assert metrics.source == source and metrics.frames == 6 and metrics.time == TimingRecord(**TIME)
    assert (metrics.ate.rmse_cm if metrics.ate else None) == ate_cm and metrics.evaluation_complete == complete
    assert metrics.loops is None  # written before loop closure


def _closed_loop(frame: int, matched: tuple[int, ...]) -> ClosedLoop:
    return ClosedLoop(frame, matched, MotionSize(0.025, 1.5), detect_s=0.04, correct_s=0.125, published_s=0.5)


def test_loop_closure_s_outcome_round_trips_through_json() -> None:
    tally = LoopTally(detected=8, verified=6, accepted=3, rejected=5, failed_verification=2, unconfirmed=1)
    loops = LoopRecord.of(tally, [_closed_loop(40, (3,)), _closed_loop(90, (5, 7))])
    metrics = RunMetrics("room", frames=100, loops=loops)
    table = json.loads(json.dumps(metrics.to_json()))
    assert table["loops"]["closed"][1]["matched_frames"] == [5, 7]
    assert RunMetrics.from_json(table) == metrics
    assert RunMetrics.from_json({**table, "loops": None}).loops is None
    with pytest.raises(ValueError, match="expected a list"):
        RunMetrics.from_json({**table, "loops": {**table["loops"], "closed": {"frame": 40}}})


def test_the_tally_keeps_the_longest_search_and_the_wait_before_searches_beside_the_total() -> None:
    nothing_found = LoopDetection(current=3, checks=())
    tally = LoopTally().counted(nothing_found, 0.05).counted(nothing_found, 16.0, 0.3).counted(nothing_found, 0.07)
    assert (tally.searches, tally.search_s, tally.search_max_s) == (3, pytest.approx(16.12), 16.0)
    assert tally.search_wait_s == pytest.approx(0.3)  # apart from the searches' own time
    record = LoopRecord.of(tally, [])
    assert record.search_max_ms == pytest.approx(16000.0) and record.search_wait_ms == pytest.approx(100.0)


def test_a_loop_record_is_the_tally_and_each_closed_loop_in_cm_degrees_and_ms() -> None:
    tally = LoopTally(detected=8, verified=6, accepted=3, rejected=5, failed_verification=2, unconfirmed=1,
                      dropped_by_graph=1, searches=4, search_s=0.2, search_max_s=0.11, search_wait_s=0.04)  # fmt: skip
    loops = LoopRecord.of(tally, [_closed_loop(40, (3, 11))])
    counts = {
        k: v
        for k, v in dataclasses.asdict(loops).items()
        if k not in ("closed", "search_ms", "search_max_ms", "search_wait_ms")
    }
    assert counts == {
        k: v for k, v in dataclasses.asdict(tally).items() if k not in ("search_s", "search_max_s", "search_wait_s")
    }
    assert loops.search_ms == pytest.approx(50.0)  # the mean per keyframe searched
    assert loops.search_max_ms == pytest.approx(110.0)
    assert LoopRecord.of(LoopTally(), []).search_ms is None
    (row,) = loops.closed
    assert row == ClosedLoopRow(40, [3, 11], correction_cm=2.5, correction_deg=1.5, detect_ms=40.0,
                                correct_ms=125.0, published_ms=500.0)  # fmt: skip


def test_the_run_description_keeps_what_it_records() -> None:
    dataset = RunDescription("room", False, "3d", True, "replica", (64, 48), 0, 1)
    assert dataset.to_json()["size"] == [64, 48] and RunDescription.from_json(dataset.to_json()) == dataset
    live = RunDescription("record3d", True, "3d", True)
    assert set(live.to_json()) == {"source", "live", "gaussians", "isotropic"}
    assert RunDescription.from_json({"source": "room", "unknown": 1}) == RunDescription("room")


def test_a_frame_row_has_one_cell_per_column() -> None:
    seconds = {"tracking": 0.01, "densify": 0.002, "mapping": 0.03, "total": 0.042}
    result = FrameResult(3, 0.1, torch.eye(4), seconds, 100, 5, 0.25, 0.9, warning="weak", age_s=0.05)
    row = FrameRow.of(result)
    assert len(row.cells()) == len(COLUMNS) == len(dataclasses.fields(FrameRow))
    cells = dict(zip(COLUMNS, row.cells()))
    assert row.cells()[:3] == [3, "0.100000", "0.010000"] and (cells["age_at_start_s"], cells["age_s"]) == (
        "",
        "0.0500",
    )
    assert cells["inlier_fraction"] == cells["renders"] == ""  # no alignment (adam, or the first frame)


def test_a_frame_row_holds_the_alignment_s_last_solve() -> None:
    """What tells a wrong step from a right one may be in the solve (bench/NOTES.md, #35): its
    inliers among the pixels on the map, residuals, conditioning, how far it moved, its renders."""
    seconds = {"tracking": 0.01, "densify": 0.0, "mapping": 0.0, "total": 0.01}
    solve = SolveReport(1000, 800, 600, 0.0125, 0.05, 2.5e-3, 0.031, 1.5, renders=2)
    cells = dict(
        zip(COLUMNS, FrameRow.of(FrameResult(3, 0.1, torch.eye(4), seconds, 100, 5, 0.25, 0.9, solve=solve)).cells())
    )
    solved = [cells[name] for name in COLUMNS[EARLIER_WIDTH:]]
    assert solved == ["0.7500", "1.2500", "0.0500", "2.500e-03", "3.100", "1.500", "2"]
