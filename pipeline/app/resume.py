"""`run --resume`: the checks made before anything in the folder is touched.

A checkpoint continues only the run it was written by: the same dataset (name, layout,
slicing), the same frame size and the same kind of Gaussian map, from a dataset (a live run
cannot be replayed). Anything else is refused with one line, the folder left as it was.
"""

from __future__ import annotations

from typing import Any

from pipeline.errors import UserError
from pipeline.io.outputs.checkpoint import read_description
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.slam.state import Checkpoint

# what a resume must match of the run that wrote the checkpoint, and how a mismatch reads
SAME_RUN = {
    "source": "dataset",
    "format": "dataset layout",
    "start": "dataset.start",
    "stride": "dataset.stride",
    "size": "frame size (width, height)",
    "gaussians": "Gaussian kind (gaussians.kind)",
    "isotropic": "gaussians.isotropic",
}


def refuse_a_live_run(folder: RunFolder) -> None:
    """UserError at once where `folder` holds a live session, which no dataset continues (before
    its config is read, so no dataset is opened or room generated for it)."""
    saved = read_description(folder.checkpoint)
    if saved is not None and saved.live:
        replay = (
            f"; {folder.recording} runs it again offline: gsplatam run {folder.recording}" if folder.recorded() else ""
        )
        raise UserError(f"{folder.path} is a live run ({saved.source}): --resume continues dataset runs only{replay}")


def read_resumable(folder: RunFolder, expected: RunDescription, frames: int) -> Checkpoint:
    """The checkpoint in `folder` if it continues the run `expected` describes over a dataset
    of `frames` frames; UserError naming what differs otherwise. A run that has all its frames
    resumes only to finish its evaluation."""
    checkpoint, saved = folder.read_checkpoint()
    if saved.live:
        raise UserError(f"{folder.path} is a live run ({saved.source}): --resume continues dataset runs only")
    for key, what in SAME_RUN.items():
        recorded, wanted = getattr(saved, key), getattr(expected, key)
        if recorded is not None and recorded != wanted:
            raise UserError(f"{folder.path} was run with {what} {_shown(recorded)}, this run has {_shown(wanted)}")
    assert expected.size is not None, "a dataset run knows its frame size"
    width, height = expected.size
    for keyframe in checkpoint.keyframes:
        if tuple(keyframe.color_u8.shape[:2]) != (height, width):
            shape = keyframe.color_u8.shape
            raise UserError(
                f"{folder.path} holds keyframes of {shape[1]}x{shape[0]}, this run's frames are {width}x{height}"
            )
    if checkpoint.frames_done > frames:
        raise UserError(
            f"{folder.path} holds {checkpoint.frames_done} frames, this dataset (as sliced) has only {frames}"
        )
    metrics = folder.read_metrics()
    if checkpoint.frames_done == frames and metrics is not None and metrics.evaluation_complete:
        raise UserError(f"{folder.path} already holds all {frames} frames and their metrics")
    return checkpoint


def _shown(value: Any) -> str:
    if isinstance(value, tuple) and len(value) == 2:
        return f"{value[0]}x{value[1]}"
    return repr(value)
