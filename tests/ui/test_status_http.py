"""The daemon's status endpoint: JSON at /status; malformed requests answered 400 and logged in
one line each, without a traceback."""

from __future__ import annotations

import asyncio
import logging
import socket

import pytest

pytest.importorskip("aiohttp", reason="the status endpoint needs the 'live' extra")

from pipeline.ui.status_http import serve_status  # noqa: E402

MALFORMED = [
    b"GARBAGE\r\n\r\n",
    b"GET /status HTTP/1.1\r\nHost: x\r\nContent-Length: abc\r\n\r\n",
    b"GET /status HTTP/9.9\r\n\r\n",
]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


async def _ask(port: int, payload: bytes) -> bytes:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(payload)
    await writer.drain()
    reply = await asyncio.wait_for(reader.read(4096), 10)
    writer.close()
    return reply


async def _session(port: int) -> list[bytes]:
    task = asyncio.create_task(serve_status("127.0.0.1", port, lambda: {"processed": 3}, asyncio.Event()))
    for _ in range(200):  # until it listens
        try:
            (await asyncio.open_connection("127.0.0.1", port))[1].close()
            break
        except OSError:
            await asyncio.sleep(0.05)
    replies = [await _ask(port, payload) for payload in MALFORMED]
    replies.append(await _ask(port, b"GET /status HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"))
    task.cancel()
    return replies


def test_malformed_requests_are_one_log_line_each_and_the_endpoint_lives(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.DEBUG, logger="gsplatam"):
        replies = asyncio.run(_session(_free_port()))
    assert all(reply.startswith(b"HTTP/1.0 400") for reply in replies[:-1])
    assert replies[-1].startswith(b"HTTP/1.1 200") and b'"processed": 3' in replies[-1]
    handled = [r for r in caplog.records if r.name == "gsplatam.status"]
    assert len(handled) == len(MALFORMED)
    assert all(r.exc_info is None and "\n" not in r.getMessage() for r in handled)
    assert "Invalid character in Content-Length" in handled[1].getMessage()
    assert "Traceback" not in caplog.text
