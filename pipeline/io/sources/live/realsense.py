"""Intel RealSense depth cameras live, through the vendor's SDK (pyrealsense2, the `realsense`
extra): `realsense:[SERIAL]`, the camera of that serial number or the first one connected.

The camera streams depth (Z16) and colour (RGB8) at STREAM_MODE; the SDK aligns each depth frame
to its colour frame (`rs2::align`), so a frame is colour with depth in the colour camera, the
colour stream's intrinsics and the depth sensor's units (metres per Z16 step), stamped by the
device's clock. Frames are resized to the working size as every live source's (`live.width` x
`live.height`, or halved to what suits the compute device).

The SDK is behind `Camera` (start, wait for the next aligned pair, stop), so the source's
conversion and fault handling run in the tests against a fake one, and the SDK's side against
the SDK playing a recording back (`SdkCamera(..., recording=PATH)`). A camera that stops sending
(unplugged, a USB reset) for `live.stall_timeout_s` or fails in the SDK ends the stream: one line
says so, the session saves as at Ctrl-C, and the command ends with exit code 1.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from pipeline.config import LiveConfig
from pipeline.devices import live_max_width
from pipeline.errors import UserError
from pipeline.frame import Frame
from pipeline.io.files.images import halved_to, resize_rgbd
from pipeline.source import SourceCounters

log = logging.getLogger("gsplatam")

STREAM_MODE = (640, 480, 30)  # width, height, frames/s of both streams: every D400 camera's
POLL_S = 0.5  # the wait for a frame, so a stop is noticed quickly and a stall is timed


class CameraLost(Exception):
    """The camera stopped streaming (unplugged, reset, an SDK error): the stream ends."""


@dataclass(frozen=True)
class CameraStreams:
    """What a started camera streams."""

    serial: str
    name: str
    intrinsics: np.ndarray  # [3, 3] the colour stream's, pixels (depth is aligned to it)
    depth_units: float  # metres per Z16 step


@dataclass(frozen=True)
class AlignedFrames:
    """One colour frame and the depth aligned to it, copied out of the SDK's buffers."""

    color: np.ndarray  # [H, W, 3] uint8 RGB
    depth: np.ndarray  # [H, W] uint16 in depth units, 0 = none
    timestamp: float  # seconds, the device's clock
    number: int  # the device's frame counter


class Camera(Protocol):
    """A RealSense camera (or a recording played as one) as the source uses it."""

    def start(self) -> CameraStreams: ...

    def wait(self, timeout_s: float) -> AlignedFrames | None:
        """The next aligned pair, or None after `timeout_s` without one; CameraLost when it fails."""
        ...

    def stop(self) -> None: ...


class SdkCamera:
    """A camera through pyrealsense2: the one of serial number `serial`, or the recording at
    `recording` played back in order, as fast as it is read rather than in real time.

    The SDK plays a recording into the same small frame queue a camera fills, so a reader that
    falls behind the playback still loses frames: the bag reader (`open_dataset`) is the lossless
    way to read a recording; this path is the SDK's own reading, kept to check ours against."""

    def __init__(self, serial: str, recording: Path | None = None) -> None:
        import pyrealsense2 as rs

        self.rs = rs
        self.serial = serial
        self.recording = recording
        self.context = rs.context()
        self.pipeline = rs.pipeline(self.context)
        self.align = rs.align(rs.stream.color)

    def start(self) -> CameraStreams:
        rs, config = self.rs, self.rs.config()
        width, height, fps = STREAM_MODE
        try:
            if self.recording is not None:
                # non-real-time before the playback starts: set after `start` (the SDK's examples),
                # the first frames are already playing in real time and a busy host drops them
                playback = self.context.load_device(str(self.recording)).as_playback()
                playback.set_real_time(False)
                config.enable_device(playback.get_info(rs.camera_info.serial_number))
            else:
                config.enable_device(self.serial)
                config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
                config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
            profile = self.pipeline.start(config)
        except RuntimeError as exc:
            raise CameraLost(f"cannot start streaming: {exc}") from None
        device = profile.get_device()
        color = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
        k = np.array([[color.fx, 0.0, color.ppx], [0.0, color.fy, color.ppy], [0.0, 0.0, 1.0]])
        info = rs.camera_info
        serial = device.get_info(info.serial_number) if device.supports(info.serial_number) else self.serial
        name = device.get_info(info.name) if device.supports(info.name) else "RealSense"
        return CameraStreams(serial, name, k, float(device.first_depth_sensor().get_depth_scale()))

    def wait(self, timeout_s: float) -> AlignedFrames | None:
        try:
            ok, frames = self.pipeline.try_wait_for_frames(int(timeout_s * 1000))
            if not ok:
                return None
            aligned = self.align.process(frames)
            depth, color = aligned.get_depth_frame(), aligned.get_color_frame()
            if not depth or not color:
                return None
            return AlignedFrames(
                np.asanyarray(color.get_data()).copy(),
                np.asanyarray(depth.get_data()).copy(),
                color.get_timestamp() / 1000.0,
                int(color.get_frame_number()),
            )
        except RuntimeError as exc:  # the SDK's errors (a device that went away)
            raise CameraLost(str(exc)) from None

    def stop(self) -> None:
        try:
            self.pipeline.stop()
        except RuntimeError as exc:  # never started, or already gone
            log.debug("realsense: stopping: %s", exc)


