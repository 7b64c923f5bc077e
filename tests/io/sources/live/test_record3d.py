"""Record3D: frame format, signalling errors, the aiortc loopback, and the daemon end to end."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import av
import numpy as np
import pytest
from aiohttp import web
from aiortc import RTCPeerConnection
from live_helpers import PhoneThread, free_port, read_status, wait_for

from pipeline.config import ColorEncoding, DatasetConfig, LiveConfig, SyntheticConfig
from pipeline.errors import DataError
from pipeline.io.sources.datasets.base import Dataset
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.io.sources.live.fake_record3d import FakePhone
from pipeline.io.sources.live.record3d import (
    Backoff,
    PhoneBusy,
    PhoneUnreachable,
    ProtocolError,
    Record3DPacket,
    Record3DSession,
    Record3DSource,
    halved_to,
    no_stun,
)
from pipeline.io.sources.live.record3d_format import (
    DEPTH_VALID_M,
    SEAM_MARGIN_PX,
    decode_depth,
    encode_depth,
    intrinsics_from_metadata,
    metadata_for,
    pack_frame,
    rgb_array,
    unpack_frame,
    yuv_frame,
)

FAST = LiveConfig(retry_initial_s=0.05, retry_max_s=0.2, connect_timeout_s=5.0, stall_timeout_s=1.0)


@pytest.fixture(scope="module")
def phone_dataset(tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    path = tmp_path_factory.mktemp("phone") / "room"
    write_synthetic(path, SyntheticConfig(frames=40, width=128, height=96, seed=5), progress=False)
    return open_dataset(DatasetConfig(path=str(path)))


def test_depth_round_trip_without_a_codec_is_within_2mm() -> None:
    low, high = DEPTH_VALID_M[0] + 0.002, DEPTH_VALID_M[1] - 0.002  # quantisation may cross the limits
    depth = np.linspace(low, high, 20_000, dtype=np.float32)[None]
    decoded = decode_depth(encode_depth(depth))
    assert (decoded > 0).all()
    assert np.abs(decoded - depth).max() < 0.002


def test_invalid_depth_is_red_and_decodes_as_invalid() -> None:
    depth = np.array([[0.0, 0.05, 2.8, 2.95, 1.0]], dtype=np.float32)
    rgb = encode_depth(depth)
    assert (rgb[0, :4] == [255, 0, 0]).all()
    assert (decode_depth(rgb)[0, :4] == 0).all() and decode_depth(rgb)[0, 4] > 0


def test_grey_pixels_have_no_hue_and_are_invalid() -> None:
    grey = np.full((2, 2, 3), 128, np.uint8)
    assert (decode_depth(grey) == 0).all()


def test_unpack_masks_the_seam_and_depth_discontinuities() -> None:
    depth = np.full((12, 24), 1.0, np.float32)
    depth[:, 12:] = 2.0  # a step in the middle
    color = np.zeros((12, 24, 3), np.uint8)
    out_color, out_depth = unpack_frame(pack_frame(color, depth))
    assert out_color.shape == (12, 24, 3)
    assert (out_depth[:, -SEAM_MARGIN_PX:] == 0).all()
    assert (out_depth[:, 11:13] == 0).all()  # both sides of the step
    assert np.allclose(out_depth[2:-2, 2:9], 1.0, atol=0.002)


@pytest.mark.parametrize("shape", [(10, 21, 3), (10, 8, 3), (10, 20)])
def test_unpack_rejects_frames_that_cannot_be_split(shape: tuple[int, ...]) -> None:
    with pytest.raises(DataError):
        unpack_frame(np.zeros(shape, np.uint8))


def test_intrinsics_are_column_major_and_scaled_by_frame_height() -> None:
    k = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    meta = metadata_for(k, 640, 480)
    assert meta["K"] == [500.0, 0, 0, 0, 510.0, 0, 320.0, 240.0, 1.0]
    half = intrinsics_from_metadata(meta, 240)
    assert np.allclose(half, [[250, 0, 160], [0, 255, 120], [0, 0, 1]])
    assert np.allclose(intrinsics_from_metadata(json.loads(json.dumps(meta)), 480), k)


@pytest.mark.parametrize(("cy", "original_height"), [(100.0, 256.0), (300.0, 640.0)])
def test_intrinsics_without_original_size_fall_back_by_cy(cy: float, original_height: float) -> None:
    meta = {"K": [200.0, 0, 0, 0, 200.0, 0, 90.0, cy, 1.0]}
    assert np.isclose(intrinsics_from_metadata(meta, 128)[0, 0], 200.0 * 128 / original_height)


@pytest.mark.parametrize(
    "metadata",
    [
        {},
        {"K": [1.0] * 8},
        {"K": ["a"] * 9},
        {"K": [float("nan")] + [1.0] * 8},
        {"K": [-5.0, 0, 0, 0, 5.0, 0, 2.0, 2.0, 1.0]},
        {"K": [5.0, 0, 0, 0, 5.0, 0, 2.0, 2.0, 1.0], "originalSize": "640x480"},
        [1, 2, 3],
    ],
)
def test_malformed_intrinsics_are_rejected_with_a_reason(metadata: Any) -> None:
    with pytest.raises(DataError, match="K|originalSize|metadata"):
        intrinsics_from_metadata(metadata, 100)


def _packet(packed: np.ndarray, metadata: dict[str, Any], index: int = 0) -> Record3DPacket:
    image = av.VideoFrame.from_ndarray(packed, format="rgb24")
    return Record3DPacket(index, 0.1 * index, image, metadata, "bt601_limited")  # RGB: no YUV matrix applies


def test_the_decoder_keeps_one_working_size_when_the_stream_resizes(phone_dataset: Dataset) -> None:
    frame = phone_dataset.decode(phone_dataset.refs[0])
    meta = metadata_for(frame.intrinsics, frame.width, frame.height)
    source = Record3DSource("http://phone", LiveConfig())
    first = source.decode(_packet(pack_frame(frame.color, frame.depth), meta))
    small = av.VideoFrame.from_ndarray(pack_frame(frame.color, frame.depth), format="rgb24").reformat(64, 24)
    second = source.decode(Record3DPacket(1, 0.1, small, meta, "bt601_limited"))
    assert first is not None and second is not None
    assert second.color.shape == first.color.shape == (96, 128, 3)
    assert np.allclose(second.intrinsics, first.intrinsics)
    assert np.allclose(first.intrinsics, frame.intrinsics)


def test_the_decoder_skips_and_counts_all_red_and_odd_frames(caplog: pytest.LogCaptureFixture) -> None:
    source = Record3DSource("http://phone", LiveConfig())
    meta = {"K": [50.0, 0, 0, 0, 50.0, 0, 32.0, 24.0, 1.0], "originalSize": [64, 48]}
    red = pack_frame(np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.float32))
    with caplog.at_level(logging.WARNING, "gsplatam"):
        assert source.decode(_packet(red, meta)) is None
        assert source.decode(_packet(np.zeros((48, 130, 3), np.uint8)[:, :126], meta)) is None
    assert source.counters.skipped == 2
    assert "no valid depth" in caplog.text


def test_working_size_for_the_cpu_is_halved() -> None:
    assert halved_to(512, 384, 128) == (128, 96)
    assert halved_to(512, 384, 0) == (512, 384)


async def _receive(
    url: str, count: int, config: LiveConfig = FAST, seconds: float = 60.0
) -> tuple[list[Record3DPacket], Record3DSource]:
    source = Record3DSource(url, config)
    packets = []
    async with asyncio.timeout(seconds):
        async for packet in source:
            packets.append(packet)
            if len(packets) == count:
                break
    return packets, source


@pytest.mark.parametrize(
    ("codec", "color", "audio", "answer_path"),
    [
        ("H264", "bt601_limited", False, "/answer"),
        ("VP8", "bt709_full", True, "/sendAnswer"),  # a browser-style sender, decoded by the default
        ("VP8", "bt601_limited", False, "/answer"),  # decoded with live.vp8_color = "bt601_limited"
    ],
)
@pytest.mark.live
def test_loopback_stream_decodes_to_the_sent_frames(
    phone_dataset: Dataset, codec: str, color: ColorEncoding, audio: bool, answer_path: str
) -> None:
    """The real aiortc path: the fake phone (or a browser-style VP8 + audio sender) on 127.0.0.1.
    Neither codec signals its YUV matrix here; VP8 in either convention keeps H.264's depth bound."""

    async def main() -> None:
        phone = FakePhone(phone_dataset, fps=30, codecs=(codec,), color=color, audio=audio, answer_path=answer_path)
        port = await phone.start("127.0.0.1", 0)
        try:
            config = replace(FAST, vp8_color=color)
            packets, source = await _receive(f"http://127.0.0.1:{port}", 8, config)
        finally:
            await phone.stop()
        assert source.counters.connections == 1
        errors = []
        for packet in packets:
            frame = source.decode(packet)
            assert frame is not None
            sent = phone_dataset.decode(phone_dataset.refs[packet.index])  # no frame is dropped at 30 fps
            assert np.allclose(frame.intrinsics, sent.intrinsics)
            assert np.abs(frame.color.astype(float) - sent.color).mean() < 12
            valid = frame.depth > 0
            assert valid.mean() > 0.4  # of 0.76 sent valid (beyond 2.8 m is invalid); masks take edges
            errors.append(np.abs(frame.depth[valid] - sent.depth[valid]))
        error = np.concatenate(errors)
        assert np.median(error) < 0.015 and np.percentile(error, 95) < 0.08  # bitrate adapts: loose bounds

    asyncio.run(main())


