"""RealSense: the SDK (pyrealsense2) plays back the tests' recording and aligns as the bag reader
does; the live source's conversion and faults against a fake camera; the command's exit codes.

No camera is attached here: the SDK's live path (`SdkCamera` on a device) is not run by these tests."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from bag_writers import DepthCamera, TumFolder, write_realsense_bag

from pipeline.app.cli import main
from pipeline.config import DatasetConfig, LiveConfig
from pipeline.io.files.trajectory import pose_from_tum_row
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.tum import DEPTH_SCALE
from pipeline.io.sources.live import realsense
from pipeline.io.sources.live.realsense import (
    AlignedFrames,
    CameraLost,
    CameraStreams,
    RealSensePacket,
    RealSenseSource,
)


def _sdk() -> None:
    try:
        import pyrealsense2  # noqa: F401
    except ImportError as exc:  # no wheel for this platform, or no libusb-1.0
        pytest.skip(f"pyrealsense2 cannot be imported here: {exc}")


def _played(path: Path) -> list[AlignedFrames]:
    """The aligned pairs the SDK plays back from the recording at `path`, in order.

    The SDK's playback fills a small queue as fast as it reads, so on a busy host it may drop a
    pair (it did in CI): the tests match pairs to frames by timestamp, never by position."""
    camera = realsense.SdkCamera("", recording=path)
    camera.start()
    frames = []
    while (pair := camera.wait(2.0)) is not None:
        frames.append(pair)
    camera.stop()
    return frames


def _index_of(timestamp: float, stamps: np.ndarray) -> int:
    """The index of the recorded frame at `timestamp` (s); fails the test when there is none."""
    matches = [i for i, t in enumerate(stamps) if abs(t - timestamp) < 1e-6]
    assert len(matches) == 1, f"no one recorded frame at {timestamp}"
    return matches[0]


def test_the_sdk_plays_the_tests_recording_back(tum_seq: Path, tmp_path: Path) -> None:
    _sdk()
    folder = TumFolder.read(tum_seq)
    path = write_realsense_bag(tmp_path / "d435.bag", folder)
    camera = realsense.SdkCamera("", recording=path)
    streams = camera.start()
    camera.stop()
    assert streams.serial == "123456789012" and streams.name == "Intel RealSense D435"
    assert np.allclose(streams.intrinsics, folder.intrinsics) and streams.depth_units == pytest.approx(1 / DEPTH_SCALE)
    frames = _played(path)
    indices = [_index_of(pair.timestamp, folder.color_t) for pair in frames]
    assert len(frames) >= 2 and indices == sorted(set(indices))  # in order, none twice
    for pair, i in zip(frames, indices):
        color, raw = folder.colors[i], folder.depths[i]
        assert np.array_equal(pair.color, color)
        # one camera: the SDK's align keeps depth where it is, but for rows that float rounding moves by one
        assert (pair.depth == raw)[raw > 0].mean() >= 0.9


@pytest.mark.parametrize("size", [(80, 60, 45.0), (40, 30, 22.0)])  # depth denser than colour, then coarser
def test_a_recordings_depth_is_aligned_to_colour_as_the_sdk_aligns_it(
    size: tuple[int, int, float], tum_seq: Path, tmp_path: Path
) -> None:
    _sdk()
    folder = TumFolder.read(tum_seq)
    width, height, focal = size
    k = np.array([[focal, 0, width / 2 - 0.3], [0, focal * 1.01, height / 2 + 0.2], [0, 0, 1]])
    yy, xx = np.mgrid[0:height, 0:width]
    depths = []
    for i in range(len(folder.depth_t)):
        metres = 1.0 + 0.4 * np.sin(xx / (width / 11) + i) * np.cos(yy / (height / 7)) + 0.002 * xx
        raw = np.round(metres * DEPTH_SCALE).astype(np.uint16)
        raw[height // 3 : height // 3 + 3, width // 3 : width // 2] = 0  # a hole
        depths.append(raw)
    depth_to_color = pose_from_tum_row(np.array([0.015, -0.002, 0.003, 0.01, -0.02, 0.005, 1.0]))
    path = write_realsense_bag(tmp_path / "d435.bag", folder, DepthCamera(k, width, height, depth_to_color), depths)
    dataset = open_dataset(DatasetConfig(path=str(path)))
    ours = [dataset.decode(ref).depth for ref in dataset.refs]
    assert len(ours) == len(folder.colors)
    played = _played(path)
    assert len(played) >= 2
    for pair in played:
        sdk = pair.depth.astype(np.float32) * np.float32(1 / DEPTH_SCALE)
        mine = ours[_index_of(pair.timestamp, folder.color_t)]
        assert (sdk > 0).mean() > 0.5 and np.array_equal(mine, sdk)  # pixel for pixel


class FakeCamera:
    """A camera that streams `frames`, then fails (`then`: a CameraLost) or stalls (None)."""

    def __init__(self, frames: list[AlignedFrames], then: CameraLost | None, fail_start: bool = False) -> None:
        self.frames, self.then, self.fail_start = list(frames), then, fail_start
        self.stopped = False

    def start(self) -> CameraStreams:
        if self.fail_start:
            raise CameraLost("cannot start streaming: Couldn't resolve requests")
        k = np.array([[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]])
        return CameraStreams("123456789012", "Intel RealSense D435", k, 0.001)

    def wait(self, timeout_s: float) -> AlignedFrames | None:
        if self.frames:
            return self.frames.pop(0)
        if self.then is not None:
            raise self.then
        return None

    def stop(self) -> None:
        self.stopped = True


def _frames(count: int) -> list[AlignedFrames]:
    rng = np.random.default_rng(0)
    return [
        AlignedFrames(
            rng.integers(0, 255, (480, 640, 3), dtype=np.uint8),
            np.full((480, 640), 1500 + i, dtype=np.uint16) * (i != 1),  # frame 1: no depth at all
            100.0 + i / 30,
            i + 7,
        )
        for i in range(count)
    ]


def _packets(source: RealSenseSource) -> list[RealSensePacket]:
    async def collect() -> list[RealSensePacket]:
        return [packet async for packet in source]

    return asyncio.run(collect())


def test_frames_are_converted_and_a_lost_camera_ends_the_stream(caplog: pytest.LogCaptureFixture) -> None:
    camera = FakeCamera(_frames(3), CameraLost("Frame didn't arrive within 500"))
    source = RealSenseSource(camera, LiveConfig(), max_width=128)
    packets = _packets(source)
    assert [p.index for p in packets] == [0, 1, 2] and camera.stopped
    assert source.counters.received == 3 and not source.counters.connected and source.counters.stage == "lost"
    assert source.counters.last_error == "camera 123456789012 lost: Frame didn't arrive within 500"
    assert "realsense: camera 123456789012 lost: Frame didn't arrive within 500; the session ends" in caplog.text
    frame = source.decode(packets[0])
    assert frame is not None and frame.color.shape == (60, 80, 3)  # halved until at most 128 wide
    assert frame.timestamp == pytest.approx(100.0)  # the device's clock
    assert np.allclose(frame.depth, 1.5) and frame.depth.dtype == np.float32  # 1500 units of 1 mm
    assert np.allclose(frame.intrinsics, [[50.0, 0, 39.9375], [0, 50.0, 29.9375], [0, 0, 1]])
    assert frame.received_at is not None and frame.c2w_gt is None
    assert source.decode(packets[1]) is None and source.counters.skipped == 1  # no valid depth


def test_a_camera_that_stops_sending_is_lost_after_the_stall_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(realsense, "POLL_S", 0.01)
    source = RealSenseSource(FakeCamera(_frames(1), None), LiveConfig(stall_timeout_s=0.05))
    assert len(_packets(source)) == 1
    assert source.counters.last_error == "camera 123456789012 lost: no frame for 0.05 s (live.stall_timeout_s)"


@pytest.fixture
def fake_camera(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[FakeCamera]]:
    """`realsense:` opens a fake camera (connected: serial 123456789012) that streams 12 frames, then is lost."""
    made: list[FakeCamera] = []

    def camera(serial: str) -> FakeCamera:
        made.append(FakeCamera(_frames(12)[2:], CameraLost("No device connected")))
        return made[-1]

    monkeypatch.setattr(realsense, "connected_serials", lambda: ["123456789012"])
    monkeypatch.setattr(realsense, "SdkCamera", camera)
    yield made


@pytest.mark.slow
def test_a_camera_lost_mid_session_saves_the_run_and_exits_1(
    fake_camera: list[FakeCamera], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["run", "realsense:", "--output", str(tmp_path), "--name", "live", "-q", "--set", "live.status_port=0",
            "--set", "live.record=true", "--device", "cpu", "--set", "live.width=32", "--set", "live.height=24"]  # fmt: skip
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (
        "gsplatam: error: the live source ended (camera 123456789012 lost: No device connected); "
        "what was processed is saved"
    )
    folder = tmp_path / "live"
    for name in ("map.ply", "trajectory.txt", "metrics.json", "checkpoint.safetensors"):
        assert (folder / name).is_file(), name
    assert len((folder / "recording" / "rgb.txt").read_text().splitlines()) >= 2 + 1  # a header, frames decoded
    assert fake_camera[0].stopped


def test_realsense_mistakes_are_one_line_and_exit_2(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = ["--output", str(tmp_path), "-q", "--set", "live.status_port=0"]
    assert main(["run", "realsense:12-34", *out]) == 2
    assert capsys.readouterr().err.strip() == (
        "gsplatam: error: bad serial number in 'realsense:12-34': letters and digits, e.g. realsense:123456789012"
    )
    monkeypatch.setattr(realsense, "connected_serials", lambda: [])
    assert main(["run", "realsense:", *out]) == 2
    assert "no RealSense camera is connected" in capsys.readouterr().err
    monkeypatch.setattr(realsense, "connected_serials", lambda: ["111"])
    assert main(["serve", "--realsense", "222", *out]) == 2
    assert (
        capsys.readouterr().err.strip() == "gsplatam: error: realsense: no camera of serial number 222 (connected: 111)"
    )
    monkeypatch.setattr(realsense, "SdkCamera", lambda serial: FakeCamera([], None, fail_start=True))
    assert main(["run", "realsense:111", *out, "--name", "x"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[-1].endswith("realsense: cannot start streaming: Couldn't resolve requests"), lines
