"""A small JSON status endpoint for the daemon: `GET /status`."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from aiohttp import web

log = logging.getLogger("gsplatam")


class _OneLine(logging.Filter):
    """aiohttp's report of a request it could not handle (a malformed request line or header:
    the endpoint answers 400 and lives) as one line, without the traceback."""

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        if error is not None:
            reason = " ".join(line.strip() for line in str(error).splitlines() if line.strip() not in ("", "^"))
            record.msg, record.args = f"status endpoint: {record.getMessage()}: {reason}", None
            record.exc_info, record.exc_text = None, None
        return True


request_log = logging.getLogger("gsplatam.status")  # the endpoint's request handling (aiohttp's server log)
request_log.addFilter(_OneLine())


async def serve_status(host: str, port: int, read: Callable[[], dict[str, Any]], stop: asyncio.Event) -> None:
    """Serve `read()` as JSON at http://host:port/status until cancelled (`stop` is not needed:
    the status stays up until the graph has finished)."""

    async def status(request: web.Request) -> web.Response:
        return web.json_response(read())

    app = web.Application()
    app.add_routes([web.get("/status", status)])
    runner = web.AppRunner(app, access_log=None, logger=request_log)
    await runner.setup()
    try:
        site = web.TCPSite(runner, host, port)
        try:
            await site.start()
        except OSError as exc:
            log.error("status endpoint: cannot listen on %s:%d (%s); running without it", host, port, exc)
            return
        log.info("status: http://%s:%d/status", host, port)
        await asyncio.Event().wait()
    finally:
        await runner.cleanup()
