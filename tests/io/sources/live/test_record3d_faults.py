"""Record3D under bad input: malformed addresses and every kind of malformed reply from the
phone's address, alone and injected between good streams into a running daemon."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from aiohttp import web
from live_helpers import PhoneThread, free_port, read_status, wait_for

from pipeline.config import DatasetConfig, LiveConfig, SyntheticConfig
from pipeline.errors import UserError
from pipeline.io.sources.datasets.base import Dataset
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.io.sources.live.fake_record3d import FakePhone
from pipeline.io.sources.live.record3d import PhoneUnreachable, ProtocolError, Record3DSession, phone_url

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


async def garbage_status_line(request: web.Request) -> web.StreamResponse:
    assert request.transport is not None
    request.transport.write(b"NOT HTTP AT ALL\r\n\r\n")
    request.transport.close()
    raise asyncio.CancelledError  # the connection is gone: aiohttp writes nothing more


async def non_utf8_body(request: web.Request) -> web.StreamResponse:
    return web.Response(body=b"\xff\xfe\x00{}", content_type="application/json")


async def oversized_header(request: web.Request) -> web.StreamResponse:
    return web.json_response({}, headers={"X-Padding": "a" * 20_000})


async def redirect_loop(request: web.Request) -> web.StreamResponse:
    raise web.HTTPFound(f"{request.path}?again=1")


async def http_error(request: web.Request) -> web.StreamResponse:
    return web.Response(status=500, text="internal error")


BAD_REPLIES: dict[str, tuple[Handler, str]] = {  # what the phone's address answers -> what the receiver says
    "garbage status line": (garbage_status_line, "not a usable HTTP reply"),
    "non-UTF-8 body": (non_utf8_body, "not UTF-8 text"),
    "oversized header": (oversized_header, "not a usable HTTP reply"),
    "redirect loop": (redirect_loop, "redirected in a loop"),
    "HTTP error": (http_error, "HTTP 500"),
}


@pytest.mark.parametrize(
    "address, message",
    [("ftp://192.168.1.20", "serves http://"), ("http://", "expected http://HOST"), ("http://[::1", "bad phone address"),
     ("http://phone:99999", "bad phone address"), ("http://phone/stream?x=1", "expected http://HOST")],
)  # fmt: skip
def test_a_malformed_phone_address_is_refused_with_its_text(address: str, message: str) -> None:
    with pytest.raises(UserError, match=message.replace("(", r"\(")):
        phone_url(address)
    assert phone_url("192.168.1.20/") == "http://192.168.1.20" and phone_url("https://p:8000") == "https://p:8000"


async def _serve(routes: list[web.RouteDef], middlewares: list = ()) -> tuple[web.AppRunner, str]:  # type: ignore[assignment]
    app = web.Application(middlewares=list(middlewares))
    app.add_routes(routes)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    return runner, f"http://127.0.0.1:{site._server.sockets[0].getsockname()[1]}"  # type: ignore[union-attr]


@pytest.mark.live
@pytest.mark.parametrize("kind", list(BAD_REPLIES))
def test_every_malformed_reply_is_a_phone_error(kind: str) -> None:
    handler, message = BAD_REPLIES[kind]

    async def main() -> None:
        runner, url = await _serve([web.get("/metadata", handler)])
        session = Record3DSession(url, LiveConfig(connect_timeout_s=2.0))
        try:
            with pytest.raises(ProtocolError, match=message) as error:
                await session.open()
            assert "\n" not in str(error.value)
        finally:
            await session.close()
            await runner.cleanup()

    asyncio.run(main())


@dataclass
class Turn:
    """One connection attempt of the receiver: the phone's stream, or a bad reply at `path`."""

    fault: str | None = None
    path: str = "/metadata"


class FaultyAddress:
    """The fake phone behind a schedule of turns. A connection attempt starts with GET
    /metadata; each takes the next turn (after the last, every attempt gets an HTTP error)."""

    def __init__(self, phone: FakePhone, turns: list[Turn]) -> None:
        self.phone = phone
        self.turns = list(turns)
        self.turn = Turn()

    @web.middleware
    async def middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.path == "/metadata" and "again" not in request.query:
            self.turn = self.turns.pop(0) if self.turns else Turn("HTTP error")
        if self.turn.fault is not None and request.path == self.turn.path:
            return await BAD_REPLIES[self.turn.fault][0](request)
        return await handler(request)

    async def start(self) -> tuple[web.AppRunner, str]:
        phone = self.phone
        routes = [web.get("/getOffer", phone.get_offer), web.post("/answer", phone.post_answer),
                  web.get("/metadata", phone.get_metadata)]  # fmt: skip
        return await _serve(routes, [self.middleware])


