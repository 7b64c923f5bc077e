"""metrics.json: one typed record for every run, from a dataset or live, and its reading.

Written by `RunFolder.write_metrics` only. `RunMetrics.from_json` also reads the files of
earlier versions that a `--resume` meets: a run's (`dataset`, `ate` as a table), a daemon's
(`source`, `ate_rmse_cm`) and those of gsplatam 0.2 (no `evaluation`). One without `loops` (a
version before loop closure, or loops.enabled off) reads as `loops` None.
"""

from __future__ import annotations

import typing
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from pipeline.metrics import absolute_trajectory_error, step_errors
from pipeline.slam.handoff import FrameResult

if TYPE_CHECKING:  # loop_closure brings the alignment with it: not imported to read a metrics.json
    from _typeshed import DataclassInstance

    from pipeline.slam.loops.detection import ClosedLoop, LoopTally

RIGID = "rigid (rotation + translation, no scale), least squares over camera centres"
Record = TypeVar("Record", bound="DataclassInstance")


@dataclass(frozen=True)
class AteRecord:
    """Absolute trajectory error of the camera centres after a rigid alignment, centimetres."""

    rmse_cm: float
    mean_cm: float | None = None  # None: not recorded (a daemon's metrics of an earlier version)
    median_cm: float | None = None
    max_cm: float | None = None
    frames: int | None = None
    alignment: str = RIGID

    @staticmethod
    def between(estimated: np.ndarray, reference: np.ndarray) -> AteRecord:
        """Of camera-to-world poses [N, 4, 4] against their references [N, 4, 4]."""
        ate = absolute_trajectory_error(estimated, reference)
        return AteRecord(100 * ate.rmse_m, 100 * ate.mean_m, 100 * ate.median_m, 100 * ate.max_m, ate.frames)


@dataclass(frozen=True)
class StepRecord:
    """The frame-to-frame motion's error over the reference's large steps (`metrics.step_errors`), centimetres."""

    steps: int  # consecutive frames further apart than min_step_cm in the reference
    mean_cm: float
    median_cm: float
    max_cm: float
    min_step_cm: float

    @staticmethod
    def between(estimated: np.ndarray, reference: np.ndarray) -> StepRecord:
        """Of camera-to-world poses [N, 4, 4] against their references [N, 4, 4]."""
        error = step_errors(estimated, reference)
        return StepRecord(
            error.steps, 100 * error.mean_m, 100 * error.median_m, 100 * error.max_m, 100 * error.min_step_m
        )


@dataclass(frozen=True)
class RenderRecord:
    """The final map rendered at the estimated poses against the input, means over the frames evaluated."""

    psnr_db: float
    ssim: float
    depth_l1_cm: float
    frames_evaluated: int
    every: int  # run.eval_every
    pixels: str = "valid-depth pixels only"
    keyframes_psnr_db: float | None = None  # the map at every keyframe's pose against its stored (8-bit) colour
    keyframes: int = 0
    depth_rmse_cm: float | None = None  # root mean square of the depth error (None: a version before it)


@dataclass(frozen=True)
class TimingRecord:
    """Mean seconds per frame and stage after the warm-up frames, and frames per second."""

    tracking_s: float
    densify_s: float
    mapping_s: float
    total_s: float
    frames_timed: int
    warmup_frames_excluded: int
    fps_wall: float  # frames over the whole run's wall time
    fps_steady: float | None  # after the warm-up frames; None with too few frames
    first_result_s: float | None = None  # from the pipeline's start to the first frame's result
    warmup_s: float | None = None  # from the pipeline's start to the last warm-up frame's result (compiles, graphs)
    warmup_stages_s: dict[str, float] | None = None  # tracking, densify, mapping: summed over the warm-up frames
    compile_s: float | None = None  # torch.compile's own compile time in this process during the run (tracing included)


@dataclass(frozen=True)
class FrameAges:
    """Median and 95th percentile of live frames' ages, milliseconds: from arrival to the start
    of SLAM, and to the result; None without live frames."""

    start_p50: float | None = None
    start_p95: float | None = None
    result_p50: float | None = None
    result_p95: float | None = None

    @staticmethod
    def of(results: list[FrameResult]) -> FrameAges:
        start = _percentiles([r.age_at_start_s for r in results if r.age_at_start_s is not None])
        done = _percentiles([r.age_s for r in results if r.age_s is not None])
        return FrameAges(*start, *done)


def _percentiles(ages_s: list[float]) -> tuple[float | None, float | None]:
    if not ages_s:
        return None, None
    p50, p95 = np.percentile(np.array(ages_s) * 1000.0, [50, 95])
    return float(p50), float(p95)


@dataclass(frozen=True)
class StopRecord:
    """Where and why a run stopped on an error, and how many frames its last save holds."""

    stage: str
    frame: int | None
    reason: str
    frames_saved: int


@dataclass(frozen=True)
class ClosedLoopRow:
    """One loop closed: at which keyframe, to which old ones, how far it moved the keyframe poses
    (the largest correction) and how long it took, milliseconds."""

    frame: int  # the current keyframe's frame index
    matched_frames: list[int]  # the old keyframes whose loop edges the pose graph kept
    correction_cm: float
    correction_deg: float
    detect_ms: float  # candidates and their verification
    correct_ms: float  # the pose graph's optimisation and moving the map
    published_ms: float  # from the detection's start to the corrected map published

    @staticmethod
    def of(loop: ClosedLoop) -> ClosedLoopRow:
        return ClosedLoopRow(
            frame=loop.frame,
            matched_frames=list(loop.matched),
            correction_cm=100 * loop.correction.translation_m,
            correction_deg=loop.correction.rotation_deg,
            detect_ms=1000 * loop.detect_s,
            correct_ms=1000 * loop.correct_s,
            published_ms=1000 * loop.published_s,
        )


