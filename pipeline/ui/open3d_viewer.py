"""The desktop viewer (Open3D, the `mesh` extra): the map's Gaussian centres as a coloured point
cloud, the trajectory and the current camera's frustum, updated live, in a window of its own.

Mouse: Open3D's (left drag orbits, Ctrl+left pans, wheel zooms). Keys: W A S D move the view
forward, left, back and right, E and C up and down; F follows the camera from behind its
frustum; Space pauses and resumes SLAM; K saves the map now; Escape stops the run (as Ctrl-C),
and after the run closes the window. Closing the window during a run only closes the viewer.

Open3D draws in the thread that made its window, so the window lives in a thread of its own;
updates are handed over under a lock and the newest of each kind wins.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import numpy as np

from pipeline.errors import UserError
from pipeline.ui.display import FrameView, MapView, follow_pose

log = logging.getLogger("gsplatam")

FRAME_S = 1 / 60  # the window's event loop runs at most this often
WINDOW_TIMEOUT_S = 60.0
STEP_FRACTION = 0.02  # one key press moves the view this fraction of the map's extent
FRUSTUM_DEPTH_M = 0.15
FOLLOW_BACK_M = 0.6  # the follow view sits this far behind the current camera
FOLLOW_UP_M = 0.25  # and this far above it
TRAJECTORY_RGB = (0.9, 0.24, 0.16)
KEY_ESCAPE, KEY_SPACE = 256, 32


def frustum_lines(c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int, depth_m: float) -> np.ndarray:
    """The 8 edges of a camera's frustum, [8, 2, 3] world metres: eye to the four image corners
    back-projected to `depth_m`, and the rectangle between them."""
    corners = np.array([[0, 0], [width, 0], [width, height], [0, height]], dtype=np.float64)
    rays = np.stack(
        [(corners[:, 0] - intrinsics[0, 2]) / intrinsics[0, 0], (corners[:, 1] - intrinsics[1, 2]) / intrinsics[1, 1]],
        axis=1,
    )
    points = np.concatenate([rays, np.ones((4, 1))], axis=1) * depth_m @ c2w[:3, :3].T + c2w[:3, 3]
    eye = c2w[:3, 3]
    return np.array([[eye, p] for p in points] + [[points[i], points[(i + 1) % 4]] for i in range(4)])


class Open3DViewer:
    """A MapDisplay in an Open3D window. `live`: SLAM runs (Space, K and Escape act on it)."""

    def __init__(self, title: str, live: bool = True, width: int = 1024, height: int = 768) -> None:
        import open3d  # noqa: F401  (fails here, in the caller's thread, when the extra is missing)

        self.title, self.live, self.size = title, live, (width, height)
        self.running = threading.Event()
        self.running.set()
        self.save_requested = threading.Event()
        self.stopped = threading.Event()
        self.follow = False
        self._finished = False
        self._open = threading.Event()  # the window is up
        self._closing = threading.Event()
        self._lock = threading.Lock()
        self._pending: dict[str, Any] = {}  # "map": MapView, "path": poses, "camera": FrameView
        self._calls: list[tuple[Callable[[Any], Any], Future[Any]]] = []
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._window, name="open3d", daemon=True)
        self._thread.start()
        if not self._open.wait(WINDOW_TIMEOUT_S):
            self._error = TimeoutError(f"no window after {WINDOW_TIMEOUT_S:g} s")
        if self._error is not None:
            raise UserError(f"the Open3D viewer cannot open a window (no display?): {self._error}")
        log.info("viewer: an Open3D window (W A S D E C move, F follows, Space pauses, K saves, Escape stops)")

    # The MapDisplay contract (any thread).

    def clients(self) -> int:
        return 1 if self._thread.is_alive() and not self._closing.is_set() else 0

    def show_map(self, view: MapView) -> None:
        self._post("map", view)

    def show_trajectory(self, poses: np.ndarray) -> None:
        """The camera path through `poses` [F, 4, 4] camera-to-world."""
        self._post("path", poses)

    def show_frame(self, view: FrameView) -> None:
        self._post("path", view.poses)
        self._post("camera", view)

    def show_saved(self, message: str) -> None:
        log.info("viewer: %s", message)

    def show_summary(self, markdown: str) -> None:
        self._finished = True
        log.info("viewer: %s (close the window or press Escape to end)", markdown.replace("**", ""))

    def look_from(self, c2w: np.ndarray) -> None:
        """Put the view at camera-to-world `c2w` [4, 4] (OpenCV axes)."""
        self.call(lambda vis: self._set_view(vis, c2w))

    def capture(self) -> np.ndarray:
        """What the window shows now: [H, W, 3] uint8 RGB."""
        image = self.call(lambda vis: np.asarray(vis.capture_screen_float_buffer(do_render=True)))
        return (np.clip(image, 0, 1) * 255).round().astype(np.uint8)

    def call(self, fn: Callable[[Any], Any], timeout_s: float = 30.0) -> Any:
        """Run `fn(visualizer)` in the window's thread (after the pending updates); -> its result."""
        future: Future[Any] = Future()
        with self._lock:
            self._calls.append((fn, future))
        return future.result(timeout_s)

    def wait_closed(self) -> None:
        """Until the window is closed (or Escape)."""
        while self._thread.is_alive() and not self.stopped.wait(0.2):
            pass

    def close(self) -> None:
        self.running.set()
        self._closing.set()
        self._thread.join(timeout=30)

    # The window's thread.

    def _post(self, kind: str, value: Any) -> None:
        with self._lock:
            self._pending[kind] = value

    def _window(self) -> None:
        import open3d as o3d

        vis = o3d.visualization.VisualizerWithKeyCallback()
        scene = _Scene(o3d)
        try:
            if not vis.create_window(self.title, *self.size):
                raise RuntimeError("create_window failed")
            vis.get_render_option().point_size = 2.0
            vis.get_render_option().background_color = np.array([0.08, 0.08, 0.1])
            self._bind_keys(vis, scene)
        except Exception as exc:  # reported to the constructor
            self._error = exc
            self._open.set()
            return
        self._open.set()
        try:
            while not self._closing.is_set():
                self._apply(vis, scene)
                if not vis.poll_events():
                    break  # the user closed the window
                vis.update_renderer()
                self._closing.wait(FRAME_S)
        except Exception:  # the viewer must never stop SLAM
            log.exception("open3d viewer failed")
        finally:
            self._closing.set()
            if self._finished:
                self.stopped.set()
            self._fail_calls()
            vis.destroy_window()

    def _apply(self, vis: Any, scene: _Scene) -> None:
        with self._lock:
            pending, self._pending = self._pending, {}
            calls, self._calls = self._calls, []
        if "map" in pending:
            scene.show_points(vis, pending["map"])
        if "path" in pending:
            scene.show_path(vis, pending["path"])
        if "camera" in pending:
            view: FrameView = pending["camera"]
            height, width = view.color.shape[:2]
            scene.show_frustum(vis, frustum_lines(view.poses[-1], view.intrinsics, width, height, FRUSTUM_DEPTH_M))
            if self.follow or scene.first_view:
                scene.first_view = False
                self._set_view(vis, follow_pose(view.poses[-1], FOLLOW_BACK_M, FOLLOW_UP_M))
        for fn, future in calls:
            try:
                future.set_result(fn(vis))
            except Exception as exc:
                future.set_exception(exc)

    def _fail_calls(self) -> None:
        with self._lock:
            calls, self._calls = self._calls, []
        for _, future in calls:
            future.set_exception(RuntimeError("the Open3D window is closed"))

    @staticmethod
    def _set_view(vis: Any, c2w: np.ndarray) -> None:
        control = vis.get_view_control()
        params = control.convert_to_pinhole_camera_parameters()
        params.extrinsic = np.linalg.inv(c2w)  # world-to-camera; Open3D's camera axes are OpenCV's
        control.convert_from_pinhole_camera_parameters(params, allow_arbitrary=True)

    def _bind_keys(self, vis: Any, scene: _Scene) -> None:
        def move(forward: float, right: float, up: float) -> Callable[[Any], bool]:
            def step(v: Any) -> bool:
                s = STEP_FRACTION * scene.extent_m
                v.get_view_control().camera_local_translate(forward * s, right * s, up * s)
                return True

            return step

        keys: dict[int, Callable[[Any], bool]] = {
            ord("W"): move(1, 0, 0),
            ord("S"): move(-1, 0, 0),
            ord("D"): move(0, 1, 0),
            ord("A"): move(0, -1, 0),
            ord("E"): move(0, 0, 1),
            ord("C"): move(0, 0, -1),
            ord("F"): self._toggle_follow,
            KEY_ESCAPE: self._escape,
        }
        if self.live:
            keys[KEY_SPACE] = self._toggle_pause
            keys[ord("K")] = self._save
        for key, callback in keys.items():
            vis.register_key_callback(key, callback)

    def _toggle_follow(self, vis: Any) -> bool:
        self.follow = not self.follow
        log.info("viewer: follow camera %s", "on" if self.follow else "off")
        return False

    def _toggle_pause(self, vis: Any) -> bool:
        if self.running.is_set():
            self.running.clear()
            log.info("viewer: SLAM paused (Space resumes)")
        else:
            self.running.set()
            log.info("viewer: SLAM resumed")
        return False

    def _save(self, vis: Any) -> bool:
        self.save_requested.set()
        return False

    def _escape(self, vis: Any) -> bool:
        """During a live run: stop it as Ctrl-C would; otherwise close the window."""
        self.running.set()
        self.stopped.set()
        if self.live and not self._finished:
            os.kill(os.getpid(), signal.SIGINT)
        else:
            self._closing.set()
        return False


