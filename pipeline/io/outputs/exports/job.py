"""What every writer of exports/ is handed: the run's checkpoint, the run's own records (config,
camera), the path to write and the export command's options. A writer module is a format of
`gsplatam export` once the registry (`EXPORTERS` in exports/__init__.py) names it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

import torch

from pipeline.config import Config
from pipeline.io.outputs.intrinsics import CameraIntrinsics
from pipeline.slam.state import Checkpoint

Frames = Literal["keyframes", "all"]  # nerfstudio: the keyframes, or every frame tracked well
Size = Literal["working", "native"]  # nerfstudio: SLAM's working size, or the dataset's own


class RunRecords(Protocol):
    """What an export reads of its run beside the checkpoint (a RunFolder has it)."""

    path: Path  # the run folder

    def read_config(self) -> Config: ...

    def read_intrinsics(self) -> CameraIntrinsics:
        """The camera at SLAM's working size (intrinsics.json)."""
        ...

    def frame_timestamps(self) -> dict[int, float]:
        """Frame index -> its timestamp, seconds (frames.csv): what the run read of its dataset."""
        ...


@dataclass(frozen=True)
class NerfstudioOptions:
    frames: Frames = "keyframes"  # keyframes, or every frame tracked well
    size: Size = "working"  # SLAM's working size, or the dataset's own


NERFSTUDIO_DEFAULTS = NerfstudioOptions()  # the keyframes at SLAM's working size


@dataclass(frozen=True)
class ExportJob:
    run: RunRecords
    checkpoint: Checkpoint  # validated on reading
    target: Path  # the file (a folder for nerfstudio) to write, already checked by the caller
    voxel_m: float = 0.02  # mesh: TSDF voxel size, metres
    device: torch.device | None = None  # mesh: where to render (None: the CPU)
    nerfstudio: NerfstudioOptions = NERFSTUDIO_DEFAULTS


class Exporter(Protocol):
    """What a writer module of exports/ holds to be a format of `gsplatam export`."""

    DEFAULT_NAME: str  # where it goes inside the run folder unless --output says otherwise
    FOR: str  # what reads it, one phrase (the command's help and the docs' table)
    NEEDS: str | None  # the module of an optional extra it needs (pipeline/extras.py), or None

    def export(self, job: ExportJob) -> str:
        """Write the format of `job.checkpoint` to `job.target` -> what it holds, one line."""
        ...
