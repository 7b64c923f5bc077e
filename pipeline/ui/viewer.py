"""The live web viewer (viser): splats, trajectory, the latest frame, stats and controls.

The map is pushed to viser's in-browser splat renderer: the browser's GPU draws every view the
user moves to at display rate, and the SLAM GPU only pays for a host copy of the map at a
bounded rate (bench/results/viewer.md measures the cost). Rendered depth and silhouette at the
latest pose are small images made by the viewer thread.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from typing import TYPE_CHECKING

import numpy as np

from pipeline.ui.display import FrameView, MapView, follow_pose

if TYPE_CHECKING:  # imported when a viewer is made: runs without one need no viser
    import viser
    import viser.transforms as vtf

log = logging.getLogger("gsplatam")

FOLLOW_BACK_M = 0.6  # the follow camera sits this far behind the current camera
FOLLOW_UP_M = 0.25  # and this far above it


def _se3(c2w: np.ndarray) -> vtf.SE3:
    import viser.transforms as vtf

    return vtf.SE3.from_matrix(c2w)


class Viewer:
    """A viser server with the scene and the controls (a MapDisplay). Every method may be called
    from any thread (viser queues messages to its own event loop)."""

    def __init__(self, host: str, port: int, title: str, live: bool = True) -> None:
        """`live`: the latest frame's images and the pause, save and stop buttons (for a running
        SLAM; not for a saved map)."""
        import viser

        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        self.server.scene.set_up_direction("-y")  # OpenCV world: y points down
        self.running = threading.Event()  # cleared while paused
        self.running.set()
        self.save_requested = threading.Event()
        self.stopped = threading.Event()
        self._finished = False  # the run is over: Stop closes the viewer instead of stopping SLAM
        gui = self.server.gui
        self.stats = gui.add_markdown("waiting for the first frame")
        self.follow = gui.add_checkbox("Follow camera", initial_value=False)
        self.images: dict[str, viser.GuiImageHandle] = {}
        if live:
            self.pause = gui.add_button("Pause SLAM")
            self.pause.on_click(lambda _: self._toggle_pause())
            gui.add_button("Save map now").on_click(lambda _: self.save_requested.set())
            self.save_status = gui.add_markdown("")
            gui.add_button("Stop").on_click(lambda _: self.request_stop())
            blank = np.zeros((2, 2, 3), np.uint8)
            self.images = {
                name: gui.add_image(blank, label=name, format="jpeg")
                for name in ("input colour", "input depth", "rendered depth", "silhouette")
            }
        self._camera_pose: vtf.SE3 | None = None  # where a new browser starts
        self._look_at: np.ndarray | None = None
        self.server.on_client_connect(self._place_camera)
        log.info("viewer: %s", self.url)

    def _place_camera(self, client: viser.ClientHandle) -> None:
        if self._camera_pose is not None:
            with client.atomic():
                client.camera.wxyz = self._camera_pose.rotation().wxyz
                client.camera.position = self._camera_pose.translation()
                if self._look_at is not None:
                    client.camera.look_at = self._look_at

    def _toggle_pause(self) -> None:
        if self.running.is_set():
            self.running.clear()
            self.pause.label = "Resume SLAM"
        else:
            self.running.set()
            self.pause.label = "Pause SLAM"

    def request_stop(self) -> None:
        """During the run: finish it cleanly, as Ctrl-C would. After it: close the viewer."""
        self.running.set()
        self.stopped.set()
        if not self._finished:
            os.kill(os.getpid(), signal.SIGINT)

    def show_map(self, view: MapView) -> None:
        self.server.scene.add_gaussian_splats("/map", view.centers, view.covariances, view.rgbs, view.opacities)

    def show_trajectory(self, poses: np.ndarray) -> None:
        """The camera path through `poses` [F, 4, 4] camera-to-world."""
        if len(poses) > 1:
            centres = poses[:, :3, 3].astype(np.float32)
            segments = np.stack([centres[:-1], centres[1:]], axis=1)
            self.server.scene.add_line_segments("/trajectory", segments, colors=(230, 60, 40), thickness=0.01)

    def show_frame(self, view: FrameView) -> None:
        self.stats.content = view.stats
        height, width = view.color.shape[:2]
        fov = 2.0 * np.arctan2(height / 2.0, view.intrinsics[1, 1])
        pose = _se3(view.poses[-1])
        self.server.scene.add_camera_frustum(
            "/camera", fov=fov, aspect=width / height, scale=0.15, image=view.color, format="jpeg",
            wxyz=pose.rotation().wxyz, position=pose.translation(), color=(230, 60, 40),
        )  # fmt: skip
        self.show_trajectory(view.poses)
        images = {
            "input colour": view.color,
            "input depth": view.depth,
            "rendered depth": view.rendered_depth,
            "silhouette": view.silhouette,
        }
        for name, image in images.items():
            self.images[name].image = image
        if self.follow.value or self._camera_pose is None:
            self.look_from(follow_pose(view.poses[-1], FOLLOW_BACK_M, FOLLOW_UP_M), view.poses[-1][:3, 3])

    def show_saved(self, message: str) -> None:
        self.save_status.content = message
        for client in self.server.get_clients().values():
            client.add_notification("Saved", message, auto_close_seconds=5.0)

    def show_summary(self, markdown: str) -> None:
        self._finished = True
        self.stats.content = markdown

    def look_from(self, c2w: np.ndarray, target: np.ndarray | None = None) -> None:
        """Put every browser's camera (and any that connects later) at `c2w` [4, 4], turning
        about `target` [3] (world metres) when given."""
        self._camera_pose = _se3(c2w)
        self._look_at = target
        for client in self.server.get_clients().values():
            self._place_camera(client)

    def clients(self) -> int:
        return len(self.server.get_clients())

    def close(self) -> None:
        self.running.set()
        self.server.stop()