@pytest.fixture(scope="module")
def small_phone_dataset(tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    path = tmp_path_factory.mktemp("phone") / "room"
    write_synthetic(path, SyntheticConfig(frames=30, width=64, height=48, seed=5), progress=False)
    return open_dataset(DatasetConfig(path=str(path)))


@pytest.mark.slow
@pytest.mark.live
def test_the_daemon_survives_every_malformed_reply_and_maps_into_one_map(
    small_phone_dataset: Dataset, tmp_path: Path
) -> None:
    """Good streams of 2 frames with each bad reply between two of them: the daemon retries
    every one, never dies, and every frame it received is either in its one map or counted as
    dropped (a live daemon keeps only the newest frame: a slow CPU drops some; few iterations:
    the test is about the daemon, not the map)."""
    faults = [Turn(kind) for kind in BAD_REPLIES] + [Turn("HTTP error", "/getOffer")]
    turns = [Turn()] + [t for fault in faults for t in (fault, Turn())]
    good = sum(t.fault is None for t in turns)
    phone = FakePhone(small_phone_dataset, fps=6, loop=True, per_connection=2)
    address = FaultyAddress(phone, turns)
    device = PhoneThread()
    runner, url = device.call(address.start)
    status_port = free_port()
    log_path = tmp_path / "daemon.log"
    command = [
        sys.executable, "-m", "pipeline", "serve", "--record3d", url, "--device", "cpu", "--preset", "tiny",
        "--output", str(tmp_path), "--name", "live", "--quiet", "--set", f"live.status_port={status_port}",
        "--set", "live.retry_initial_s=0.05", "--set", "live.retry_max_s=0.2", "--set", "live.stall_timeout_s=2",
        "--set", "tracking.iters=2", "--set", "mapping.iters=2",
    ]  # fmt: skip
    with open(log_path, "w") as log_file:
        daemon = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT)

    def all_streamed() -> bool:
        status = read_status(status_port) or {}
        done = not address.turns and status.get("connections") == good and not status.get("connected")
        return done and status.get("processed", 0) + status.get("dropped", 0) == status["received"] - status["skipped"]

    try:
        wait_for(all_streamed, 180, f"{good} good streams and every bad reply", log_path)
    finally:
        daemon.send_signal(signal.SIGINT)
        code = daemon.wait(timeout=60)
        device.call(phone.stop)
        device.call(runner.cleanup)
        device.close()
    log_text = log_path.read_text()
    assert code == 0, log_text[-3000:]
    metrics = json.loads((tmp_path / "live" / "metrics.json").read_text())
    counters = metrics["counters"]
    dropped = sum(queue["dropped"] for queue in metrics["runtime"]["queues"].values())
    assert counters["connections"] == good
    # 2 sent per stream; the last can stay in the receiver's jitter buffer when the phone hangs up
    assert metrics["frames"] + dropped == counters["received"] - counters["skipped"] >= good
    assert metrics["frames"] >= 1
    assert metrics["frames"] == len(_rows(tmp_path / "live" / "trajectory.txt"))
    for _, said in BAD_REPLIES.values():
        assert said in log_text, said
    assert "Traceback" not in log_text


def _rows(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if not line.startswith("#")]


@pytest.mark.live
def test_a_slow_phone_is_no_reply_within_the_configured_timeout() -> None:
    async def slow_metadata(request: web.Request) -> web.StreamResponse:
        await asyncio.sleep(0.6)
        return web.json_response({"K": "not intrinsics"})

    async def main() -> None:
        runner, url = await _serve([web.get("/metadata", slow_metadata)])
        try:
            with pytest.raises(PhoneUnreachable, match=r"/metadata: no reply within 0.2 s \(live.http_timeout_s\)"):
                await Record3DSession(url, LiveConfig(http_timeout_s=0.2)).open()
            with pytest.raises(ProtocolError, match="/metadata"):  # waited for: the reply itself is read
                await Record3DSession(url, LiveConfig(http_timeout_s=5.0)).open()
        finally:
            await runner.cleanup()

    asyncio.run(main())
