"""The Record3D iPhone app's Wi-Fi stream: HTTP signalling, an aiortc receiver, and the live
source that reconnects with back-off.

The phone serves HTTP on port 80: `GET /getOffer` -> {"type": "offer", "sdp": ...} (403 while
another receiver is connected), `POST /answer` {"type": "answer", "data": <sdp>} (older apps:
`/sendAnswer`), `GET /metadata` -> {"K": [...], "originalSize": [w, h]}. ICE is not trickled:
the offer carries the phone's candidates, and aiortc's `setLocalDescription` gathers every one of
ours before the answer is sent. The answer picks H.264 whenever the offer lists it, else VP8.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any
from urllib.parse import urlsplit

import aiohttp
import av
import torch
from aiortc import RTCConfiguration, RTCPeerConnection, RTCRtpCodecCapability, RTCRtpReceiver, RTCSessionDescription
from aiortc import sdp as sdp_text
from aiortc.contrib.media import MediaBlackhole
from aiortc.exceptions import OperationError
from aiortc.mediastreams import MediaStreamError, MediaStreamTrack

from pipeline.config import ColorEncoding, LiveConfig
from pipeline.devices import live_max_width
from pipeline.errors import DataError, UserError
from pipeline.frame import Frame
from pipeline.io.files.images import halved_to, resize_rgbd
from pipeline.io.sources.live.record3d_format import intrinsics_from_metadata, rgb_array, unpack_frame
from pipeline.source import SourceCounters

log = logging.getLogger("gsplatam")

VIDEO_CODECS = ("video/H264", "video/VP8")  # what the answer accepts, best first: H.264 is the app's own
H264_COLOR: ColorEncoding = "bt601_limited"  # H.264 that signals no matrix (what aiortc's encoder sends)


class Stage(StrEnum):
    """A connection's progress, as the status shows it (`stage`)."""

    WAITING = "waiting"  # between attempts: `last_error` says why
    SIGNALLING = "signalling"  # metadata, offer and answer over HTTP
    ICE_CONNECTED = "ice_connected"  # a candidate pair answers; no frame yet
    STREAMING = "streaming"  # the first frame arrived: `connected`


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


def phone_url(address: str) -> str:
    """The phone's address as the app shows it (`192.168.1.20`, `http://phone:8000/`) -> its
    base URL; UserError for an address that is not one."""
    url = address.strip()
    if "://" not in url:
        url = "http://" + url
    url = url.rstrip("/")
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 - parsing the port raises ValueError for a bad one
    except ValueError as exc:
        raise UserError(f"bad phone address '{address}': {exc}") from None
    if parts.scheme not in ("http", "https"):
        raise UserError(f"bad phone address '{address}': the app serves http://, not {parts.scheme}://")
    if not parts.hostname or parts.path.strip("/") or parts.query or parts.fragment:
        raise UserError(f"bad phone address '{address}': expected http://HOST or http://HOST:PORT")
    return url


def receive_codecs() -> list[RTCRtpCodecCapability]:
    """aiortc's video codecs in VIDEO_CODECS' order (with retransmission), for the receiving transceiver."""
    capabilities = RTCRtpReceiver.getCapabilities("video")
    assert capabilities is not None, "aiortc receives video"
    ranked = (*VIDEO_CODECS, "video/rtx")
    usable = [c for c in capabilities.codecs if c.mimeType in ranked]
    return sorted(usable, key=lambda c: ranked.index(c.mimeType))


def _video_codecs(description: sdp_text.SessionDescription) -> list[str]:
    """The video codecs a session description lists, in its order, without retransmission."""
    names = [c.mimeType.removeprefix("video/") for m in description.media if m.kind == "video" for c in m.rtp.codecs]
    return [name for name in dict.fromkeys(names) if name.lower() != "rtx"]


def _udp_candidates(description: sdp_text.SessionDescription) -> int:
    """How many ICE candidates aiortc can use (UDP) the description carries."""
    return sum(c.protocol.lower() == "udp" for m in description.media for c in m.ice_candidates)


def _read_offer(url: str, offer: Any) -> sdp_text.SessionDescription:
    """`/getOffer`'s reply -> its parsed SDP; ProtocolError for an offer this receiver cannot answer."""
    if not isinstance(offer, dict) or not isinstance(offer.get("sdp"), str) or offer.get("type") != "offer":
        raise ProtocolError(f"{url}: expected {{'type': 'offer', 'sdp': ...}}, got {offer!r:.80}")
    try:
        description = sdp_text.SessionDescription.parse(offer["sdp"])
    except ValueError as exc:
        raise ProtocolError(f"{url}: unusable offer SDP ({exc})") from exc
    if not any(m.kind == "video" for m in description.media):
        raise ProtocolError(f"{url}: the offer has no video track")
    if not _udp_candidates(description):
        raise ProtocolError(f"{url}: the offer has no usable ICE candidate (no UDP address of the phone)")
    return description


def _reply_text(url: str, body: bytes) -> str:
    try:
        return body.decode("utf-8")
    except UnicodeDecodeError:
        raise ProtocolError(f"{url}: the reply is not UTF-8 text: {body[:40]!r}") from None


