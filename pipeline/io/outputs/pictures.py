"""Pictures of a run: its renders beside the input (renders/, PNG) and its trajectory against
the reference (trajectory.png, drawn by matplotlib as evo draws one: a top view and the height
over time)."""

from __future__ import annotations

import io
import logging
from pathlib import Path

import cv2
import numpy as np

from pipeline.io.files.atomic import atomic_write_bytes
from pipeline.io.files.images import encode_color
from pipeline.metrics import rigid_alignment
from pipeline.ui.display import colorize_depth

log = logging.getLogger("gsplatam")

PANEL_MAX_WIDTH = 640  # pixels: a larger frame is halved (and again) in its picture, which stays small
LABEL_MIN_WIDTH = 200  # pixels: a narrower panel is not labelled


def spread(indices: list[int], most: int) -> list[int]:
    """At most `most` of `indices`, evenly spread from the first to the last."""
    if most <= 0 or not indices:
        return []
    if most >= len(indices):
        return list(indices)
    if most == 1:
        return [indices[0]]
    return [indices[round(k * (len(indices) - 1) / (most - 1))] for k in range(most)]


def render_picture(
    color: np.ndarray, depth: np.ndarray, rendered_color: np.ndarray, rendered_depth: np.ndarray
) -> np.ndarray:
    """The input beside its render: colour above depth, input left and render right, [2H, 2W, 3]
    uint8. Colours [H, W, 3] in [0, 1], depths [H, W] metres (0: none), both depths on the scale
    of the input's (its 99th percentile) so that they compare by colour."""
    valid = depth[depth > 0]
    far = float(np.percentile(valid, 99)) if valid.size else float(max(rendered_depth.max(), 1e-3))
    panels = [
        [_uint8(color), _uint8(rendered_color)],
        [colorize_depth(depth, far), colorize_depth(rendered_depth, far)],
    ]
    labels = [["input", "render"], ["input depth", "rendered depth"]]
    rows = [np.concatenate([_labelled(p, t) for p, t in zip(row, names)], axis=1) for row, names in zip(panels, labels)]
    picture = np.concatenate(rows, axis=0)
    while picture.shape[1] > 2 * PANEL_MAX_WIDTH:
        picture = cv2.resize(picture, (picture.shape[1] // 2, picture.shape[0] // 2), interpolation=cv2.INTER_AREA)
    return picture


def write_render_picture(folder: Path, index: int, picture: np.ndarray) -> Path:
    """`picture` as renders/frameNNNNNN.png in the run folder `folder` (the folder made when missing)."""
    path = folder / f"frame{index:06d}.png"
    folder.mkdir(exist_ok=True)
    atomic_write_bytes(path, encode_color(picture, ".png"))
    return path


def _uint8(color: np.ndarray) -> np.ndarray:
    return (np.clip(color, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _labelled(panel: np.ndarray, text: str) -> np.ndarray:
    """The panel with `text` in its top-left corner (white on a dark band), sized to the panel;
    as it is where the panel is too small for it to be read (under LABEL_MIN_WIDTH)."""
    panel = np.ascontiguousarray(panel)
    if panel.shape[1] < LABEL_MIN_WIDTH:
        return panel
    scale = max(panel.shape[1] / 640.0, 0.3)
    height = int(22 * scale)
    panel[:height, : int((len(text) * 11 + 10) * scale)] //= 3
    cv2.putText(panel, text, (int(5 * scale), int(16 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.5 * scale, (255, 255, 255))
    return panel


def trajectory_png(timestamps: np.ndarray, estimate: np.ndarray, reference: np.ndarray | None) -> bytes:
    """The trajectory as a PNG: a top view (x and z of the first camera's axes: y points down, so
    x-z is the ground for a level camera) and the height (-y) over time; the estimate rigidly
    aligned onto the reference where there is one (as the ATE and `evo_ape -a` align it).
    Camera-to-world poses [N, 4, 4], timestamps [N] seconds."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    logging.getLogger("matplotlib").setLevel(logging.WARNING)  # its font cache's first build logs at INFO
    est = estimate[:, :3, 3]
    if reference is not None:
        rotation, translation = rigid_alignment(est, reference[:, :3, 3])
        est = est @ rotation.T + translation
    figure = Figure(figsize=(10, 4.5), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    top, height = figure.subplots(1, 2, width_ratios=[1, 1.3])
    seconds = timestamps - timestamps[0]
    if reference is not None:
        ref = reference[:, :3, 3]
        top.plot(ref[:, 0], ref[:, 2], "--", color="gray", label="reference")
        height.plot(seconds, -ref[:, 1], "--", color="gray", label="reference")
    label = "estimate (aligned)" if reference is not None else "estimate"
    top.plot(est[:, 0], est[:, 2], color="tab:blue", label=label)
    top.plot(est[:1, 0], est[:1, 2], "o", color="tab:green", label="start")
    height.plot(seconds, -est[:, 1], color="tab:blue", label=label)
    top.set(xlabel="x (m)", ylabel="z (m)", title="top view", aspect="equal")
    top.set_adjustable("datalim")
    height.set(xlabel="time (s)", ylabel="height, -y (m)", title="height")
    for axes in (top, height):
        axes.grid(True, alpha=0.3)
    top.legend(loc="best", fontsize="small")
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def write_trajectory_png(
    path: Path, timestamps: np.ndarray, estimate: np.ndarray, reference: np.ndarray | None
) -> None:
    atomic_write_bytes(path, trajectory_png(timestamps, estimate, reference))
