"""The Open3D desktop viewer in a real window under Xvfb: what it draws, its keys, and a live run."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import ROOT, needs_extra
from live_helpers import wait_for

from pipeline.ui.open3d_viewer import TRAJECTORY_RGB, frustum_lines

GREEN = (0.1, 0.9, 0.2)  # the probe's map
XVFB = shutil.which("Xvfb")
XDOTOOL = shutil.which("xdotool")
ARTIFACTS = Path(os.environ.get("GSPLATAM_TEST_ARTIFACTS", ROOT / "test-artifacts"))
PROBE = Path(__file__).with_name("open3d_probe.py")


def test_a_frustum_has_its_eye_and_the_image_corners_at_the_given_depth() -> None:
    k = np.array([[50.0, 0, 40], [0, 50.0, 30], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    lines = frustum_lines(c2w, k, 80, 60, depth_m=0.5)
    assert lines.shape == (8, 2, 3)
    assert np.allclose(lines[:4, 0], [1.0, 2.0, 3.0])  # four edges from the eye
    corners = lines[:4, 1] - c2w[:3, 3]
    assert np.allclose(corners[:, 2], 0.5)
    assert np.allclose(corners[0, :2], [-40 / 50 * 0.5, -30 / 50 * 0.5]) and np.allclose(corners[2, :2], [0.4, 0.3])


@pytest.fixture(scope="module")
def display() -> Iterator[str]:
    """An X display of Xvfb's own (it picks a free number and says which)."""
    if XVFB is None:
        pytest.skip("Xvfb is not installed (Debian: apt-get install xvfb; .ci/run installs it)")
    needs_extra("open3d")
    read, write = os.pipe()
    server = subprocess.Popen(
        [XVFB, "-displayfd", str(write), "-screen", "0", "1280x800x24", "-nolisten", "tcp"],
        pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    os.close(write)
    with os.fdopen(read) as announced:
        number = announced.readline().strip()
    if not number:
        server.kill()
        pytest.skip("Xvfb did not start")
    try:
        yield f":{number}"
    finally:
        server.terminate()
        server.wait(timeout=10)


def _env(display: str) -> dict[str, str]:
    return {**os.environ, "DISPLAY": display, "PYTHONPATH": f"{ROOT}{os.pathsep}{ROOT / 'tests'}"}


def _probe(display: str, out: Path, keys: bool) -> dict:
    done = subprocess.run(
        [sys.executable, str(PROBE), str(out), "keys" if keys else "still"],
        env=_env(display), capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads((out / "report.json").read_text())


def _mask(image: np.ndarray, rgb: tuple[float, float, float], tolerance: int) -> np.ndarray:
    """[H, W] pixels of a BGR image within `tolerance` of colour `rgb` in [0, 1]."""
    return np.abs(image.astype(np.float64) - np.array(rgb[::-1]) * 255).max(axis=2) <= tolerance


def _share(image: np.ndarray, rgb: tuple[float, float, float], tolerance: int = 40) -> float:
    return float(_mask(image, rgb, tolerance).mean())


def _span(image: np.ndarray, rgb: tuple[float, float, float]) -> float:
    """Width in pixels of the region of that colour (points are drawn at a fixed pixel size, so
    how many pixels they cover does not grow as the view comes closer; their spread does)."""
    columns = np.nonzero(_mask(image, rgb, 40).any(axis=0))[0]
    return float(columns.max() - columns.min()) if len(columns) else 0.0


@pytest.mark.live
def test_the_window_draws_the_map_the_path_and_the_frustum(display: str, tmp_path: Path) -> None:
    report = _probe(display, tmp_path, keys=False)
    image = cv2.imread(str(tmp_path / "open3d-viewer.png"))
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    shutil.copy(tmp_path / "open3d-viewer.png", ARTIFACTS / "open3d-viewer.png")
    assert image.shape[:2] == (480, 640)
    assert _share(image, GREEN) > 0.05  # the green wall of Gaussian centres
    assert _share(image, TRAJECTORY_RGB, tolerance=60) > 0.0005  # the trajectory and the frustum's lines
    assert report == {"clients": 1, "clients_after_close": 0}


@pytest.mark.live
def test_keys_move_the_view_and_pause_slam(display: str, tmp_path: Path) -> None:
    if XDOTOOL is None:
        pytest.skip("xdotool is not installed (Debian: apt-get install xdotool; .ci/run installs it)")
    report = _probe(display, tmp_path, keys=True)
    before = cv2.imread(str(tmp_path / "open3d-viewer.png"))
    after = cv2.imread(str(tmp_path / "open3d-viewer-forward.png"))
    assert _span(after, GREEN) > 1.1 * _span(before, GREEN)  # W: forward, the wall looks wider
    assert report["running_after_space"] is False


@pytest.mark.slow
@pytest.mark.live
def test_a_run_with_the_open3d_viewer_keeps_the_final_map_until_interrupted(display: str, tmp_path: Path) -> None:
    log_path = tmp_path / "run.log"
    command = [
        sys.executable, "-m", "pipeline", "run", "--device", "cpu", "--preset", "tiny", "--output", str(tmp_path),
        "--name", "o3d", "--quiet", "--viewer", "open3d",
        "--set", "synthetic.width=48", "--set", "synthetic.height=32", "--set", "synthetic.frames=3",
    ]  # fmt: skip
    with open(log_path, "w") as log_file:
        run = subprocess.Popen(command, env=_env(display), stdout=log_file, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: "the final map stays up" in log_path.read_text(), 300, "the end of the run", log_path)
        time.sleep(1.0)
        assert run.poll() is None  # the window is still up, with the final map
        run.send_signal(signal.SIGINT)
        assert run.wait(timeout=60) == 0, log_path.read_text()[-3000:]
    finally:
        if run.poll() is None:
            run.kill()
    assert json.loads((tmp_path / "o3d" / "metrics.json").read_text())["frames"] == 3
