"""Drives the Open3D viewer in its own process (run under Xvfb by test_open3d_viewer.py): a known
map and camera, screenshots before and after key presses, and what the keys did, into OUT/."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from pipeline.ui.display import FrameView, MapView
from pipeline.ui.open3d_viewer import Open3DViewer

GREEN = (0.1, 0.9, 0.2)


def wall() -> MapView:
    """A green 2 m x 1.5 m wall of points 2 m in front of the first camera."""
    u, v = np.meshgrid(np.linspace(-1.0, 1.0, 120), np.linspace(-0.75, 0.75, 90))
    centers = np.stack([u.ravel(), v.ravel(), np.full(u.size, 2.0)], axis=1).astype(np.float32)
    n = len(centers)
    return MapView(
        centers,
        np.tile(np.eye(3, dtype=np.float32) * 1e-4, (n, 1, 1)),
        np.tile(GREEN, (n, 1)).astype(np.float32),
        np.ones((n, 1), np.float32),
    )


def frame(poses: np.ndarray) -> FrameView:
    k = np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])
    blank = np.zeros((60, 80, 3), np.uint8)
    return FrameView(len(poses) - 1, poses, k, blank, blank, blank, blank, "")


def settle(viewer: Open3DViewer) -> None:
    for _ in range(3):  # the pending updates are applied, then drawn
        viewer.call(lambda vis: None)
        time.sleep(0.2)


def press(key: str, times: int = 1) -> None:
    """Real key events to the window (xdotool), as a person would type them."""
    focus = ["xdotool", "search", "--name", "probe", "windowfocus", "--sync"]
    subprocess.run([*focus, "key", "--delay", "50", *[key] * times], check=True)


def main(out: Path, keys: bool) -> None:
    out.mkdir(parents=True, exist_ok=True)
    viewer = Open3DViewer("probe", live=True, width=640, height=480)
    poses = np.stack([np.eye(4)] * 3)
    poses[1, 0, 3], poses[2, 0, 3] = 0.1, 0.2  # the camera moved 20 cm to the right
    viewer.show_map(wall())
    viewer.show_frame(frame(poses))
    settle(viewer)
    report: dict[str, object] = {"clients": viewer.clients()}
    cv2.imwrite(str(out / "open3d-viewer.png"), cv2.cvtColor(viewer.capture(), cv2.COLOR_RGB2BGR))
    if keys:
        press("w", times=10)
        settle(viewer)
        cv2.imwrite(str(out / "open3d-viewer-forward.png"), cv2.cvtColor(viewer.capture(), cv2.COLOR_RGB2BGR))
        press("space")
        settle(viewer)
        report["running_after_space"] = viewer.running.is_set()
    viewer.close()
    report["clients_after_close"] = viewer.clients()
    (out / "report.json").write_text(json.dumps(report))


if __name__ == "__main__":
    main(Path(sys.argv[1]), keys=sys.argv[2] == "keys")
