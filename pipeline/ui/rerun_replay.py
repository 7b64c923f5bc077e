"""`gsplatam view --rerun`: a saved run in rerun, as `RerunFeed` logs a running one: the map's
Gaussians (as splats, or points: rerun_recording.py), the camera along the estimated trajectory (frame by frame,
with the run's intrinsics) and both trajectories, estimated and ground truth, as lines."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.intrinsics import CameraIntrinsics
from pipeline.io.outputs.ply import read_ply
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.ui.rerun_recording import MapSplats, RerunRecording


@dataclass
class SavedRun:
    """What a replay shows, read before anything is logged (a bad file leaves no recording)."""

    map: Path
    splats: MapSplats  # the map.ply's Gaussians
    poses: np.ndarray  # [F, 4, 4] estimated camera-to-world (F = 0 without trajectory.txt)
    camera: CameraIntrinsics | None  # intrinsics.json's, where the run has it
    reference: np.ndarray | None  # [F, 4, 4] ground-truth camera-to-world, where the run has it


def read_saved_run(path: Path) -> SavedRun:
    """A run folder (map.ply, trajectory.txt, intrinsics.json, groundtruth.txt; all but the map
    optional) or a 3DGS PLY alone."""
    folder = RunFolder(path) if path.is_dir() else None
    ply = folder.map if folder is not None else path
    if not ply.is_file():
        raise UserError(f"no map to show: {ply} does not exist")
    run = SavedRun(ply, MapSplats.of(read_ply(ply)), np.zeros((0, 4, 4)), None, None)
    if folder is None:
        return run
    if folder.trajectory.is_file():
        run.poses = read_tum_trajectory(folder.trajectory)[1]
    if folder.intrinsics.is_file():
        run.camera = folder.read_intrinsics()
    if folder.groundtruth.is_file():
        run.reference = read_tum_trajectory(folder.groundtruth)[1]
    return run


def replay_saved_run(path: Path, save: Path | None) -> str:
    """Log the run or PLY at `path` to a spawned rerun viewer or into the `.rrd` file `save`;
    -> what was logged, in a line."""
    run = read_saved_run(path)
    recording = RerunRecording(f"gsplatam: {path}", save)
    recording.map(run.splats, static=True)
    for number, c2w in enumerate(run.poses):
        recording.at(number)
        recording.pose(c2w)
    if run.camera is not None:
        recording.at(0)
        recording.view(run.camera.matrix(), run.camera.width, run.camera.height)
    recording.trajectory("trajectory", run.poses[:, :3, 3], static=True)
    if run.reference is not None:
        recording.trajectory("groundtruth", run.reference[:, :3, 3], static=True)
    what = f"{len(run.splats.centres):,} Gaussians from {run.map}, {len(run.poses)} poses" + (
        ", the ground truth" if run.reference is not None else ""
    )
    recording.summary(what)
    recording.close()
    return f"wrote {save}: {what}" if save is not None else f"sent to rerun's viewer: {what}"
