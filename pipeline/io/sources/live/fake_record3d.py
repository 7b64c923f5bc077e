"""A fake Record3D phone: the app's Wi-Fi endpoints and frame packing, streaming a dataset.

It is how tests, demos and users without an iPhone exercise the `serve` daemon. It serves
`/getOffer` (403 while a receiver is connected), `/answer`, `/metadata` (K column-major), and
sends H.264 video of hue-encoded depth | colour at a fixed frame rate (or VP8, in either YUV
convention, to play a browser-style sender). The frame cursor is kept across connections and
moves on at the stream's rate while no receiver is connected, as a hand-held phone keeps moving
while the receiver reconnects.
"""

from __future__ import annotations

import asyncio
import fractions
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import av
from aiohttp import web
from aiortc import RTCPeerConnection, RTCRtpSender, RTCSessionDescription
from aiortc.mediastreams import AudioStreamTrack, MediaStreamError, MediaStreamTrack

from pipeline.config import ColorEncoding
from pipeline.io.sources.datasets.base import Dataset
from pipeline.io.sources.live.record3d import no_stun
from pipeline.io.sources.live.record3d_format import metadata_for, pack_frame, yuv_frame

log = logging.getLogger("gsplatam")

CLOCK_RATE = 90_000  # RTP video clock, Hz
ANSWER_TIMEOUT_S = 10.0  # an offer not answered within this frees the phone again


@dataclass
class PhoneState:
    dataset: Dataset
    fps: float
    loop: bool
    color: ColorEncoding  # the YUV matrix and range of the frames the encoder gets (neither codec signals it)
    cursor: int = 0  # next dataset frame to send
    sent: int = 0
    away_since: float | None = None  # time.monotonic() when the last connection ended

    def next_index(self) -> int | None:
        if self.cursor >= len(self.dataset):
            if not self.loop:
                return None
            self.cursor %= len(self.dataset)
        index, self.cursor = self.cursor, self.cursor + 1
        return index

    def resume(self) -> None:
        """A new connection's first frame: skip the frames the camera passed while none was connected."""
        if self.away_since is not None:
            self.cursor += round((time.monotonic() - self.away_since) * self.fps)
            self.away_since = None


class DatasetVideoTrack(MediaStreamTrack):
    """Packed depth | colour frames of the dataset at `state.fps`; ends at the dataset's end
    unless looping, and after `per_connection` frames (0: never), when it calls `on_limit`."""

    kind = "video"

    def __init__(self, state: PhoneState, per_connection: int = 0, on_limit: Callable[[], None] | None = None) -> None:
        super().__init__()
        self.state = state
        self.per_connection = per_connection
        self.on_limit = on_limit
        self._start: float | None = None
        self._count = 0

    async def recv(self) -> av.VideoFrame:
        if self._start is None:
            self._start = time.monotonic()
            self.state.resume()
        due = self._start + self._count / self.state.fps
        await asyncio.sleep(max(0.0, due - time.monotonic()))
        if self.per_connection and self._count >= self.per_connection:
            if self.on_limit is not None:
                self.on_limit()
            self.stop()
            raise MediaStreamError
        index = self.state.next_index()
        if index is None:
            self.stop()
            raise MediaStreamError
        frame = await asyncio.to_thread(self.state.dataset.decode, self.state.dataset.refs[index])
        image = yuv_frame(pack_frame(frame.color, frame.depth), self.state.color)
        image.pts = round(self._count * CLOCK_RATE / self.state.fps)
        image.time_base = fractions.Fraction(1, CLOCK_RATE)
        self._count += 1
        self.state.sent += 1
        return image