@dataclass
class RealSensePacket:
    """One aligned pair, not yet converted (conversion runs in the decode stage's threads)."""

    index: int
    frames: AlignedFrames
    streams: CameraStreams
    received_at: float = field(default_factory=time.perf_counter)  # host clock, s


class RealSenseSource:
    """Aligned frames from one camera until it stops. Live: the runtime's queues keep the newest
    frames when SLAM falls behind. `size` (width, height) is the working size; None: the
    camera's, halved until at most `max_width` wide (0: no limit)."""

    name = "realsense"
    live = True
    last_index = None

    def __init__(
        self, camera: Camera, config: LiveConfig, size: tuple[int, int] | None = None, max_width: int = 0
    ) -> None:
        self.camera = camera
        self.config = config
        self.size = size
        self.max_width = max_width
        self.counters = SourceCounters()

    async def __aiter__(self) -> AsyncIterator[RealSensePacket]:
        loop = asyncio.get_running_loop()
        with ThreadPoolExecutor(1, thread_name_prefix="realsense") as pool:
            try:
                streams = await loop.run_in_executor(pool, self.camera.start)
            except CameraLost as exc:
                raise UserError(f"realsense: {exc}") from None
            try:
                log.info("realsense: %s %s streaming", streams.name, streams.serial)
                self.counters.connected, self.counters.connections, self.counters.stage = True, 1, "streaming"
                async for packet in self._packets(loop, pool, streams):
                    yield packet
            finally:
                self.counters.connected = False
                await loop.run_in_executor(pool, self.camera.stop)

    async def _packets(
        self, loop: asyncio.AbstractEventLoop, pool: ThreadPoolExecutor, streams: CameraStreams
    ) -> AsyncIterator[RealSensePacket]:
        """Packets until the camera is lost (then the stream ends, the loss in `counters`)."""
        heard = time.monotonic()
        try:
            while True:
                frames = await loop.run_in_executor(pool, self.camera.wait, POLL_S)
                if frames is not None:
                    heard = time.monotonic()
                    self.counters.received += 1
                    yield RealSensePacket(self.counters.received - 1, frames, streams)
                elif time.monotonic() - heard >= self.config.stall_timeout_s:
                    raise CameraLost(f"no frame for {self.config.stall_timeout_s:g} s (live.stall_timeout_s)")
        except CameraLost as exc:
            self.counters.stage = "lost"
            self.counters.last_error = f"camera {streams.serial} lost: {exc}"
            log.error("realsense: %s; the session ends and saves", self.counters.last_error)

    def decode(self, packet: RealSensePacket) -> Frame | None:
        """-> the frame at the working size, or None without any valid depth (counted as skipped)."""
        frames = packet.frames
        if not frames.depth.any():
            self.counters.skipped += 1
            log.warning("realsense: frame %d skipped: no valid depth", frames.number)
            return None
        depth = (frames.depth.astype(np.float32) * np.float32(packet.streams.depth_units)).astype(np.float32)
        if self.size is None:
            self.size = halved_to(frames.color.shape[1], frames.color.shape[0], self.max_width)
        color, depth, intrinsics = resize_rgbd(frames.color, depth, packet.streams.intrinsics, self.size)
        return Frame(packet.index, frames.timestamp, color, depth, intrinsics, None, received_at=packet.received_at)


def connected_serials() -> list[str]:
    """The serial numbers of the RealSense cameras connected now."""
    import pyrealsense2 as rs

    return [device.get_info(rs.camera_info.serial_number) for device in rs.context().query_devices()]


def open_realsense(address: str, live: LiveConfig, device: torch.device) -> RealSenseSource:
    """`realsense:[SERIAL]` (sources/cameras.py): UserError when no such camera is connected."""
    serials = connected_serials()
    if not serials:
        raise UserError("realsense: no RealSense camera is connected (see docs/cameras.md, troubleshooting)")
    if address and address not in serials:
        raise UserError(f"realsense: no camera of serial number {address} (connected: {', '.join(serials)})")
    size = (live.width, live.height) if live.width else None
    return RealSenseSource(SdkCamera(address or serials[0]), live, size, live_max_width(device))
