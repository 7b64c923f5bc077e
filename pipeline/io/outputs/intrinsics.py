"""The camera of a run, saved beside its map: `intrinsics.json` (what exports need to project)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import DataError
from pipeline.frame import DeviceFrame
from pipeline.io.files.atomic import atomic_write_text
from pipeline.slam.handoff import FrameResult
from pipeline.slam.view import SlamView


@dataclass(frozen=True)
class CameraIntrinsics:
    """A pinhole camera at SLAM's working size; pixel (u, v) is centred at (u + 0.5, v + 0.5)."""

    fx: float  # pixels
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @staticmethod
    def of_matrix(k: np.ndarray, width: int, height: int) -> CameraIntrinsics:
        """From a [3, 3] intrinsics matrix."""
        return CameraIntrinsics(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), width, height)

    def matrix(self) -> np.ndarray:
        """[3, 3] float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def write_intrinsics(path: Path, camera: CameraIntrinsics) -> None:
    atomic_write_text(path, json.dumps(asdict(camera), indent=2) + "\n")


def read_intrinsics(path: Path) -> CameraIntrinsics:
    """DataError naming the file when it is missing or malformed."""
    try:
        table = json.loads(path.read_text())
        fx, fy, cx, cy = (float(table[k]) for k in ("fx", "fy", "cx", "cy"))
        camera = CameraIntrinsics(fx, fy, cx, cy, int(table["width"]), int(table["height"]))
    except FileNotFoundError:
        raise DataError(
            f"no {path.name} in {path.parent} (older run folders lack it: run the sequence again)"
        ) from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{path} is not a camera description ({exc.__class__.__name__}: {exc})") from None
    if camera.width <= 0 or camera.height <= 0 or camera.fx <= 0 or camera.fy <= 0:
        raise DataError(f"{path}: sizes and focal lengths must be positive")
    return camera


class IntrinsicsRecorder:
    """A SLAM-stage observer writing the camera of the first frame (every frame of a run has
    the working size of the first; one host read of a [3, 3] tensor per run)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.written = False

    def __call__(self, slam: SlamView, frame: DeviceFrame, result: FrameResult) -> None:
        if not self.written:
            k = frame.intrinsics.double().cpu().numpy()
            write_intrinsics(self.path, CameraIntrinsics.of_matrix(k, frame.width, frame.height))
            self.written = True
