"""Summaries of a torch-profiler run: GPU busy time from the kernel timeline, per-stage GPU
time and the top kernels, so the next optimisation is chosen from data."""

from __future__ import annotations

from typing import Any

from torch.autograd import DeviceType
from torch.profiler import profile

STAGES = ("decode", "upload", "slam_step", "tracking", "densify", "mapping")
ANNOTATIONS = (*STAGES, "total")  # record_function ranges, which also appear on the device timeline


def all_threads_config() -> Any:
    """The profiler setting that records the stage threads too, not only the calling thread."""
    from torch._C._profiler import _ExperimentalConfig

    try:
        return _ExperimentalConfig(profile_all_threads=True)
    except TypeError:  # older torch: only the calling thread is recorded
        return None


def kernel_busy(prof: profile) -> dict[str, float]:
    """Union of kernel intervals on the device over the span from the first kernel to the last."""
    spans = sorted(
        (e.time_range.start, e.time_range.end)
        for e in prof.events()
        if e.device_type == DeviceType.CUDA and e.time_range.end > e.time_range.start
    )
    if not spans:
        return {"kernel_busy_fraction": float("nan"), "kernel_wall_ms": 0.0}
    busy, (current_start, current_end) = 0.0, spans[0]
    for start, end in spans[1:]:
        if start > current_end:
            busy += current_end - current_start
            current_start, current_end = start, end
        else:
            current_end = max(current_end, end)
    busy += current_end - current_start
    wall = spans[-1][1] - spans[0][0]
    return {"kernel_busy_fraction": busy / wall, "kernel_wall_ms": wall / 1000.0, "kernel_busy_ms": busy / 1000.0}


def stage_times(prof: profile) -> dict[str, dict[str, float]]:
    """Host and device time inside each named range (record_function) of the pipeline."""
    rows = {}
    for avg in prof.key_averages():
        if avg.key in STAGES:
            rows[avg.key] = {
                "count": avg.count,
                "cpu_ms": avg.cpu_time_total / 1000.0,
                "device_ms": avg.device_time_total / 1000.0,
            }
    return rows


def summarise(prof: profile, cuda: bool) -> tuple[dict[str, Any], str]:
    summary: dict[str, Any] = {"stages": stage_times(prof)}
    if cuda:
        summary.update(kernel_busy(prof))
    sort_key = "device_time_total" if cuda else "cpu_time_total"
    table = prof.key_averages().table(sort_by=sort_key, row_limit=25)
    return summary, table