@pytest.mark.live
def test_debug_lines_follow_each_connection_step(phone_dataset: Dataset, caplog: pytest.LogCaptureFixture) -> None:
    """Behind -v: what the receiver asked the phone, what it offered and how ICE went, in order."""

    async def main() -> None:
        phone = FakePhone(phone_dataset, fps=30)
        port = await phone.start("127.0.0.1", 0)
        try:
            await _receive(f"http://127.0.0.1:{port}", 2, FAST)
        finally:
            await phone.stop()

    with caplog.at_level(logging.DEBUG, logger="gsplatam"):
        asyncio.run(main())
    steps = [r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG and "record3d:" in r.getMessage()]
    wanted = ["/metadata", "/getOffer", "offer of video H264", "posting the answer", "ICE connection"]
    found = [next((i for i, line in enumerate(steps) if w in line), -1) for w in wanted]
    assert -1 not in found and found == sorted(found), steps


def test_the_fake_phone_moves_on_while_no_receiver_is_connected(phone_dataset: Dataset) -> None:
    """A hand-held phone keeps moving while the receiver reconnects: the next connection starts
    the away time's worth of frames later (wrapping when looping)."""
    state = FakePhone(phone_dataset, fps=5, loop=True).state
    state.cursor = 3
    state.resume()  # never away: no skip
    assert state.cursor == 3
    state.away_since = time.monotonic() - 2.0
    state.resume()
    assert state.cursor == 3 + 10 and state.away_since is None
    state.cursor = len(phone_dataset) + 4
    assert state.next_index() == 4


