"""The `render` command: a run's map seen again, as a fly-through video along its trajectory
(every `stride`-th camera pose of the checkpoint, at SLAM's working size), written as an MP4 and
noted in exports.json as exports are (a `--resume` that moves the map on marks it stale)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from pipeline.errors import OutputError, UserError
from pipeline.geometry import invert_pose
from pipeline.io.files.folders import make_folder
from pipeline.io.outputs.run_folder import RunFolder, run_owning
from pipeline.io.outputs.video import write_mp4
from pipeline.render import Camera, Gaussians, make_renderer
from pipeline.slam.gaussian_map import copied
from pipeline.ui.display import follow_pose

VIDEO = "flythrough.mp4"  # in the run folder, unless --output names another file


def render_video(
    run_dir: Path, output: Path | None, fps: float, back_m: float, stride: int, device: torch.device
) -> tuple[Path, int]:
    """The fly-through of the run in `run_dir` rendered on `device` into `output` (default: the
    run folder's VIDEO), seen from `back_m` metres behind each pose; -> (its path, frames)."""
    folder = RunFolder.existing(run_dir.resolve())  # outputs/latest: the run it points at
    checkpoint, _ = folder.read_checkpoint()
    target = _checked_target(output or folder.path / VIDEO)
    poses = checkpoint.poses[::stride].double().numpy()
    try:
        frames = write_mp4(target, _views(folder, checkpoint.gaussians, poses, back_m, device), fps)
        folder.record_export("video", target, checkpoint)
    except OSError as exc:
        raise OutputError(f"cannot write {target}: {exc.strerror or exc}") from None
    return target, frames


def _checked_target(target: Path) -> Path:
    """`target` (its folder resolved, and created) once a video may be written there: never onto
    one of a run's own files, nor onto a folder; UserError naming it otherwise."""
    target = target.parent.resolve() / target.name
    owner = run_owning(target)
    if owner is not None:
        raise UserError(f"{target} is one of the run folder {owner.path}'s own files: choose another --output")
    if target.is_dir():
        raise UserError(f"{target} is a folder: --output names the .mp4 file to write")
    make_folder(target.parent, "the video's folder")
    return target


def _views(
    folder: RunFolder, gaussians_on_host: Gaussians, poses: np.ndarray, back_m: float, device: torch.device
) -> Iterator[np.ndarray]:
    """The map rendered from each camera-to-world pose [N, 4, 4] (moved `back_m` behind it),
    one [H, W, 3] uint8 image at a time."""
    config, camera = folder.read_config(), folder.read_intrinsics()
    # the backend that suits `device` (the run's may have been another machine's)
    renderer = make_renderer(replace(config.render, backend="auto"), config.gaussians, device)
    k = torch.tensor(camera.matrix(), dtype=torch.float32, device=device)
    gaussians = copied(gaussians_on_host, device)
    for pose in poses:
        c2w = torch.from_numpy(follow_pose(pose, back_m, 0.0)).float().to(device)
        view = Camera(invert_pose(c2w), k, camera.width, camera.height, config.render.near, config.render.far)
        with torch.no_grad():
            color = renderer(gaussians, view).color.clamp(0, 1)
        yield (color * 255 + 0.5).to(torch.uint8).cpu().numpy()
