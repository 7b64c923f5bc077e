"""Summaries of a torch-profiler run: GPU busy time from the kernel timeline, per-stage GPU
time and the top kernels, so the next optimisation is chosen from data."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from torch.autograd import DeviceType
from torch.autograd.profiler_util import EventList, FunctionEventAvg
from torch.profiler import profile

STAGES = ("decode", "upload", "slam_step", "tracking_stage", "mapping_stage", "tracking", "densify", "mapping")


def all_threads_config() -> Any:
    """The profiler setting that records the stage threads too, not only the calling thread."""
    from torch._C._profiler import _ExperimentalConfig

    try:
        return _ExperimentalConfig(profile_all_threads=True)
    except TypeError:  # older torch: only the calling thread is recorded
        return None


def kernel_busy(averages: Iterable[FunctionEventAvg], wall_s: float) -> dict[str, float]:
    """Device time spent in kernels and copies (user-annotation ranges excluded, as in the
    profiler's own "Self CUDA time total") as a fraction of the run's wall time."""
    busy_us = sum(
        e.self_device_time_total for e in averages if e.device_type == DeviceType.CUDA and not e.is_user_annotation
    )
    return {
        "kernel_busy_ms": busy_us / 1000.0,
        "kernel_busy_fraction": busy_us / 1e6 / wall_s if wall_s > 0 else float("nan"),
    }


def stage_times(averages: Iterable[FunctionEventAvg]) -> dict[str, dict[str, float]]:
    """Host and device time inside each named range (record_function) of the pipeline.

    With CUDA a range appears twice in the averages, as its host span and as its span on the
    device (the other's time 0 in each); a stage's row takes the larger of each.
    """
    rows: dict[str, dict[str, float]] = {}
    for avg in averages:
        if avg.key in STAGES:
            row = rows.setdefault(avg.key, {"count": 0, "cpu_ms": 0.0, "device_ms": 0.0})
            row["count"] = max(row["count"], avg.count)
            row["cpu_ms"] = max(row["cpu_ms"], avg.cpu_time_total / 1000.0)
            row["device_ms"] = max(row["device_ms"], avg.device_time_total / 1000.0)
    return rows


def summarise(prof: profile, cuda: bool, wall_s: float) -> tuple[dict[str, Any], str]:
    """-> (stage times and GPU busy time, the top-ops tables). The averages are computed once:
    over a run's events that takes seconds (a 3-frame CPU run: ~3 s per call)."""
    averages: EventList = prof.key_averages()
    summary: dict[str, Any] = {"stages": stage_times(averages)}
    if cuda:
        summary.update(kernel_busy(averages, wall_s))
    if not cuda:
        return summary, averages.table(sort_by="cpu_time_total", row_limit=25)
    # On a GPU both views: the kernels that fill the device, and the host calls that keep it
    # waiting (the SLAM loop is host-bound; self CPU time names the Python/C++ overhead).
    device_table = averages.table(sort_by="device_time_total", row_limit=25)
    host_table = averages.table(sort_by="self_cpu_time_total", row_limit=30)
    return summary, f"{device_table}\nTop host time (self CPU):\n{host_table}"
