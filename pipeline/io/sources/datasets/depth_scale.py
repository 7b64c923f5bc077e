"""The depth scale checked before SLAM starts: a dataset's depth read at the wrong units per
metre gives a map at the wrong scale without any other sign (millimetre depth read at TUM's 5000
units per metre is a map at 1/5 scale)."""

from __future__ import annotations

import logging
import math

import numpy as np

from pipeline.config import DatasetConfig
from pipeline.errors import UserError
from pipeline.io.files.images import read_depth_image
from pipeline.io.sources.datasets.base import Dataset

log = logging.getLogger("gsplatam")

FIRST_FRAMES = 3  # frames whose depth is looked at
# A room-scale RGB-D camera's median depth (TUM fr1/xyz: 1.2 m, the generated room: 2.5 m). Outside
# it, at a scale the user did not set, a line names the convention that brings it inside.
TYPICAL_MEDIAN_M = (0.6, 8.0)
TYPICAL_M = 2.0
CONVENTIONS = {  # depth units per metre -> what they are
    1000.0: "millimetres (RealSense, Azure Kinect, ScanNet, 7-Scenes)",
    5000.0: "TUM RGB-D's units (0.2 mm)",
    6553.5: "Replica's units (NICE-SLAM's renders)",
}


IMAGE_LAYOUTS = ("tum", "replica")  # folders of depth images, read at dataset.depth_scale


def check_depth_scale(dataset: Dataset, config: DatasetConfig) -> None:
    """Read the depth of the first frames and log its median (debug); UserError where that
    median lies outside `config.depth_range_m`, a warning where the scale is the layout's default
    (not set) and another usual one gives a more usual median. Float depth images are metres, and
    a bag's depth comes in its messages' own units: no scale applies to them."""
    median, where = _median_depth(dataset, config)
    if median is None:
        return  # no valid depth: the first frame's decoding names it
    found = f"the first {min(FIRST_FRAMES, len(dataset))} frames' depth has a median of {median:.3g} m at {where}"
    log.debug("depth: %s", found)
    scaled = where.startswith("dataset.depth_scale")
    advice = _advice(median, dataset.depth_scale) if scaled else ""
    if config.depth_range_m:
        near, far = config.depth_range_m
        if not near <= median <= far:
            fix = advice or "set dataset.depth_scale to the depth images' units per metre"
            raise UserError(f"{found}, outside dataset.depth_range_m ({near:g} to {far:g} m): {fix}")
    low, high = TYPICAL_MEDIAN_M
    if advice and not config.depth_scale and not low <= median <= high:
        log.warning("depth: %s, unusual for an RGB-D camera: %s", found, advice)


def _median_depth(dataset: Dataset, config: DatasetConfig) -> tuple[float | None, str]:
    """-> (the median of the first frames' valid depth in metres, None without any; what it was
    read at)."""
    first = dataset.refs[:FIRST_FRAMES]
    if dataset.format not in IMAGE_LAYOUTS:  # a bag: decoded in its own units
        depths = [dataset.decode(ref).depth for ref in first]
        where = f"the {dataset.format}'s own depth units"
    else:
        raw = [read_depth_image(ref.depth_path) for ref in first]
        floats = any(image.dtype == np.float32 for image in raw)
        depths = [image if floats else image.astype(np.float32) / np.float32(dataset.depth_scale) for image in raw]
        origin = "set" if config.depth_scale else f"{dataset.format}'s default"
        where = (
            "float depth images' own metres" if floats else f"dataset.depth_scale={dataset.depth_scale:g} ({origin})"
        )
    values = np.concatenate([d[np.isfinite(d) & (d > 0)] for d in depths]) if depths else np.zeros(0)
    return (float(np.median(values)) if values.size else None), where


def _advice(median: float, scale: float) -> str:
    """What to set: the usual scale that puts the median nearest a typical depth, if it is
    another than `scale` and puts it among the typical ones; '' otherwise."""
    low, high = TYPICAL_MEDIAN_M

    def distance(units: float) -> float:
        return abs(math.log(median * scale / units / TYPICAL_M))

    best = min(CONVENTIONS, key=distance)
    then = median * scale / best
    if best == scale or not low <= then <= high:
        return ""
    return (
        f"if the depth is in {CONVENTIONS[best]}, --set dataset.depth_scale={best:g} (the median is then {then:.2f} m)"
    )