@dataclass(frozen=True)
class LoopRecord:
    """Loop closure over a run: its candidates and their verdicts (`LoopTally`), and the loops closed."""

    detected: int = 0
    verified: int = 0
    accepted: int = 0  # kept by the pose graph
    rejected: int = 0
    failed_verification: int = 0
    unconfirmed: int = 0
    dropped_by_graph: int = 0
    searches: int = 0  # keyframes searched
    search_ms: float | None = None  # mean per keyframe searched (odometry alignment, candidates, verification)
    search_max_ms: float | None = None  # the longest search
    search_wait_ms: float | None = None  # mean per search: waiting for the device's queued work before it
    closed: list[ClosedLoopRow] = field(default_factory=list)

    @staticmethod
    def of(tally: LoopTally, closed: Sequence[ClosedLoop]) -> LoopRecord:
        return LoopRecord(
            detected=tally.detected,
            verified=tally.verified,
            accepted=tally.accepted,
            rejected=tally.rejected,
            failed_verification=tally.failed_verification,
            unconfirmed=tally.unconfirmed,
            dropped_by_graph=tally.dropped_by_graph,
            searches=tally.searches,
            search_ms=1000 * tally.search_s / tally.searches if tally.searches else None,
            search_max_ms=1000 * tally.search_max_s if tally.searches else None,
            search_wait_ms=1000 * tally.search_wait_s / tally.searches if tally.searches else None,
            closed=[ClosedLoopRow.of(loop) for loop in closed],
        )


@dataclass(frozen=True)
class RunMetrics:
    """What a run reports: sizes, counts, device, timing, the ATE where the frames bring
    reference poses and, for a dataset, the rendering quality and how complete its evaluation is."""

    source: str  # the dataset's or the live source's name
    live: bool = False
    preset: str = ""
    schedule: str = ""
    mapping_process: dict[str, Any] | None = None  # the process schedule: what the mapping process did
    frames: int = 0  # in the map, earlier runs of a resumed folder included
    frames_this_run: int = 0
    gaussians: int = 0
    lost_frames: int = 0
    weak_frames: int = 0  # tracked with a warning, still mapped
    relocalised_frames: int = 0
    unmapped_frames: int = 0
    between_keyframes: int = 0  # tracked only, by design (mapping.rate=keyframe)
    device: str = ""
    versions: dict[str, str | None] = field(default_factory=dict)
    peak_gpu_memory_gb: float | None = None  # None on the CPU
    counters: dict[str, Any] = field(default_factory=dict)  # the source's (SourceCounters)
    frame_age_ms: FrameAges = FrameAges()
    runtime: dict[str, Any] = field(default_factory=dict)  # RuntimeReport.summary()
    time: TimingRecord | None = None
    ate: AteRecord | None = None
    ate_as_tracked: AteRecord | None = None  # with loop closure: of the poses before its corrections
    large_steps: StepRecord | None = None  # the motion's error over the reference's steps beyond 3 cm
    render: RenderRecord | None = None
    render_before_final_iters: RenderRecord | None = None  # before mapping.final_iters (None without it)
    evaluation: str | None = None  # "complete", or why not; None: live (no evaluation)
    interrupted: bool = False
    stopped: StopRecord | None = None
    write_error: str | None = None  # a write that failed while SLAM went on (a frames.csv line)
    loops: LoopRecord | None = None  # loop closure (loops.enabled): candidates, verdicts, loops closed

    @property
    def evaluation_complete(self) -> bool:
        return self.evaluation == "complete"

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_json(table: dict[str, Any]) -> RunMetrics:
        """metrics.json as any version wrote it; ValueError or TypeError when it is none."""
        table = dict(table)
        if "dataset" in table:  # a run's, before runs and daemons shared one shape
            table.setdefault("source", table.pop("dataset"))
        if table.get("ate_rmse_cm") is not None:  # a daemon's, likewise
            table.setdefault("ate", {"rmse_cm": table["ate_rmse_cm"]})
        if "evaluation" not in table:  # gsplatam 0.2: complete where it holds render metrics
            table["evaluation"] = "complete" if table.get("render") else "skipped"
        return _record(RunMetrics, table)


def _record(kind: type[Record], table: Any) -> Record:
    """`kind` (a dataclass) from its JSON table: known keys, nested records recursively, defaults for the rest."""
    if not isinstance(table, dict):
        raise ValueError(f"expected a table for {kind.__name__}, found {type(table).__name__}")
    hints = typing.get_type_hints(kind)
    values = {item.name: _value(hints[item.name], table[item.name]) for item in fields(kind) if item.name in table}
    return kind(**values)


def _value(hint: Any, raw: Any) -> Any:
    """`raw` as `hint` reads it: a nested record, a list of them (or of plain values), or itself."""
    if typing.get_origin(hint) is list and raw is not None:
        if not isinstance(raw, list):
            raise ValueError(f"expected a list for {hint}, found {type(raw).__name__}")
        (item,) = typing.get_args(hint)
        return [_value(item, entry) for entry in raw]
    record = next((t for t in (hint, *typing.get_args(hint)) if isinstance(t, type) and is_dataclass(t)), None)
    return raw if record is None or raw is None else _record(record, raw)
