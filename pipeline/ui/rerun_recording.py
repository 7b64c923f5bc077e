"""A run as a rerun recording (the `rerun` extra), streamed to a spawned rerun viewer or written
to a `.rrd` file.

Entities, in SLAM's world frame (the first camera's; OpenCV axes: x right, y down, z forward),
on the timeline `frame` (a pose's position in trajectory.txt):
- `world/camera`: the camera's pose (camera-to-world) at each frame;
- `world/camera/image`: its pinhole (intrinsics at the images' size), under it `color` (JPEG)
  and `depth` (16-bit millimetres, which rerun also draws as a point cloud in 3D);
- `world/trajectory/<k>`: the estimated camera path, a line strip per TRAJECTORY_PIECE frames
  (re-logging one whole strip every frame would make the recording quadratic in its length);
  a replay adds `world/groundtruth/<k>`;
- `world/map`: the map, one snapshot at a time: its Gaussians as rerun's Gaussian splats
  (`GaussianSplats3D`: centres, scales, rotations, colours with opacity), or, with a rerun that
  lacks that archetype, their centres as coloured points.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import uuid
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import torch

from pipeline.errors import OutputError, UserError
from pipeline.io.files.atomic import temporary_name
from pipeline.render import Gaussians
from pipeline.ui.thumbnail import as_u8

log = logging.getLogger("gsplatam")

TIMELINE = "frame"
CAMERA = "world/camera"
IMAGE = "world/camera/image"
MAP = "world/map"
TRAJECTORY_PIECE = 100  # poses per line strip of a trajectory (each strip also holds the next one's first)
JPEG_QUALITY = 90
FLUSH_TIMEOUT_S = 10.0  # a spawned viewer closed by its user holds the command's end no longer than this
COLORS = {"trajectory": (230, 60, 40), "groundtruth": (40, 180, 90)}  # RGB of each trajectory
SPLATS = hasattr(rr, "GaussianSplats3D")  # rerun's Gaussian-splat archetype (unstable in 0.41)


@dataclass
class MapSplats:
    """The map's Gaussians on the host, activated as rerun's splats take them."""

    centres: np.ndarray  # [N, 3] float32 world metres
    scales: np.ndarray  # [N, 3] float32 metres: the standard deviations along the axes
    quaternions: np.ndarray  # [N, 4] float32 (x, y, z, w), unit
    colors: np.ndarray  # [N, 4] uint8 RGB and opacity

    @staticmethod
    def of(gaussians: Gaussians) -> MapSplats:
        """From the parameters as SLAM holds them (on any device; copied to the host)."""
        quats = torch.nn.functional.normalize(gaussians.quats.detach().float(), dim=-1)
        opacity = as_u8(torch.sigmoid(gaussians.opacity_logits.detach().float())[:, None])
        return MapSplats(
            gaussians.means.detach().float().cpu().numpy(),
            gaussians.scales().detach().float().cpu().numpy(),
            quats[:, [1, 2, 3, 0]].cpu().numpy(),
            torch.cat([as_u8(gaussians.colors.detach()), opacity], dim=1).cpu().numpy(),
        )


class RerunRecording:
    """One recording. `save`: write it to this `.rrd` file (into a hidden sibling, renamed over
    `save` when closed: complete or absent), else spawn rerun's viewer (the one already open on
    its port takes it instead). Logging may happen from any thread; `at` sets the calling
    thread's frame."""

    def __init__(self, name: str, save: Path | None) -> None:
        self._rec = rr.RecordingStream("gsplatam", recording_id=str(uuid.uuid4()))
        self.save = save
        if save is None:
            _spawn_viewer(self._rec)
        else:
            try:
                self._rec.save(_partial(save))
            except RuntimeError as exc:
                raise UserError(f"cannot write the rerun recording {save}: {exc}") from None
        self._rec.send_recording_name(name)
        self._rec.log("world", rr.ViewCoordinates.RDF, static=True)

    def at(self, number: int) -> None:
        """What this thread logs next belongs to the frame of pose `number`."""
        self._rec.set_time(TIMELINE, sequence=number)

    def pose(self, c2w: np.ndarray) -> None:
        """The camera at `c2w` [4, 4] camera-to-world."""
        self._rec.log(CAMERA, rr.Transform3D(translation=c2w[:3, 3], mat3x3=c2w[:3, :3]))

    def view(self, intrinsics: np.ndarray, width: int, height: int) -> None:
        """The camera's pinhole: `intrinsics` [3, 3] pixels for images of `width` x `height`."""
        pinhole = rr.Pinhole(
            image_from_camera=intrinsics, resolution=[width, height], camera_xyz=rr.ViewCoordinates.RDF
        )
        self._rec.log(IMAGE, pinhole)

    def images(self, color: np.ndarray, depth: np.ndarray) -> None:
        """`color` [h, w, 3] uint8 RGB and `depth` [h, w] metres (0 = invalid) seen by the camera."""
        jpeg = cv2.imencode(".jpg", cv2.cvtColor(color, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])[1]
        self._rec.log(f"{IMAGE}/color", rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"))
        millimetres = np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16)
        self._rec.log(f"{IMAGE}/depth", rr.DepthImage(millimetres, meter=1000.0))

    def trajectory(self, name: str, centres: np.ndarray, since: int = 0, static: bool = False) -> None:
        """The path through `centres` [N, 3] world metres, of which those from `since` on are
        new: only the pieces holding a new centre are logged again."""
        if len(centres) <= since:
            return
        for piece in range(max(since - 1, 0) // TRAJECTORY_PIECE, (len(centres) - 1) // TRAJECTORY_PIECE + 1):
            strip = centres[piece * TRAJECTORY_PIECE : (piece + 1) * TRAJECTORY_PIECE + 1]
            self._rec.log(f"world/{name}/{piece}", rr.LineStrips3D([strip], colors=COLORS[name]), static=static)

    def map(self, splats: MapSplats, static: bool = False) -> None:
        """The map: as Gaussian splats where this rerun has them, else its centres as points."""
        if SPLATS:
            archetype = rr.GaussianSplats3D(
                centers=splats.centres, scales=splats.scales, quaternions=splats.quaternions, colors=splats.colors
            )
            self._rec.log(MAP, archetype, static=static)
        else:
            self._rec.log(MAP, rr.Points3D(splats.centres, colors=splats.colors[:, :3]), static=static)

    def summary(self, markdown: str) -> None:
        self._rec.log("summary", rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=True)

    def close(self) -> None:
        """Send or write what is still buffered and let go of the viewer or file; a `.rrd` is then
        renamed into place (OutputError naming it if it cannot be completed). Once."""
        if self.save is None:
            try:
                self._rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
            except RuntimeError as exc:
                log.warning("rerun: the viewer did not take the whole recording: %s", exc)
            self._rec.disconnect()
            return
        partial = _partial(self.save)
        try:
            self._rec.flush()
            self._rec.disconnect()
            os.replace(partial, self.save)
        except (RuntimeError, OSError) as exc:
            with contextlib.suppress(OSError):
                partial.unlink()
            raise OutputError(f"cannot write the rerun recording {self.save}: {exc}") from None


def _partial(save: Path) -> Path:
    """Where rerun writes the recording until it is complete (rerun writes the file itself)."""
    return temporary_name(save, str(os.getpid()))


def _spawn_viewer(rec: rr.RecordingStream) -> None:
    """Start rerun's viewer (the one of this Python's environment, found even when it is not on
    PATH); UserError where it cannot show a window."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise UserError(
            "rerun's viewer needs a display: write the recording to a file instead "
            "(run and serve: --set viewer.rerun_save=FILE.rrd; view: --rerun-save FILE.rrd)"
        )
    beside = Path(sys.executable).with_name("rerun")
    try:
        rr.spawn(recording=rec, executable_path=str(beside) if beside.is_file() else None)
    except RuntimeError as exc:
        raise UserError(f"cannot start rerun's viewer: {str(exc).splitlines()[0]}") from None