async def _request(http: aiohttp.ClientSession, method: str, url: str, body: Any = None) -> tuple[int, str]:
    """-> (HTTP status, reply text). Whatever the phone's address answers, a failure is a
    PhoneError: no connection or a timeout (PhoneUnreachable), a reply that is not HTTP, too
    large a header, a redirect loop, a body that is not text (ProtocolError)."""
    try:
        async with http.request(method, url, json=body) as response:
            return response.status, _reply_text(url, await response.read())
    except TimeoutError as exc:  # connected or not: nothing came back in time
        limit = http.timeout.total
        raise PhoneUnreachable(f"{url}: no reply within {limit:g} s (live.http_timeout_s)") from exc
    except aiohttp.ClientConnectionError as exc:
        raise PhoneUnreachable(f"{url}: cannot connect ({exc.__class__.__name__}: {exc})") from exc
    except aiohttp.TooManyRedirects as exc:
        raise ProtocolError(f"{url}: redirected in a loop ({len(exc.history)} redirects)") from exc
    except (aiohttp.ClientError, ValueError) as exc:  # ValueError: e.g. an unusable redirect address
        said = " ".join(str(exc).split())[:160]  # aiohttp's parser errors span lines
        raise ProtocolError(f"{url}: not a usable HTTP reply ({exc.__class__.__name__}: {said})") from exc


async def _get_json(http: aiohttp.ClientSession, url: str) -> Any:
    status, text = await _request(http, "GET", url)
    if status == 403:
        raise PhoneBusy(f"{url}: HTTP 403, the phone is streaming to another receiver")
    if status != 200:
        raise ProtocolError(f"{url}: HTTP {status} {text[:120]!r}")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProtocolError(f"{url}: malformed JSON ({exc}): {text[:80]!r}") from exc


async def _post_answer(http: aiohttp.ClientSession, base: str, sdp: str) -> None:
    body = {"type": "answer", "data": sdp}
    for path in ("/answer", "/sendAnswer"):
        status, text = await _request(http, "POST", base + path, body)
        if status == 404:
            continue
        if status >= 300:
            raise ProtocolError(f"{base}{path}: HTTP {status} {text[:120]!r}")
        return
    raise ProtocolError(f"{base}: neither /answer nor /sendAnswer exists (HTTP 404)")


