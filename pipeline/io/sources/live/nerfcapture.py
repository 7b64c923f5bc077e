"""The NeRFCapture iPhone app's live stream over DDS: colour, LiDAR depth and the ARKit pose.

DDS domain 0, topic `Frames`, reliable QoS. The depth buffer is raw float32 metres at the
LiDAR's resolution (lower than colour); `depth_scale` describes the app's 16-bit PNG export
and is not applied. The pose is ARKit's camera-to-world, which this module converts to the
OpenCV camera convention and makes relative to the first frame.

(No `from __future__ import annotations` here: cyclonedds reads the IDL struct's annotations
as real types.)
"""

import asyncio
import functools
import logging
import math
import threading
import time
from collections.abc import AsyncIterator, Collection, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import cyclonedds.idl as idl
import cyclonedds.idl.annotations as annotate
import cyclonedds.idl.types as types
import numpy as np
import torch
from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from pipeline.config import LiveConfig, PoseUse
from pipeline.errors import DataError
from pipeline.frame import Frame
from pipeline.source import SourceCounters

log = logging.getLogger("gsplatam")

DOMAIN_ID = 0  # the app's; `live.dds_domain` chooses another (tests take their own)
TOPIC = "Frames"
POLL_S = 0.2  # the reader waits this long per poll, so a stop is noticed quickly
RECEIVE_BUFFER = "10MB"  # asked for (not required): full-resolution frames overflow the default buffer
ARKIT_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # ARKit camera: y up, z backwards; OpenCV: y down, z forwards


@dataclass
@annotate.final
@annotate.autoid("sequential")
class SplatCaptureFrame(idl.IdlStruct, typename="SplatCaptureData.SplatCaptureFrame"):  # type: ignore[call-arg]
    id: types.uint32
    annotate.key("id")
    timestamp: types.float64
    fl_x: types.float32
    fl_y: types.float32
    cx: types.float32
    cy: types.float32
    transform_matrix: types.array[types.float32, 16]
    width: types.uint32
    height: types.uint32
    image: types.sequence[types.uint8]
    has_depth: bool
    depth_width: types.uint32
    depth_height: types.uint32
    depth_scale: types.float32
    depth_image: types.sequence[types.uint8]


def reliable_qos() -> Qos:
    return Qos(Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1)))


@functools.cache
def _configured_domain(domain_id: int) -> Domain:
    """The DDS domain with the larger socket receive buffer, configured once per process and id
    (cyclonedds refuses a second configuration of a live domain), kept alive for its participants."""
    config = f"<CycloneDDS><Domain id='any'><Internal><SocketReceiveBufferSize max='{RECEIVE_BUFFER}'/></Internal></Domain></CycloneDDS>"
    return Domain(domain_id, config)


_DOMAIN_LOCK = threading.Lock()


def participant(domain_id: int = DOMAIN_ID) -> DomainParticipant:
    with _DOMAIN_LOCK:
        _configured_domain(domain_id)
    return DomainParticipant(domain_id)


def arkit_to_opencv(transform_matrix: Sequence[float]) -> np.ndarray:
    """The message's 16 floats (column-major ARKit camera-to-world) -> [4, 4] float64
    camera-to-world with OpenCV camera axes (P X P^T, P = diag(1, -1, -1, 1))."""
    arkit = np.asarray(transform_matrix, dtype=np.float64).reshape(4, 4).T
    return ARKIT_TO_OPENCV @ arkit @ ARKIT_TO_OPENCV.T


def opencv_to_arkit(c2w: np.ndarray) -> list[float]:
    """The inverse of `arkit_to_opencv`: [4, 4] OpenCV camera-to-world -> 16 column-major floats."""
    arkit = ARKIT_TO_OPENCV.T @ c2w @ ARKIT_TO_OPENCV
    return [float(v) for v in arkit.T.reshape(-1)]


def check_sample(sample: SplatCaptureFrame) -> None:
    """Raise DataError naming what is wrong with a message (sizes, buffers, intrinsics, pose)."""
    if sample.width == 0 or sample.height == 0:
        raise DataError(f"image size {sample.width}x{sample.height}")
    if len(sample.image) != sample.width * sample.height * 3:
        raise DataError(
            f"image holds {len(sample.image)} bytes, {sample.width}x{sample.height} RGB needs {sample.width * sample.height * 3}"
        )
    if sample.depth_width == 0 or sample.depth_height == 0:
        raise DataError(f"depth size {sample.depth_width}x{sample.depth_height}")
    if len(sample.depth_image) != sample.depth_width * sample.depth_height * 4:
        raise DataError(
            f"depth buffer holds {len(sample.depth_image)} bytes, {sample.depth_width}x{sample.depth_height} "
            f"float32 needs {sample.depth_width * sample.depth_height * 4}"
        )
    intrinsics = (sample.fl_x, sample.fl_y, sample.cx, sample.cy)
    if not all(math.isfinite(v) and v > 0 for v in intrinsics):
        raise DataError(f"intrinsics fl_x, fl_y, cx, cy = {intrinsics}")
    if not all(math.isfinite(v) for v in sample.transform_matrix):
        raise DataError("transform_matrix holds NaN or infinite values")