@pytest.mark.live
def test_a_busy_phone_answers_403_and_the_receiver_says_so(phone_dataset: Dataset) -> None:
    async def main() -> None:
        phone = FakePhone(phone_dataset, fps=30, loop=True)
        port = await phone.start("127.0.0.1", 0)
        url = f"http://127.0.0.1:{port}"
        first = Record3DSession(url, FAST)
        second = Record3DSession(url, FAST)
        try:
            await first.open()
            with pytest.raises(PhoneBusy, match="403"):
                await second.open()
        finally:
            await first.close()
            await second.close()
            await phone.stop()

    asyncio.run(main())


@pytest.mark.live
def test_an_unreachable_phone_is_retried_with_back_off(caplog: pytest.LogCaptureFixture) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens

    async def main() -> None:
        with pytest.raises(PhoneUnreachable, match="cannot connect"):
            await Record3DSession(f"http://127.0.0.1:{port}", FAST).open()
        with caplog.at_level(logging.WARNING, "gsplatam"):
            with pytest.raises(TimeoutError):
                await _receive(f"127.0.0.1:{port}", 1, replace(FAST, retry_max_s=0.1))

    with pytest.raises(TimeoutError):
        asyncio.run(asyncio.wait_for(main(), 1.0))
    retries = [r for r in caplog.records if "cannot connect" in r.getMessage() and "retrying" in r.getMessage()]
    assert len(retries) >= 3


async def _serve_app(routes: list[web.RouteDef]) -> tuple[web.AppRunner, str]:
    app = web.Application()
    app.add_routes(routes)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    return runner, f"http://127.0.0.1:{site._server.sockets[0].getsockname()[1]}"  # type: ignore[union-attr]


GOOD_META = {"K": [50.0, 0, 0, 0, 50.0, 0, 32.0, 24.0, 1.0], "originalSize": [64, 48]}


async def _audio_only_offer(request: web.Request) -> web.Response:
    pc = RTCPeerConnection(no_stun())
    pc.addTransceiver("audio", direction="sendonly")
    await pc.setLocalDescription(await pc.createOffer())
    sdp = pc.localDescription.sdp
    await pc.close()
    return web.json_response({"type": "offer", "sdp": sdp})