@dataclass
class Record3DSession:
    """One connection to the phone, from signalling to the last frame; `close()` is idempotent
    and must run, or the phone answers 403 to the next receiver."""

    url: str
    config: LiveConfig
    on_stage: Callable[[Stage], None] = lambda stage: None
    metadata: dict[str, Any] = field(default_factory=dict)
    codec: str = ""  # the video codec of the answer (H264 or VP8)
    _pc: RTCPeerConnection | None = None
    _video: asyncio.Future[MediaStreamTrack] | None = None
    _sinks: list[MediaBlackhole] = field(default_factory=list)
    _sink_starts: list[asyncio.Task[None]] = field(default_factory=list)  # held: the loop keeps only weak refs

    @property
    def color(self) -> ColorEncoding:
        """How frames that signal no YUV matrix are decoded: by the negotiated codec's convention."""
        return H264_COLOR if self.codec == "H264" else self.config.vp8_color

    async def open(self) -> None:
        self.on_stage(Stage.SIGNALLING)
        timeout = aiohttp.ClientTimeout(total=self.config.http_timeout_s)
        async with aiohttp.ClientSession(timeout=timeout) as http:
            log.debug("record3d: asking %s/metadata", self.url)
            self.metadata = await _get_json(http, self.url + "/metadata")
            try:
                intrinsics_from_metadata(self.metadata, 1)
            except DataError as exc:
                raise ProtocolError(f"{self.url}/metadata: {exc}") from exc
            log.debug("record3d: asking %s/getOffer", self.url)
            offer = await _get_json(http, self.url + "/getOffer")
            offered = _read_offer(self.url + "/getOffer", offer)
            log.debug("record3d: offer of video %s; answering", ", ".join(_video_codecs(offered)) or "none")
            self._pc = pc = RTCPeerConnection(no_stun())
            self._video = asyncio.get_running_loop().create_future()
            pc.on("track", self._on_track)
            pc.on("iceconnectionstatechange", self._on_ice_state)
            pc.addTransceiver("video", direction="recvonly").setCodecPreferences(receive_codecs())
            try:
                await pc.setRemoteDescription(RTCSessionDescription(offer["sdp"], "offer"))
                await pc.setLocalDescription(await pc.createAnswer())
            except ValueError as exc:
                raise ProtocolError(f"{self.url}/getOffer: unusable offer SDP ({exc})") from exc
            except OperationError:  # no codec in common
                listed = ", ".join(_video_codecs(offered)) or "none"
                takes = ", ".join(name.removeprefix("video/") for name in VIDEO_CODECS)
                raise ProtocolError(
                    f"{self.url}/getOffer: no codec this receiver decodes (the offer lists video {listed}; it takes {takes})"
                ) from None
            answer = sdp_text.SessionDescription.parse(pc.localDescription.sdp)
            if not _udp_candidates(answer):
                raise PhoneError("this host gathered no usable ICE candidate (no UDP address on a network interface)")
            self.codec = _video_codecs(answer)[0]
            log.debug("record3d: posting the answer (%d UDP candidates) to %s", _udp_candidates(answer), self.url)
            await _post_answer(http, self.url, pc.localDescription.sdp)
            log.info("record3d: answered %s with %s, connecting", self.url, self.codec)

    def _on_ice_state(self) -> None:
        if self._pc is not None:
            log.debug("record3d: ICE connection %s", self._pc.iceConnectionState)
        if self._pc is not None and self._pc.iceConnectionState == "completed":
            self.on_stage(Stage.ICE_CONNECTED)

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
        first, timeout = True, self.config.connect_timeout_s
        while True:
            try:
                frame = await asyncio.wait_for(track.recv(), timeout)
                assert isinstance(frame, av.VideoFrame), "a video track yields video frames"
            except MediaStreamError:
                raise StreamEnded("the phone ended the stream") from None
            except TimeoutError:
                raise StreamEnded(f"no frame for {timeout:g} s: the phone is gone or stalled") from None
            if first:
                self.on_stage(Stage.STREAMING)
                first, timeout = False, self.config.stall_timeout_s
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
    color: ColorEncoding  # how the image is decoded when it signals no YUV matrix
    received_at: float = field(default_factory=time.perf_counter)  # host clock, s


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
        self.url = phone_url(url)
        self.config = config
        self.counters = SourceCounters()
        self.size = size
        self.max_width = max_width
        self._clock0 = time.perf_counter()

    async def __aiter__(self) -> AsyncIterator[Record3DPacket]:
        backoff = Backoff(self.config)
        while True:
            session = Record3DSession(self.url, self.config, self._on_stage)
            streamed = False
            try:
                await session.open()
                async for image in session.frames():
                    streamed = True
                    yield self._packet(image, session)
            except Exception as exc:  # a PhoneError, or whatever else the phone's replies cause: never fatal
                error = exc
            finally:
                self.counters.connected = False
                self.counters.stage = Stage.WAITING
                await session.close()
            self.counters.last_error = describe(error)
            delay = backoff.after(error, streamed)
            log.warning("record3d: %s; retrying in %.1f s", self.counters.last_error, delay)
            await asyncio.sleep(delay)

    def _on_stage(self, stage: Stage) -> None:
        self.counters.stage = stage
        if stage is Stage.ICE_CONNECTED:
            log.info("record3d: ICE connected to %s, waiting for the first frame", self.url)
        elif stage is Stage.STREAMING:
            log.info("record3d: connected to %s, frames arriving", self.url)
            self.counters.connected = True
            self.counters.connections += 1

    def _packet(self, image: av.VideoFrame, session: Record3DSession) -> Record3DPacket:
        index = self.counters.received
        self.counters.received += 1
        return Record3DPacket(index, time.perf_counter() - self._clock0, image, session.metadata, session.color)

    def decode(self, packet: Record3DPacket) -> Frame | None:
        """-> the frame at the working size, or None for an unusable one (counted as skipped)."""
        packed = rgb_array(packet.image, packet.color)
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
        return Frame(packet.index, packet.timestamp, color, depth, intrinsics, None, received_at=packet.received_at)

    def _skip(self, packet: Record3DPacket, why: str) -> None:
        self.counters.skipped += 1
        log.warning("record3d: frame %d skipped: %s", packet.index, why)


def describe(error: Exception) -> str:
    """A failed attempt in one line: a PhoneError says what went wrong; anything else (from aiortc) is named."""
    return (
        str(error)
        if isinstance(error, PhoneError)
        else f"unexpected {error.__class__.__name__} from the phone: {error}"
    )


@dataclass
class Backoff:
    """The wait before the next connection attempt. A busy phone (HTTP 403) is asked again every
    `busy_probe_s`: it is free the moment its other receiver leaves. Any other failure waits
    `retry_initial_s`, doubling up to `retry_max_s`; a connection that streamed starts over."""

    config: LiveConfig
    _next_s: float = 0.0

    def __post_init__(self) -> None:
        self._next_s = self.config.retry_initial_s

    def after(self, error: Exception, streamed: bool) -> float:
        """-> seconds to wait after an attempt that ended with `error`."""
        if streamed:
            self._next_s = self.config.retry_initial_s
        if isinstance(error, PhoneBusy):
            return self.config.busy_probe_s
        delay, self._next_s = self._next_s, min(2 * self._next_s, self.config.retry_max_s)
        return delay


def open_record3d(address: str, live: LiveConfig, device: torch.device) -> Record3DSource:
    """`record3d:URL` (sources/cameras.py): frames at `live.width` x `live.height`, or the
    phone's halved to what suits `device`."""
    size = (live.width, live.height) if live.width else None
    return Record3DSource(address, live, size, live_max_width(device))