@dataclass
class NeRFCapturePacket:
    """One checked message, with its pose already relative to the first frame of its session."""

    index: int
    timestamp: float  # seconds, the phone's clock
    sample: SplatCaptureFrame
    c2w: np.ndarray  # [4, 4] float64 device camera-to-world (OpenCV axes) relative to its session's first frame
    received_at: float = field(default_factory=time.perf_counter)  # host clock, s
    session: int = 0  # 0 for the first publisher session, +1 at each app restart
    session_start: bool = False  # the first frame of a session after a restart: its pose starts a new world


HANDLE_BITS = 2**64  # publication handles: unsigned in sample infos, signed in the matched list
FOLLOW_SILENT_S = 2.0  # a followed publisher silent this long is left for another (a crashed app stays
# matched until its DDS lease expires, 10 s by default)


class NeRFCaptureSource:
    """Messages from the `Frames` topic, checked, numbered and made relative to the first pose.
    Waits for a publisher indefinitely; bad messages are logged, counted and skipped.

    It follows one publisher at a time: frames of others are ignored (counted in `ignored`)
    while it is there and sending. An app that restarts (a new publisher once the old one has gone, or ids
    from 1 again) starts a new session that continues into the same map: ARKit's world origin
    is new, so that session's first frame brings no pose prior, and its poses are no reference
    for the live ATE (which covers the first session).

    Decoding gives a frame at the colour size: depth resized nearest (no depths mixed across
    edges), intrinsics as sent (they are the colour image's). The device pose becomes the
    tracking prior, the reference for a live ATE, or nothing (`device_pose`)."""

    name = "nerfcapture"
    live = True
    last_index = None

    def __init__(self, device_pose: PoseUse = "initial_guess", domain_id: int = DOMAIN_ID) -> None:
        self.device_pose = device_pose
        self.domain_id = domain_id
        self.counters = SourceCounters()
        self._publisher: int | None = None
        self._heard_at = 0.0  # time.monotonic() of the followed publisher's last message
        self._session = -1
        self._session_start = False
        self._first_inverse: np.ndarray | None = None
        self._last_id: int | None = None
        self._accepted = 0

    async def __aiter__(self) -> AsyncIterator[NeRFCapturePacket]:
        log.debug("nerfcapture: joining DDS domain %d, reading topic '%s'", self.domain_id, TOPIC)
        dp = participant(self.domain_id)
        reader = DataReader(dp, Topic(dp, TOPIC, SplatCaptureFrame), qos=reliable_qos())
        condition = ReadCondition(reader, ViewState.Any | InstanceState.Any | SampleState.NotRead)
        waitset = WaitSet(dp)
        waitset.attach(condition)
        loop = asyncio.get_running_loop()
        with ThreadPoolExecutor(1, thread_name_prefix="dds") as pool:
            waiting_logged = False
            while True:
                samples = await loop.run_in_executor(pool, _wait_and_take, waitset, reader, condition)
                alive = {handle % HANDLE_BITS for handle in reader.get_matched_publications()}
                if bool(alive) != self.counters.connected:
                    log.debug("nerfcapture: %d publishers matched on DDS domain %d", len(alive), self.domain_id)
                self.counters.connected = bool(alive)
                if not samples and not self.counters.connected and not waiting_logged:
                    log.info("nerfcapture: waiting for a publisher on DDS domain %d, topic '%s'", self.domain_id, TOPIC)
                    waiting_logged = True
                for sample in samples:
                    packet = self._accept(sample, sample.sample_info.publication_handle % HANDLE_BITS, alive)
                    if packet is not None:
                        yield packet

    def _accept(self, sample: SplatCaptureFrame, publisher: int, alive: Collection[int]) -> NeRFCapturePacket | None:
        """Check one message from `publisher` (`alive`: the publishers matched now)."""
        self.counters.received += 1
        now = time.monotonic()
        if publisher != self._publisher:
            if self._publisher in alive and now - self._heard_at < FOLLOW_SILENT_S:
                self.counters.ignored += 1
                return None
            self._new_session(f"following publisher {publisher:x}")
            self._publisher = publisher
        self._heard_at = now
        if not sample.has_depth:
            self.counters.skipped += 1
            return None
        if self._last_id is not None and sample.id <= 1 < self._last_id:
            self._new_session(f"ids from {sample.id} again after {self._last_id}: the app restarted")
        try:
            if self._last_id is not None and sample.id <= self._last_id:
                raise DataError(f"id {sample.id} after {self._last_id} (duplicate or out of order)")
            check_sample(sample)
        except DataError as exc:
            self.counters.rejected += 1
            self.counters.last_error = f"frame id {sample.id}: {exc}"
            log.warning("nerfcapture: frame id %d skipped: %s", sample.id, exc)
            return None
        self._last_id = sample.id
        c2w = arkit_to_opencv(sample.transform_matrix)
        if self._first_inverse is None:
            self._first_inverse = np.linalg.inv(c2w)
        start, self._session_start = self._session_start, False
        self._accepted += 1
        return NeRFCapturePacket(
            self._accepted - 1,
            float(sample.timestamp),
            sample,
            self._first_inverse @ c2w,
            session=self._session,
            session_start=start,
        )

    def _new_session(self, why: str) -> None:
        self._session += 1
        self._last_id = None
        self._first_inverse = None
        self._session_start = self._session > 0
        if self._session > 0:
            log.info("nerfcapture: %s; continuing into the same map", why)
        else:
            log.info("nerfcapture: %s", why)

    def decode(self, packet: NeRFCapturePacket) -> Frame | None:
        """-> the frame, or None when it has no valid depth (counted as skipped)."""
        s = packet.sample
        # sequences arrive as lists of ints from DDS (bytes when built locally); bytearray() takes
        # both, and gives the frame a writable buffer (tensors made from it may be written)
        color = np.frombuffer(bytearray(s.image), np.uint8).reshape(s.height, s.width, 3)
        raw = np.frombuffer(bytes(s.depth_image), np.float32).reshape(s.depth_height, s.depth_width)
        depth: np.ndarray = np.where(np.isfinite(raw) & (raw > 0), raw, 0.0).astype(np.float32)
        if not (depth > 0).any():
            self.counters.skipped += 1
            log.warning("nerfcapture: frame id %d skipped: no valid depth", s.id)
            return None
        if depth.shape != color.shape[:2]:
            depth = cv2.resize(depth, (s.width, s.height), interpolation=cv2.INTER_NEAREST)
        intrinsics = np.array([[s.fl_x, 0.0, s.cx], [0.0, s.fl_y, s.cy], [0.0, 0.0, 1.0]])
        prior = self.device_pose == "initial_guess" and not packet.session_start
        return Frame(
            packet.index,
            packet.timestamp,
            color,
            depth,
            intrinsics,
            c2w_gt=packet.c2w if self.device_pose == "groundtruth" and packet.session == 0 else None,
            c2w_prior=packet.c2w if prior else None,
            received_at=packet.received_at,
        )