@pytest.mark.parametrize(
    ("metadata_body", "offer_handler", "message"),
    [
        ("{not json", None, "malformed JSON"),
        (json.dumps({"originalSize": [64, 48]}), None, "no 'K'"),
        (json.dumps({"K": [1, 2, 3]}), None, "9 numbers"),
        (json.dumps(GOOD_META), lambda r: web.Response(text="<html>"), "malformed JSON"),
        (json.dumps(GOOD_META), lambda r: web.json_response({"type": "answer"}), "expected"),
        (json.dumps(GOOD_META), _audio_only_offer, "no video track"),
    ],
)
@pytest.mark.live
def test_bad_phone_responses_give_specific_errors(
    metadata_body: str, offer_handler: Callable[[web.Request], Any] | None, message: str
) -> None:
    async def metadata(request: web.Request) -> web.Response:
        return web.Response(text=metadata_body, content_type="application/json")

    async def offer(request: web.Request) -> web.Response:
        assert offer_handler is not None
        result = offer_handler(request)
        return await result if asyncio.iscoroutine(result) else result

    async def main() -> None:
        runner, url = await _serve_app([web.get("/metadata", metadata), web.get("/getOffer", offer)])
        session = Record3DSession(url, FAST)
        try:
            with pytest.raises(ProtocolError, match=message):
                await session.open()
        finally:
            await session.close()
            await runner.cleanup()

    asyncio.run(main())


@pytest.mark.slow
@pytest.mark.live
def test_daemon_reconstructs_from_the_fake_phone_and_survives_a_reconnect(
    phone_dataset: Dataset, tmp_path: Path
) -> None:
    phone = FakePhone(phone_dataset, fps=5, loop=True)
    device = PhoneThread()
    port = device.call(lambda: phone.start("127.0.0.1", 0))
    status_port = free_port()
    log_path = tmp_path / "daemon.log"
    command = [
        sys.executable, "-m", "pipeline", "serve", "--record3d", f"http://127.0.0.1:{port}", "--device", "cpu",
        "--preset", "tiny", "--output", str(tmp_path), "--name", "live", "--quiet",
        "--set", f"live.status_port={status_port}", "--set", "live.retry_initial_s=0.2",
        "--set", "live.stall_timeout_s=2", "--set", "live.save_every_s=1",
        "--set", "mapping.iters=2",  # the reconnection is the point, not the map
        "--set", "live.warm_up=on",  # as on CUDA: the first frame warms SLAM up and is dropped
    ]  # fmt: skip
    with open(log_path, "w") as log_file:
        daemon = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT, env={**os.environ})
    try:
        wait_for(lambda: (read_status(status_port) or {}).get("processed", 0) >= 3, 120, "3 frames", log_path)
        device.call(phone.disconnect)
        wait_for(lambda: (read_status(status_port) or {}).get("connections", 0) >= 2, 60, "a reconnection", log_path)
        before = read_status(status_port)["processed"]  # type: ignore[index]
        wait_for(lambda: (read_status(status_port) or {})["processed"] >= before + 2, 120, "frames after it", log_path)
        status = read_status(status_port)
        assert status is not None and status["gaussians"] > 0 and status["received"] >= status["processed"]
    finally:
        daemon.send_signal(signal.SIGINT)
        code = daemon.wait(timeout=60)
        device.call(phone.stop)
        device.close()
    assert code == 0, log_path.read_text()[-3000:]
    folder = tmp_path / "live"
    trajectory = [line for line in (folder / "trajectory.txt").read_text().splitlines() if not line.startswith("#")]
    metrics = json.loads((folder / "metrics.json").read_text())
    assert len(trajectory) == metrics["frames"] >= 5
    assert metrics["counters"]["connections"] >= 2
    assert (folder / "map.ply").stat().st_size > 1000 and (folder / "checkpoint.safetensors").exists()
    assert "retrying" in log_path.read_text() and "SLAM warmed up on frame" in log_path.read_text()


@pytest.mark.live
def test_a_phone_that_stops_sending_is_detected_and_retried(phone_dataset: Dataset, caplog) -> None:
    """The phone goes silent without closing (the end of a non-looping fake stream): the stall
    timeout ends the session, and the retries get a specific refusal, never a hang."""

    async def main() -> None:
        phone = FakePhone(phone_dataset, fps=60)
        port = await phone.start("127.0.0.1", 0)
        try:
            with caplog.at_level(logging.WARNING, "gsplatam"), pytest.raises(TimeoutError):
                url, count = f"http://127.0.0.1:{port}", len(phone_dataset) + 10
                await _receive(url, count, replace(FAST, stall_timeout_s=0.5), seconds=5.0)
        finally:
            await phone.stop()

    asyncio.run(main())
    messages = [r.getMessage() for r in caplog.records]
    assert any("no frame for 0.5 s" in m for m in messages)
    assert any("503" in m and "streamed to its end" in m for m in messages)


