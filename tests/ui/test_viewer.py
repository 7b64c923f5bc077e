"""The web viewer: map conversion, the SLAM-side feed, and the page in a real headless Chromium."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import ROOT
from live_helpers import free_port, wait_for

from pipeline.config import RenderConfig
from pipeline.frame import DeviceFrame
from pipeline.geometry import quat_to_rotmat
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.render import Gaussians
from pipeline.slam.handoff import FrameResult
from pipeline.ui.viewer_feed import ViewerFeed, map_view

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
ARTIFACTS = Path(os.environ.get("GSPLATAM_TEST_ARTIFACTS", ROOT / "test-artifacts"))


def test_map_view_covariances_are_rotated_squared_scales() -> None:
    quats = torch.tensor([[1.0, 0, 0, 0], [0.9, 0.1, -0.3, 0.2]])
    log_scales = torch.log(torch.tensor([[0.1, 0.1, 0.1], [0.3, 0.2, 0.05]]))
    g = Gaussians(torch.zeros(2, 3), quats, log_scales, torch.tensor([0.0, 2.0]), torch.tensor([[0.5, 1.2, -0.1]] * 2))
    view = map_view(g)
    assert np.allclose(view.covariances[0], 0.01 * np.eye(3), atol=1e-7)
    rotation = quat_to_rotmat(quats[1]).numpy()
    assert np.allclose(rotation.T @ view.covariances[1] @ rotation, np.diag([0.09, 0.04, 0.0025]), atol=1e-6)
    assert np.allclose(view.opacities[:, 0], [0.5, 1 / (1 + np.exp(-2.0))])
    assert view.rgbs.max() <= 1.0 and view.rgbs.min() >= 0.0


class FakeViewer:
    """What ViewerFeed needs of a Viewer, recording what it is shown."""

    def __init__(self) -> None:
        import threading

        self.running = threading.Event()
        self.running.set()
        self.save_requested = threading.Event()
        self.stopped = threading.Event()
        self.watching = 1
        self.maps: list = []
        self.frames: list = []
        self.saved: list[str] = []
        self.summary = ""

    def clients(self) -> int:
        return self.watching

    def show_saved(self, message: str) -> None:
        self.saved.append(message)

    def show_summary(self, markdown: str) -> None:
        self.summary = markdown

    def show_map(self, view) -> None:
        self.maps.append(view)

    def show_frame(self, view) -> None:
        self.frames.append(view)

    def close(self) -> None:
        pass


class FakeSlam:
    """What the feed reads of SLAM: the published map and the poses."""

    def __init__(self, gaussians: Gaussians) -> None:
        self.gaussians = gaussians
        self.poses = [torch.eye(4)]


def _frame(index: int) -> DeviceFrame:
    k = torch.tensor([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    return DeviceFrame(index, 0.0, torch.rand(12, 16, 3), torch.full((12, 16), 2.0), k, None)


def _result(index: int) -> FrameResult:
    seconds = {"tracking": 0.01, "densify": 0.0, "mapping": 0.02, "total": 0.03}
    return FrameResult(index, 0.0, torch.eye(4), seconds, 10, 0, 0.0, 1.0)


@pytest.fixture
def slam_like() -> FakeSlam:
    n = 10
    means = torch.rand(n, 3) + torch.tensor([0.0, 0.0, 2.0])
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    return FakeSlam(Gaussians(means, quats, torch.full((n, 1), -3.0), torch.zeros(n), torch.rand(n, 3)))


def _renderer():
    from pipeline.config import GaussianConfig
    from pipeline.render import make_renderer

    return make_renderer(RenderConfig(), GaussianConfig(), torch.device("cpu"))


def test_the_feed_is_rate_limited_and_shows_what_slam_had(slam_like: FakeSlam, tmp_path: Path) -> None:
    viewer = FakeViewer()
    feed = ViewerFeed(viewer, _renderer(), RenderConfig(), max_hz=1000.0, folder=RunFolder(tmp_path))
    feed(slam_like, _frame(0), _result(0))
    deadline = time.monotonic() + 10
    while not viewer.frames and time.monotonic() < deadline:
        time.sleep(0.01)
    slam_like.gaussians.means.add_(1.0)  # SLAM moves on; the snapshot must not change
    feed.close()
    assert len(viewer.maps) == 1 and viewer.frames[0].index == 0
    assert viewer.maps[0].centers[:, 2].max() < 3.0
    assert viewer.frames[0].rendered_depth.shape == (12, 16, 3) and "frame 0" in viewer.frames[0].stats

    slow = ViewerFeed(FakeViewer(), _renderer(), RenderConfig(), max_hz=0.001, folder=RunFolder(tmp_path))
    for i in range(20):
        slow(slam_like, _frame(i), _result(i))
    slow.close()
    assert slow.snapshots == 1


def test_pause_holds_slam_at_the_frame_boundary_until_resumed_or_stopped(slam_like: FakeSlam, tmp_path) -> None:
    import threading

    viewer = FakeViewer()
    feed = ViewerFeed(viewer, _renderer(), RenderConfig(), max_hz=0.001, folder=RunFolder(tmp_path))
    viewer.running.clear()
    done = threading.Event()
    worker = threading.Thread(target=lambda: (feed(slam_like, _frame(0), _result(0)), done.set()))
    worker.start()
    assert not done.wait(0.5)
    viewer.running.set()
    assert done.wait(5)
    viewer.running.clear()
    done.clear()
    worker = threading.Thread(target=lambda: (feed(slam_like, _frame(1), _result(1)), done.set()))
    worker.start()
    assert not done.wait(0.3)
    feed.released.set()  # the run was asked to stop
    assert done.wait(5)
    feed.close()


def test_save_now_writes_the_map_without_waiting_for_the_end(slam_like: FakeSlam, tmp_path: Path) -> None:
    viewer = FakeViewer()
    folder = RunFolder(tmp_path)
    feed = ViewerFeed(viewer, _renderer(), RenderConfig(), max_hz=0.001, folder=folder)
    viewer.save_requested.set()
    feed(slam_like, _frame(0), _result(0))
    feed.close()  # at once: closing waits for the requested save and its confirmation
    assert folder.map.exists() and not viewer.save_requested.is_set()
    assert len(viewer.saved) == 1 and viewer.saved[0].startswith("saved 10 Gaussians to ")  # confirmed in the page


def _wait(predicate, seconds: float = 10.0) -> None:
    deadline = time.monotonic() + seconds
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.02)


def test_finish_shows_the_final_frame_and_map_even_between_snapshots(slam_like: FakeSlam, tmp_path: Path) -> None:
    viewer = FakeViewer()
    feed = ViewerFeed(viewer, _renderer(), RenderConfig(), max_hz=0.001, folder=RunFolder(tmp_path), map_every_s=1e9)
    for i in range(4):
        feed(slam_like, _frame(i), _result(i))
    _wait(lambda: len(viewer.frames) == 1)
    assert [f.index for f in viewer.frames] == [0] and len(viewer.maps) == 1  # rate-limited: frames 1-3 not shown
    slam_like.gaussians.means.add_(1.0)
    feed.finish()
    _wait(lambda: len(viewer.frames) == 2)
    feed.close()
    assert viewer.frames[-1].index == 3 and len(viewer.maps) == 2  # the final map, though maps were rate-limited
    assert viewer.maps[-1].centers[:, 2].min() > 2.9  # as SLAM left it
    assert feed.released.is_set()


def test_linger_waits_for_stop_or_for_the_watchers_to_leave(slam_like: FakeSlam, tmp_path: Path, monkeypatch) -> None:
    import threading

    import pipeline.ui.viewer_feed as viewer_feed

    viewer = FakeViewer()
    feed = ViewerFeed(viewer, _renderer(), RenderConfig(), max_hz=0.001, folder=RunFolder(tmp_path))
    viewer.watching = 0
    feed.linger("**run finished**")  # nobody watches: no wait
    assert viewer.summary == "**run finished**"

    viewer.watching = 1
    done = threading.Event()
    worker = threading.Thread(target=lambda: (feed.linger("done"), done.set()))
    worker.start()
    assert not done.wait(0.8)  # someone watches: the final map stays
    viewer.stopped.set()  # Stop pressed
    assert done.wait(5)

    monkeypatch.setattr(viewer_feed, "RECONNECT_GRACE_S", 0.5)
    viewer.stopped.clear()
    done.clear()
    worker = threading.Thread(target=lambda: (feed.linger("done"), done.set()))
    worker.start()
    assert not done.wait(0.8)
    viewer.watching = 0  # the page was closed
    assert done.wait(5)
    feed.close()
    feed.close()  # idempotent


def test_the_follow_view_sits_behind_and_above_the_camera() -> None:
    from pipeline.ui.display import follow_pose

    c2w = np.eye(4)
    c2w[:3, :3] = cv2.Rodrigues(np.array([0.1, 0.7, -0.2]))[0]
    c2w[:3, 3] = [1.0, 2.0, 3.0]
    view = follow_pose(c2w, back_m=0.6, up_m=0.25)
    assert np.allclose(view[:3, :3], c2w[:3, :3])  # looking the same way
    offset = np.linalg.inv(c2w)[:3, :3] @ (view[:3, 3] - c2w[:3, 3])  # in the camera's axes (y down, z forward)
    assert np.allclose(offset, [0.0, -0.25, -0.6])


@pytest.fixture
def browser():
    """Headless Chromium, closed whatever the test does (Playwright's sync API holds an event loop
    in this thread until it stops: left running, it breaks every later asyncio test)."""
    if CHROMIUM is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install chromium; .ci/run installs it)")
    playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    manager = playwright_api.sync_playwright().start()
    try:
        chromium = manager.chromium.launch(
            executable_path=CHROMIUM,
            args=["--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        try:
            yield chromium
        finally:
            chromium.close()
    finally:
        manager.stop()


def _frame_number(page) -> int | None:
    match = re.search(r"frame (\d+)", page.inner_text("body"))
    return int(match.group(1)) if match else None


def _canvas_is_drawn(page, path: Path) -> bool:
    """Whether the 3D canvas shows something, from one screenshot of the page kept at `path`
    (software WebGL makes each screenshot cost seconds)."""
    box = page.locator("canvas").first.bounding_box()
    page.screenshot(path=str(path))
    image = cv2.imread(str(path))
    if image is None or box is None:
        return False
    x, y, w, h = (round(box[k]) for k in ("x", "y", "width", "height"))
    return float(image[y : y + h, x : x + w].std()) > 5.0


@pytest.mark.slow
@pytest.mark.live
def test_the_viewer_in_headless_chromium_follows_a_run_and_shows_its_map(browser, tmp_path: Path) -> None:
    port = free_port()
    log_path = tmp_path / "run.log"
    command = [
        sys.executable, "-m", "pipeline", "run", "--device", "cpu", "--preset", "tiny", "--output", str(tmp_path),
        "--name", "viewed", "--quiet", "--viewer", "--viewer-port", str(port),
        "--set", "synthetic.width=64", "--set", "synthetic.height=48", "--set", "synthetic.frames=100",
    ]  # fmt: skip
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w") as log_file:
        run = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT)
    try:
        page = browser.new_page(viewport={"width": 960, "height": 600})
        wait_for(lambda: "viewer:" in log_path.read_text(), 120, "the viewer to start", log_path)
        page.goto(f"http://127.0.0.1:{port}", timeout=60_000)
        page.wait_for_selector("canvas", timeout=60_000)
        wait_for(lambda: (_frame_number(page) or 0) >= 2, 120, "frame 2 in the page", log_path)
        first = _frame_number(page)
        wait_for(lambda: (_frame_number(page) or 0) > (first or 0), 60, "the frame counter to advance", log_path)
        wait_for(lambda: _canvas_is_drawn(page, ARTIFACTS / "viewer-run.png"), 30, "splats on the canvas", log_path)
        page.get_by_text("Stop").click()
        assert run.wait(timeout=120) == 0, log_path.read_text()[-3000:]
        page.close()  # its viewer is gone: left open, it keeps reconnecting and slows the next page
    finally:
        if run.poll() is None:
            run.send_signal(signal.SIGINT)
            run.wait(timeout=60)
    metrics = json.loads((tmp_path / "viewed" / "metrics.json").read_text())
    assert metrics["interrupted"] and metrics["frames"] >= 3

    port = free_port()
    view_log = tmp_path / "view.log"
    with open(view_log, "w") as log_file:
        viewing = subprocess.Popen(
            [sys.executable, "-m", "pipeline", "view", str(tmp_path / "viewed"), "--viewer-port", str(port)],
            stdout=log_file,
            stderr=subprocess.STDOUT,
        )
    try:
        wait_for(lambda: "showing" in view_log.read_text(), 60, "the view command", view_log)
        page = browser.new_page(viewport={"width": 960, "height": 600})
        page.goto(f"http://127.0.0.1:{port}", timeout=60_000)
        wait_for(lambda: "Gaussians from" in page.inner_text("body"), 60, "the map's stats", view_log)
        wait_for(lambda: _canvas_is_drawn(page, ARTIFACTS / "viewer-saved-map.png"), 30, "the saved map", view_log)
    finally:
        viewing.send_signal(signal.SIGINT)
        assert viewing.wait(timeout=30) == 0


def test_view_rejects_a_missing_map(tmp_path: Path, capsys) -> None:
    from pipeline.app.cli import main

    assert main(["view", str(tmp_path)]) == 2
    assert "no map to show" in capsys.readouterr().err


def test_a_common_3dgs_ply_with_extra_properties_is_viewable(tmp_path: Path) -> None:
    from pipeline.io.outputs.ply import read_ply, write_ply

    n = 5
    g = Gaussians(torch.rand(n, 3), torch.rand(n, 4), torch.rand(n, 3) - 3, torch.rand(n), torch.rand(n, 3))
    write_ply(tmp_path / "ours.ply", g)
    header, body = (tmp_path / "ours.ply").read_bytes().split(b"end_header\n")
    table = np.frombuffer(body, "<f4").reshape(n, -1)
    extra = np.concatenate([table, np.zeros((n, 45), "<f4")], axis=1)  # f_rest_0..44, as 3DGS training writes
    names = [line for line in header.decode().splitlines() if line.startswith("property")]
    rest = [f"property float f_rest_{i}" for i in range(45)]
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {n}", *names, *rest, "end_header"]
    (tmp_path / "3dgs.ply").write_bytes(("\n".join(lines) + "\n").encode() + extra.tobytes())
    view = map_view(read_ply(tmp_path / "3dgs.ply"))
    assert np.allclose(view.centers, replace(g).means.numpy(), atol=1e-6)


def test_the_web_viewer_takes_a_frame_a_save_and_the_summary_without_a_browser() -> None:
    from pipeline.ui.display import FrameView
    from pipeline.ui.viewer import Viewer

    viewer = Viewer("127.0.0.1", free_port(), "test")
    try:
        image = np.zeros((12, 16, 3), np.uint8)
        poses = np.stack([np.eye(4), np.eye(4)])
        poses[1, 0, 3] = 0.1
        k = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
        viewer.show_frame(FrameView(1, poses, k, image, image, image, image, "**frame 1**"))
        viewer.show_saved("saved 10 Gaussians to map.ply")
        assert viewer.save_status.content == "saved 10 Gaussians to map.ply"
        viewer.show_summary("**run finished**")
        assert viewer.stats.content == "**run finished**" and viewer.clients() == 0
        viewer.request_stop()  # after the run: closes the viewer, sends no signal
        assert viewer.stopped.is_set()
    finally:
        viewer.close()


def test_sigint_stops_a_command_started_with_sigint_ignored(tmp_path: Path) -> None:
    """A shell's background job starts with SIGINT ignored; the command still stops on it, as
    the README promises (here `view`, which waits for Ctrl-C)."""
    from pipeline.io.outputs.ply import write_ply

    one = Gaussians(
        torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.zeros(1, 1), torch.zeros(1), torch.zeros(1, 3)
    )
    write_ply(tmp_path / "map.ply", one)
    log_path = tmp_path / "view.log"
    with open(log_path, "w") as log_file:
        viewing = subprocess.Popen(
            [sys.executable, "-m", "pipeline", "view", str(tmp_path / "map.ply"), "--viewer-port", str(free_port())],
            stdout=log_file,
            stderr=subprocess.STDOUT,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
        )
    try:
        wait_for(lambda: "showing" in log_path.read_text(), 60, "the view command", log_path)
        viewing.send_signal(signal.SIGINT)
        assert viewing.wait(timeout=30) == 0, log_path.read_text()[-3000:]
    finally:
        viewing.kill()