def _wait_and_take(waitset: WaitSet, reader: DataReader, condition: ReadCondition) -> list[SplatCaptureFrame]:
    """Up to 64 new frames, after waiting at most POLL_S for any. Samples without data (a
    publisher leaving disposes its instances) are dropped."""
    waitset.wait(duration(seconds=POLL_S))
    return [s for s in reader.take(N=64, condition=condition) if isinstance(s, SplatCaptureFrame)]


def sample_from_frame(frame: Frame, frame_id: int, c2w_world: np.ndarray) -> SplatCaptureFrame:
    """A message as the app would send it: colour at the frame's size, depth at half that (the
    LiDAR's resolution is lower), the pose `c2w_world` [4, 4] (OpenCV axes) in ARKit's convention."""
    depth = cv2.resize(frame.depth, (frame.width // 2, frame.height // 2), interpolation=cv2.INTER_NEAREST)
    k = frame.intrinsics
    return SplatCaptureFrame(
        id=frame_id,
        timestamp=frame.timestamp,
        fl_x=float(k[0, 0]),
        fl_y=float(k[1, 1]),
        cx=float(k[0, 2]),
        cy=float(k[1, 2]),
        transform_matrix=opencv_to_arkit(c2w_world),
        width=frame.width,
        height=frame.height,
        image=frame.color.tobytes(),
        has_depth=True,
        depth_width=depth.shape[1],
        depth_height=depth.shape[0],
        depth_scale=10.0,
        depth_image=np.ascontiguousarray(depth, dtype=np.float32).tobytes(),
    )


def open_nerfcapture(address: str, live: LiveConfig, device: torch.device) -> NeRFCaptureSource:
    """`nerfcapture:[DOMAIN]` (sources/cameras.py): the DDS domain given, else `live.dds_domain`."""
    return NeRFCaptureSource(live.device_pose, int(address) if address else live.dds_domain)