@pytest.mark.live
def test_the_daemon_stops_cleanly_while_waiting_for_an_absent_phone(tmp_path: Path) -> None:
    command = [
        sys.executable, "-m", "pipeline", "serve", "--record3d", f"http://127.0.0.1:{free_port()}",
        "--device", "cpu", "--output", str(tmp_path), "--quiet", "--set", "live.status_port=0",
    ]  # fmt: skip
    log_path = tmp_path / "daemon.log"
    with open(log_path, "w") as log_file:
        daemon = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT)
    wait_for(lambda: "cannot connect" in log_path.read_text(), 120, "a connection attempt", log_path)
    daemon.send_signal(signal.SIGINT)  # once it runs (a slow start would otherwise end as a plain Ctrl-C)
    daemon.wait(timeout=30)
    output = log_path.read_text()
    assert daemon.returncode == 0, output
    assert "cannot connect" in output and "nothing to save" in output
    # nothing saved: the session's fresh, timestamped run folder is gone, and latest was not moved
    assert list(tmp_path.glob("live_record3d_tiny-2*")) == [] and not (tmp_path / "latest").exists()


@pytest.mark.parametrize("sent", ["bt709_full", "bt601_limited"])
def test_unsignalled_yuv_decodes_by_the_setting_and_signalled_yuv_by_its_own(sent: ColorEncoding) -> None:
    """Colour errors are depth errors: decoding in the sender's convention keeps depth within
    5 mm, the other convention is several times worse; a frame that names its matrix ignores
    the setting."""
    depth = np.tile(np.linspace(0.15, 2.7, 256, dtype=np.float32), (48, 1))
    packed = pack_frame(np.full((48, 256, 3), 90, np.uint8), depth)
    signalled = yuv_frame(packed, sent)
    unsignalled = av.VideoFrame.from_ndarray(signalled.to_ndarray(), format="yuv420p")  # as VP8 decodes

    def median_error(frame: av.VideoFrame, setting: ColorEncoding) -> float:
        decoded = unpack_frame(rgb_array(frame, setting))[1]
        valid = decoded > 0
        assert valid.mean() > 0.8
        return float(np.median(np.abs(decoded[valid] - depth[valid])))

    other: ColorEncoding = "bt601_limited" if sent == "bt709_full" else "bt709_full"
    assert (
        median_error(unsignalled, sent) < 0.005 < 3 * median_error(unsignalled, sent) < median_error(unsignalled, other)
    )
    assert median_error(signalled, other) == median_error(unsignalled, sent)


@pytest.mark.parametrize(("offered", "answered"), [(("VP8", "H264"), "H264"), (("VP8",), "VP8")])
@pytest.mark.live
def test_the_answer_takes_h264_whenever_offered_else_vp8(
    phone_dataset: Dataset, offered: tuple[str, ...], answered: str
) -> None:
    async def main() -> None:
        phone = FakePhone(phone_dataset, fps=30, loop=True, codecs=offered)
        port = await phone.start("127.0.0.1", 0)
        session = Record3DSession(f"http://127.0.0.1:{port}", FAST)
        try:
            await session.open()
            assert session.codec == answered
            assert session.color == ("bt601_limited" if answered == "H264" else FAST.vp8_color)
            async with asyncio.timeout(30):
                async for _ in session.frames():
                    break
        finally:
            await session.close()
            await phone.stop()

    asyncio.run(main())


HAND_WRITTEN_OFFER = """v=0
o=- 1 1 IN IP4 127.0.0.1
s=-
t=0 0
a=group:BUNDLE 0
m=video 9 UDP/TLS/RTP/SAVPF 98 45
c=IN IP4 127.0.0.1
a=mid:0
a=sendonly
a=rtcp-mux
a=rtpmap:98 VP9/90000
a=rtpmap:45 AV1/90000
a=ice-ufrag:abcd
a=ice-pwd:abcdefghijklmnopqrstuvwx
a=fingerprint:sha-256 {fingerprint}
a=setup:actpass
a=candidate:1 1 udp 2130706431 127.0.0.1 9 typ host
""".replace("\n", "\r\n").format(fingerprint=":".join(["AB"] * 32))


