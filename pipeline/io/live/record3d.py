"""The Record3D iPhone app's Wi-Fi stream: HTTP signalling, an aiortc receiver, and the live
source that reconnects with back-off.

The phone serves HTTP on port 80: `GET /getOffer` -> {"type": "offer", "sdp": ...} (403 while
another receiver is connected), `POST /answer` {"type": "answer", "data": <sdp>} (older apps:
`/sendAnswer`), `GET /metadata` -> {"K": [...], "originalSize": [w, h]}. ICE is not trickled;
aiortc's `setLocalDescription` gathers every candidate before the answer is sent.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

import aiohttp
import av
from aiortc import RTCConfiguration, RTCPeerConnection, RTCSessionDescription
from aiortc.contrib.media import MediaBlackhole
from aiortc.mediastreams import MediaStreamError, MediaStreamTrack

from pipeline.config import LiveConfig
from pipeline.errors import DataError
from pipeline.frame import Frame
from pipeline.io.images import resize_rgbd
from pipeline.io.live.record3d_format import intrinsics_from_metadata, unpack_frame
from pipeline.source import SourceCounters

log = logging.getLogger("gsplatam")

HTTP_TIMEOUT_S = 5.0


class PhoneError(Exception):
    """The phone could not be used this time; the source logs it and retries."""


class PhoneUnreachable(PhoneError):
    pass


class PhoneBusy(PhoneError):
    pass


class ProtocolError(PhoneError):
    pass


class StreamEnded(PhoneError):
    pass


def no_stun() -> RTCConfiguration:
    """Host candidates only: the phone is on the local network, and aiortc's default STUN
    server is on the internet (unreachable offline, slow to time out)."""
    return RTCConfiguration(iceServers=[])


async def _get_json(http: aiohttp.ClientSession, url: str) -> Any:
    try:
        async with http.get(url) as response:
            if response.status == 403:
                raise PhoneBusy(f"{url}: HTTP 403, the phone is streaming to another receiver")
            if response.status != 200:
                raise ProtocolError(f"{url}: HTTP {response.status} {(await response.text())[:120]!r}")
            text = await response.text()
    except (aiohttp.ClientConnectionError, TimeoutError) as exc:
        raise PhoneUnreachable(f"{url}: cannot connect ({exc.__class__.__name__}: {exc})") from exc
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProtocolError(f"{url}: malformed JSON ({exc}): {text[:80]!r}") from exc


async def _post_answer(http: aiohttp.ClientSession, base: str, sdp: str) -> None:
    body = {"type": "answer", "data": sdp}
    for path in ("/answer", "/sendAnswer"):
        try:
            async with http.post(base + path, json=body) as response:
                if response.status == 404:
                    continue
                if response.status >= 300:
                    raise ProtocolError(f"{base}{path}: HTTP {response.status} {(await response.text())[:120]!r}")
                return
        except (aiohttp.ClientConnectionError, TimeoutError) as exc:
            raise PhoneUnreachable(f"{base}{path}: cannot connect ({exc})") from exc
    raise ProtocolError(f"{base}: neither /answer nor /sendAnswer exists (HTTP 404)")


@dataclass
class Record3DSession:
    """One connection to the phone, from signalling to the last frame; `close()` is idempotent
    and must run, or the phone answers 403 to the next receiver."""

    url: str
    config: LiveConfig
    metadata: dict[str, Any] = field(default_factory=dict)
    _pc: RTCPeerConnection | None = None
    _video: asyncio.Future[MediaStreamTrack] | None = None
    _sinks: list[MediaBlackhole] = field(default_factory=list)
    _sink_starts: list[asyncio.Task[None]] = field(default_factory=list)  # held: the loop keeps only weak refs

    async def open(self) -> None:
        timeout = aiohttp.ClientTimeout(total=HTTP_TIMEOUT_S)
        async with aiohttp.ClientSession(timeout=timeout) as http:
            self.metadata = await _get_json(http, self.url + "/metadata")
            try:
                intrinsics_from_metadata(self.metadata, 1)
            except DataError as exc:
                raise ProtocolError(f"{self.url}/metadata: {exc}") from exc
            offer = await _get_json(http, self.url + "/getOffer")
            if not isinstance(offer, dict) or not isinstance(offer.get("sdp"), str) or offer.get("type") != "offer":
                raise ProtocolError(f"{self.url}/getOffer: expected {{'type': 'offer', 'sdp': ...}}, got {offer!r:.80}")
            if "m=video" not in offer["sdp"]:
                raise ProtocolError(f"{self.url}/getOffer: the offer has no video track")
            self._pc = pc = RTCPeerConnection(no_stun())
            self._video = asyncio.get_running_loop().create_future()
            pc.on("track", self._on_track)
            try:
                await pc.setRemoteDescription(RTCSessionDescription(offer["sdp"], "offer"))
                await pc.setLocalDescription(await pc.createAnswer())
            except ValueError as exc:
                raise ProtocolError(f"{self.url}/getOffer: unusable offer SDP ({exc})") from exc
            await _post_answer(http, self.url, pc.localDescription.sdp)

    def _on_track(self, track: MediaStreamTrack) -> None:
        if track.kind == "video" and self._video is not None and not self._video.done():
            self._video.set_result(track)
        else:  # audio (or a second video track): consumed and discarded
            sink = MediaBlackhole()
            sink.addTrack(track)
            self._sinks.append(sink)
            self._sink_starts.append(asyncio.get_running_loop().create_task(sink.start()))

    async def frames(self) -> AsyncIterator[av.VideoFrame]:
        """Decoded video frames until the phone stops or stalls. The first frame may take a while:
        aiortc drops frames until the first H.264 keyframe arrives."""
        assert self._video is not None, "open() first"
        try:
            track = await asyncio.wait_for(self._video, self.config.connect_timeout_s)
        except TimeoutError:
            raise ProtocolError("connected, but the phone sent no video track") from None
        timeout = self.config.connect_timeout_s
        while True:
            try:
                frame = await asyncio.wait_for(track.recv(), timeout)
                assert isinstance(frame, av.VideoFrame), "a video track yields video frames"
            except MediaStreamError:
                raise StreamEnded("the phone ended the stream") from None
            except TimeoutError:
                raise StreamEnded(f"no frame for {timeout:g} s: the phone is gone or stalled") from None
            timeout = self.config.stall_timeout_s
            yield frame

    async def close(self) -> None:
        pc, self._pc = self._pc, None
        for start in self._sink_starts:
            start.cancel()
        for sink in self._sinks:
            await sink.stop()
        self._sinks.clear()
        self._sink_starts.clear()
        if pc is not None:
            await pc.close()


@dataclass
class Record3DPacket:
    """One received frame, not yet decoded (decoding runs in the decode stage's threads)."""

    index: int
    timestamp: float  # seconds since the source started, host clock at arrival
    image: av.VideoFrame  # packed [H, 2W] depth | colour
    metadata: dict[str, Any]


class Record3DSource:
    """Frames from the phone, forever: connects, streams, and on any failure logs a specific
    message, closes the connection and retries with exponential back-off. Frame indices keep
    counting across reconnections, so SLAM maps into the same map. Live: the runtime's queues
    keep the newest frames when SLAM falls behind.

    Decoding turns a packet into a frame at one working size (the stream's size adapts to
    bandwidth, SLAM's does not): `size` (width, height), or the first usable frame's, halved
    until it is at most `max_width` wide (0: no limit)."""

    name = "record3d"
    live = True
    last_index = None

    def __init__(self, url: str, config: LiveConfig, size: tuple[int, int] | None = None, max_width: int = 0) -> None:
        self.url = url.rstrip("/")
        if "://" not in self.url:
            self.url = "http://" + self.url
        self.config = config
        self.counters = SourceCounters()
        self.size = size
        self.max_width = max_width
        self._clock0 = time.perf_counter()

    async def __aiter__(self) -> AsyncIterator[Record3DPacket]:
        delay = self.config.retry_initial_s
        while True:
            session = Record3DSession(self.url, self.config)
            streamed = False
            try:
                await session.open()
                log.info("record3d: connected to %s", self.url)
                self.counters.connected = True
                self.counters.connections += 1
                async for image in session.frames():
                    streamed = True
                    yield self._packet(image, session.metadata)
            except PhoneError as exc:
                self.counters.last_error = str(exc)
            finally:
                self.counters.connected = False
                await session.close()
            if streamed:
                delay = self.config.retry_initial_s
            log.warning("record3d: %s; retrying in %.1f s", self.counters.last_error, delay)
            await asyncio.sleep(delay)
            delay = min(2 * delay, self.config.retry_max_s)

    def _packet(self, image: av.VideoFrame, metadata: dict[str, Any]) -> Record3DPacket:
        index = self.counters.received
        self.counters.received += 1
        return Record3DPacket(index, time.perf_counter() - self._clock0, image, metadata)

    def decode(self, packet: Record3DPacket) -> Frame | None:
        """-> the frame at the working size, or None for an unusable one (counted as skipped)."""
        packed = packet.image.to_ndarray(format="rgb24")
        try:
            color, depth = unpack_frame(packed)
        except DataError as exc:
            self._skip(packet, str(exc))
            return None
        if not (depth > 0).any():
            self._skip(packet, "no valid depth (all red)")
            return None
        intrinsics = intrinsics_from_metadata(packet.metadata, color.shape[0])
        if self.size is None:
            self.size = halved_to(color.shape[1], color.shape[0], self.max_width)
        color, depth, intrinsics = resize_rgbd(color, depth, intrinsics, self.size)
        return Frame(packet.index, packet.timestamp, color, depth, intrinsics, None)

    def _skip(self, packet: Record3DPacket, why: str) -> None:
        self.counters.skipped += 1
        log.warning("record3d: frame %d skipped: %s", packet.index, why)


def halved_to(width: int, height: int, max_width: int) -> tuple[int, int]:
    """(width, height) halved until the width is at most `max_width` (0: unchanged)."""
    while max_width and width > max_width and width % 2 == 0 and height % 2 == 0:
        width, height = width // 2, height // 2
    return width, height