class _Scene:
    """The window's geometries, made on first use and updated in place (window thread only)."""

    def __init__(self, o3d: Any) -> None:
        self.o3d = o3d
        self.points = o3d.geometry.PointCloud()
        self.path = o3d.geometry.LineSet()
        self.frustum = o3d.geometry.LineSet()
        self.shown: set[str] = set()
        self.first_view = True
        self.extent_m = 1.0

    def _update(self, vis: Any, name: str, geometry: Any) -> None:
        if name in self.shown:
            vis.update_geometry(geometry)
        else:
            vis.add_geometry(geometry, reset_bounding_box=name == "points")
            self.shown.add(name)

    def show_points(self, vis: Any, view: MapView) -> None:
        vector = self.o3d.utility.Vector3dVector
        self.points.points = vector(view.centers.astype(np.float64))
        self.points.colors = vector(view.rgbs.astype(np.float64))
        if len(view.centers):
            self.extent_m = float(np.linalg.norm(view.centers.max(axis=0) - view.centers.min(axis=0)))
        self._update(vis, "points", self.points)

    def show_path(self, vis: Any, poses: np.ndarray) -> None:
        if len(poses) < 2:
            return
        self._set_lines(self.path, poses[:, :3, 3], np.stack([np.arange(len(poses) - 1), np.arange(1, len(poses))], 1))
        self._update(vis, "path", self.path)

    def show_frustum(self, vis: Any, lines: np.ndarray) -> None:
        self._set_lines(self.frustum, lines.reshape(-1, 3), np.arange(2 * len(lines)).reshape(-1, 2))
        self._update(vis, "frustum", self.frustum)

    def _set_lines(self, line_set: Any, points: np.ndarray, pairs: np.ndarray) -> None:
        utility = self.o3d.utility
        line_set.points = utility.Vector3dVector(points.astype(np.float64))
        line_set.lines = utility.Vector2iVector(pairs.astype(np.int32))
        line_set.colors = utility.Vector3dVector(np.tile(TRAJECTORY_RGB, (len(pairs), 1)))
