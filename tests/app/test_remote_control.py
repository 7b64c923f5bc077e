"""The handle another thread (a Ray actor's method) has on a running session."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time

from pipeline.app.remote_control import RemoteControl
from pipeline.io.sources.cameras import source_label


async def _graph(control: RemoteControl, ended: threading.Event) -> None:
    """What the runtime does with a service: run it beside the graph, cancel it at the end."""
    stop = asyncio.Event()
    service = asyncio.create_task(control.service(lambda: {"processed": 3})(stop))
    await asyncio.wait_for(stop.wait(), 10)
    service.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await service
    ended.set()


def test_another_thread_reads_the_status_and_stops_the_graph() -> None:
    control, ended = RemoteControl(), threading.Event()
    assert control.status() is None
    thread = threading.Thread(target=asyncio.run, args=(_graph(control, ended),))
    thread.start()
    deadline = time.monotonic() + 10
    while control.status() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert control.status() == {"processed": 3}
    control.request_stop()
    thread.join(timeout=10)
    assert ended.is_set() and control.status() is None


def test_a_stop_asked_before_the_graph_runs_stops_it_as_it_starts() -> None:
    control, ended = RemoteControl(), threading.Event()
    control.request_stop()
    asyncio.run(_graph(control, ended))
    assert ended.is_set()


def test_sources_get_names_fit_for_a_folder() -> None:
    assert source_label("record3d:http://192.168.1.20:8000/") == "record3d-192.168.1.20-8000"
    assert source_label("nerfcapture:") == "nerfcapture"
    assert source_label("nerfcapture:3") == "nerfcapture-d3"
