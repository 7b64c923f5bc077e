"""The `view` command: a saved map (a run folder or a 3DGS PLY) in the browser or an Open3D window."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.ply import read_ply
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.ui.display import follow_pose
from pipeline.ui.viewer_feed import map_view

OVERVIEW_BACK_M = 1.5  # a saved map is first seen from this far behind the first camera
OVERVIEW_UP_M = 0.5


def view_saved_map(path: Path, open3d: bool, host: str, port: int) -> None:
    """Show the map (and the trajectory beside a run folder's map) until Ctrl-C or the window closes."""
    folder = RunFolder(path) if path.is_dir() else None
    ply = folder.map if folder is not None else path
    if not ply.is_file():
        raise UserError(f"no map to show: {ply} does not exist")
    gaussians = read_ply(ply)
    trajectory = folder.trajectory if folder is not None else None
    poses = (
        read_tum_trajectory(trajectory)[1] if trajectory is not None and trajectory.is_file() else np.zeros((0, 4, 4))
    )
    start = follow_pose(poses[0], OVERVIEW_BACK_M, OVERVIEW_UP_M) if len(poses) else None
    title = f"gsplatam: {ply}"
    if open3d:
        from pipeline.ui.open3d_viewer import Open3DViewer

        window = Open3DViewer(title, live=False)
        window.show_map(map_view(gaussians))
        window.show_trajectory(poses)
        if start is not None:
            window.look_from(start)
        try:
            print(f"showing {len(gaussians):,} Gaussian centres from {ply} in an Open3D window (close it to quit)")
            window.wait_closed()
        except KeyboardInterrupt:
            pass  # a way to quit
        finally:
            window.close()
        return
    from pipeline.ui.viewer import Viewer

    viewer = Viewer(host, port, title, live=False)
    viewer.show_map(map_view(gaussians))
    viewer.show_trajectory(poses)
    if start is not None:
        viewer.look_from(start, poses[0][:3, 3])
    viewer.stats.content = f"{len(gaussians):,} Gaussians from {ply}"
    try:  # from the line that says Ctrl-C quits, Ctrl-C quits (exit 0)
        print(f"showing {len(gaussians):,} Gaussians at {viewer.url} (Ctrl-C to quit)", flush=True)
        threading.Event().wait()
    except KeyboardInterrupt:
        pass  # the way to quit
    finally:
        viewer.close()