class FakePhone:
    """The HTTP side of the fake phone and its one peer connection at a time."""

    def __init__(
        self,
        dataset: Dataset,
        fps: float = 30.0,
        loop: bool = False,
        answer_path: str = "/answer",
        codecs: tuple[str, ...] = ("H264",),
        color: ColorEncoding = "bt601_limited",
        audio: bool = False,
        per_connection: int = 0,
    ) -> None:
        """`answer_path`, `codecs` (offered in this order), `color` and `audio` let tests play
        other senders: an older app (`/sendAnswer`) or a browser-style peer (VP8 first, BT.709
        full range, an audio track); `per_connection` > 0 ends each connection after that many
        frames, as a user stopping the stream in the app."""
        self.state = PhoneState(dataset, fps, loop, color)
        self.per_connection = per_connection
        self.codecs = codecs
        self.audio = audio
        self.pc: RTCPeerConnection | None = None
        self.app = web.Application()
        self.app.add_routes(
            [
                web.get("/getOffer", self.get_offer),
                web.post(answer_path, self.post_answer),
                web.get("/metadata", self.get_metadata),
            ]
        )
        self._runner: web.AppRunner | None = None
        self._expiry: asyncio.TimerHandle | None = None
        self._closing: asyncio.Task[None] | None = None  # held: the loop keeps only weak references

    @property
    def busy(self) -> bool:
        return self.pc is not None

    async def get_metadata(self, request: web.Request) -> web.Response:
        first = self.state.dataset.decode(self.state.dataset.refs[0])
        return web.json_response(metadata_for(first.intrinsics, first.width, first.height))

    async def get_offer(self, request: web.Request) -> web.Response:
        if self.busy:
            return web.json_response({"error": "another receiver is connected"}, status=403)
        if self.state.cursor >= len(self.state.dataset) and not self.state.loop:
            return web.json_response({"error": "the dataset has been streamed to its end"}, status=503)
        self.pc = pc = RTCPeerConnection(no_stun())
        track = DatasetVideoTrack(self.state, self.per_connection, self._disconnect_soon)
        transceiver = pc.addTransceiver(track, direction="sendonly")
        offered = [f"video/{name}" for name in self.codecs]
        codecs = [c for c in RTCRtpSender.getCapabilities("video").codecs if c.mimeType in offered]
        transceiver.setCodecPreferences(sorted(codecs, key=lambda c: offered.index(c.mimeType)))
        if self.audio:
            pc.addTrack(AudioStreamTrack())
        pc.on("connectionstatechange", self._on_state_change)
        await pc.setLocalDescription(await pc.createOffer())
        self._expiry = asyncio.get_running_loop().call_later(ANSWER_TIMEOUT_S, self._expire, pc)
        return web.json_response({"type": "offer", "sdp": pc.localDescription.sdp})

    async def post_answer(self, request: web.Request) -> web.Response:
        try:
            body = await request.json()
            sdp = body["data"]
            if not isinstance(sdp, str):
                raise TypeError
        except (ValueError, KeyError, TypeError):
            return web.json_response({"error": 'expected {"type": "answer", "data": <sdp>}'}, status=400)
        if self.pc is None or self.pc.signalingState != "have-local-offer":
            return web.json_response({"error": "no offer is waiting for an answer"}, status=409)
        if self._expiry is not None:
            self._expiry.cancel()
        await self.pc.setRemoteDescription(RTCSessionDescription(sdp, "answer"))
        return web.json_response({"ok": True})

    async def _on_state_change(self) -> None:
        if self.pc is not None and self.pc.connectionState in ("failed", "closed"):
            await self.disconnect()

    def _expire(self, pc: RTCPeerConnection) -> None:
        if self.pc is pc and pc.signalingState == "have-local-offer":
            log.warning("fake-record3d: the offer was not answered in %g s", ANSWER_TIMEOUT_S)
            asyncio.get_running_loop().create_task(self.disconnect())

    def _disconnect_soon(self) -> None:
        self._closing = asyncio.get_running_loop().create_task(self.disconnect())

    async def disconnect(self) -> None:
        """End the current connection (the receiver sees the stream end); the phone is free again."""
        pc, self.pc = self.pc, None
        if pc is not None:
            self.state.away_since = time.monotonic()
            await pc.close()

    async def start(self, host: str, port: int) -> int:
        """Serve on host:port (0: any free port); -> the port."""
        self._runner = web.AppRunner(self.app, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, host, port)
        await site.start()
        return site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]

    async def stop(self) -> None:
        await self.disconnect()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
