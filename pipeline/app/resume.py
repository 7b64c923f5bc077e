"""`run --resume`: the checks made before anything in the folder is touched.

A checkpoint continues only the run it was written by: the same dataset (name, layout,
slicing), the same frame size and the same kind of Gaussian map, from a dataset (a live run
cannot be replayed). Anything else is refused with one line, the folder left as it was.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.errors import UserError
from pipeline.outputs.run_folder import RunFolder
from pipeline.slam.state import Checkpoint

# run_info keys a resume must match, and how a mismatch reads
SAME_RUN = {
    "source": "dataset",
    "format": "dataset layout",
    "start": "dataset.start",
    "stride": "dataset.stride",
    "size": "frame size (width, height)",
    "gaussians": "Gaussian kind (gaussians.kind)",
    "isotropic": "gaussians.isotropic",
}


def read_resumable(folder: Path, expected: dict[str, Any], frames: int) -> Checkpoint:
    """The checkpoint in `folder` if it continues the run `expected` describes (`describe_run`)
    over a dataset of `frames` frames; UserError naming what differs otherwise. A run that has
    all its frames resumes only to finish its evaluation."""
    run_folder = RunFolder(folder)
    checkpoint, saved = run_folder.read_checkpoint()
    if saved.get("live"):
        raise UserError(f"{folder} is a live run ({saved.get('source')}): --resume continues dataset runs only")
    for key, what in SAME_RUN.items():
        if key in saved and saved[key] != expected.get(key):
            raise UserError(
                f"{folder} was run with {what} {_shown(saved[key])}, this run has {_shown(expected.get(key))}"
            )
    width, height = expected["size"]
    for keyframe in checkpoint.keyframes:
        if tuple(keyframe.color_u8.shape[:2]) != (height, width):
            shape = keyframe.color_u8.shape
            raise UserError(
                f"{folder} holds keyframes of {shape[1]}x{shape[0]}, this run's frames are {width}x{height}"
            )
    if checkpoint.frames_done > frames:
        raise UserError(f"{folder} holds {checkpoint.frames_done} frames, this dataset (as sliced) has only {frames}")
    if checkpoint.frames_done == frames and evaluation_complete(run_folder.read_metrics()):
        raise UserError(f"{folder} already holds all {frames} frames and their metrics")
    return checkpoint


def evaluation_complete(metrics: dict[str, Any] | None) -> bool:
    """Whether metrics.json holds a complete evaluation (metrics of gsplatam 0.2 without the
    `evaluation` entry: whether they hold render metrics)."""
    if metrics is None:
        return False
    return metrics.get("evaluation", "complete" if metrics.get("render") else "skipped") == "complete"


def _shown(value: Any) -> str:
    if isinstance(value, list) and len(value) == 2:
        return f"{value[0]}x{value[1]}"
    return repr(value)