@pytest.mark.parametrize(
    ("sdp", "message"),
    [
        (HAND_WRITTEN_OFFER, "no codec this receiver decodes (the offer lists video VP9, AV1; it takes H264, VP8)"),
        (HAND_WRITTEN_OFFER.replace("98 VP9", "98 H264").split("a=candidate")[0], "no usable ICE candidate"),
    ],
)
@pytest.mark.live
def test_an_offer_without_a_usable_codec_or_candidate_is_one_retried_error(
    sdp: str, message: str, caplog: pytest.LogCaptureFixture
) -> None:
    async def metadata(request: web.Request) -> web.Response:
        return web.json_response(GOOD_META)

    async def offer(request: web.Request) -> web.Response:
        return web.json_response({"type": "offer", "sdp": sdp})

    async def main() -> None:
        runner, url = await _serve_app([web.get("/metadata", metadata), web.get("/getOffer", offer)])
        receiving = asyncio.create_task(_receive(url, 1, FAST))
        try:
            await _logged(caplog, "retrying", 3)
        finally:
            receiving.cancel()
            await runner.cleanup()

    with caplog.at_level(logging.INFO, "gsplatam"):
        asyncio.run(main())
    retries = [r.getMessage() for r in caplog.records if "retrying" in r.getMessage()]
    assert all(message in m and "\n" not in m for m in retries[:3])
    assert "Traceback" not in caplog.text and not any(r.exc_info for r in caplog.records)


async def _logged(caplog: pytest.LogCaptureFixture, text: str, count: int) -> None:
    """Until `count` log records hold `text` (the test's own timeout bounds it)."""
    async with asyncio.timeout(30):
        while sum(text in r.getMessage() for r in caplog.records) < count:
            await asyncio.sleep(0.01)


def test_a_busy_phone_is_probed_at_its_interval_and_other_failures_back_off() -> None:
    config = LiveConfig(retry_initial_s=1.0, retry_max_s=4.0, busy_probe_s=0.5)
    backoff = Backoff(config)
    busy, gone = PhoneBusy("403"), PhoneUnreachable("no route")
    delays = [backoff.after(error, streamed=False) for error in (gone, gone, busy, busy, gone, gone, gone)]
    assert delays == [1.0, 2.0, 0.5, 0.5, 4.0, 4.0, 4.0]
    assert backoff.after(gone, streamed=True) == 1.0
    assert LiveConfig().stall_timeout_s >= 10 and LiveConfig().busy_probe_s <= 1.0


@pytest.mark.live
def test_the_receiver_reconnects_at_the_first_probe_after_a_busy_phone_frees(
    phone_dataset: Dataset, caplog: pytest.LogCaptureFixture
) -> None:
    """While another receiver holds the phone, the source probes every busy_probe_s and says
    it is waiting; once freed it connects at once (back-off alone would wait an hour here), and
    reports `connected` only at the first frame."""
    hour = 3600.0  # equal timeouts, as by default: the first frame must still count as the stage change
    config = replace(
        FAST, retry_initial_s=hour, retry_max_s=hour, busy_probe_s=0.02, stall_timeout_s=FAST.connect_timeout_s
    )

    async def main() -> None:
        phone = FakePhone(phone_dataset, fps=30, loop=True)
        port = await phone.start("127.0.0.1", 0)
        url = f"http://127.0.0.1:{port}"
        other = Record3DSession(url, FAST)
        source = Record3DSource(url, config)
        stages = []

        async def leave_after_three_probes() -> None:
            await _logged(caplog, "HTTP 403", 3)
            stages.append((source.counters.stage, source.counters.connected))
            await other.close()  # the phone is free

        try:
            await other.open()
            leaving = asyncio.create_task(leave_after_three_probes())
            async with asyncio.timeout(60):
                async for _ in source:
                    stages.append((source.counters.stage, source.counters.connected))
                    break
            await leaving
        finally:
            await other.close()
            await phone.stop()
        assert stages[0][1] is False and stages[0][0] in ("waiting", "signalling")
        assert stages[1:] == [("streaming", True)]
        assert source.counters.connections == 1 and "403" in source.counters.last_error

    with caplog.at_level(logging.INFO, "gsplatam"):
        asyncio.run(main())
    messages = [r.getMessage() for r in caplog.records]
    assert sum("403" in m and "retrying in 0.0 s" in m for m in messages) >= 3
    assert any("ICE connected" in m for m in messages)
