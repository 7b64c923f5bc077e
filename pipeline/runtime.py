"""The asyncio runtime: wires source -> decode -> upload -> SLAM -> sinks with bounded queues.

Decoding and uploading run in worker threads and SLAM in a dedicated thread fed through a
thread-safe hand-off, so the event loop only moves items between queues; while SLAM works on
frame i, frames i+1.. are being read, decoded and copied to the GPU. `run_sync` is the plain
loop kept for comparison.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import threading
import time
from collections.abc import AsyncIterable, Callable, Coroutine
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from torch.profiler import record_function

from pipeline.errors import StageFailure
from pipeline.frame import Frame
from pipeline.source import Source
from pipeline.stages.queues import END, EndOfStream, Policy, StageQueue, StreamFailed
from pipeline.stages.sinks import ResultSink
from pipeline.stages.stage import StageStats, frame_index, transform_stage
from pipeline.stages.upload import UploadedFrame
from pipeline.stages.worker import DedicatedThread, ThreadedStage

try:
    import uvloop

    HAVE_UVLOOP = True
except ImportError:  # pragma: no cover - uvloop is a dependency, but optional on Windows
    HAVE_UVLOOP = False


@dataclass
class RuntimeReport:
    loader: str
    frames: int
    wall_s: float
    interrupted: bool
    stages: dict[str, dict[str, float]] = field(default_factory=dict)
    queues: dict[str, dict[str, int]] = field(default_factory=dict)
    gpu_gaps_ms: list[float] = field(default_factory=list)
    kernel_sample: dict[str, Any] | None = None  # the GPU's kernel time over a window of frames (slam/kernel_time.py)
    profile: dict[str, Any] | None = None  # kernel-timeline summary when run under the profiler
    compile_s: float | None = None  # torch.compile's own compile time during the run (compile_cache.compile_seconds)

    def summary(self) -> dict[str, Any]:
        gaps = sorted(self.gpu_gaps_ms)
        return {
            "loader": self.loader,
            "frames": self.frames,
            "wall_s": self.wall_s,
            "fps": self.frames / self.wall_s if self.wall_s > 0 else 0.0,
            "interrupted": self.interrupted,
            "stages": self.stages,
            "queues": self.queues,
            "kernel_busy_fraction": None if self.kernel_sample is None else self.kernel_sample["busy_fraction"],
            "kernel_sample": self.kernel_sample,
            "profile": self.profile,
            "gpu_gap_ms": {
                "mean": sum(gaps) / len(gaps) if gaps else None,
                "p95": gaps[int(0.95 * (len(gaps) - 1))] if gaps else None,
                "max": gaps[-1] if gaps else None,
                "over_1ms": sum(g > 1.0 for g in gaps),
            },
        }


Service = Callable[[asyncio.Event], Coroutine[Any, Any, None]]  # runs beside the graph; gets `stop`


@dataclass
class Graph:
    """What the runtime needs: a source, the upload, the SLAM stages and the sink. A live
    source's queue keeps the newest items (drops counted); an offline one's blocks (nothing lost)."""

    source: Source
    upload: Callable[[Frame], UploadedFrame]
    slam: ThreadedStage  # SLAM per frame, with its observers
    sink: ResultSink
    queue_size: int = 4
    decode_workers: int = 2
    services: list[Service] = field(default_factory=list)
    decode: Callable[[Any], Frame | None] | None = None  # the decode stage's work; None: the source's own
    queues: dict[str, StageQueue[Any]] = field(default_factory=dict)  # filled by run_graph, for live status

    @property
    def decoder(self) -> Callable[[Any], Frame | None]:
        return self.decode or self.source.decode

    @property
    def source_policy(self) -> Policy:
        return "keep_newest" if self.source.live else "block"

    def dropped(self) -> dict[str, int]:
        """Frames dropped so far, by where: each queue, and a live SLAM stage's start."""
        drops = {name: queue.dropped for name, queue in self.queues.items()}
        drops[f"{self.slam.name}_start"] = self.slam.dropped
        return {name: count for name, count in drops.items() if count}


def _finish_report(graph: Graph, loader: str, wall: float, interrupted: bool, stats: list[StageStats]) -> RuntimeReport:
    report = RuntimeReport(loader, len(graph.sink.results), wall, interrupted)
    report.stages = {s.name: s.summary() for s in stats}
    report.gpu_gaps_ms = graph.slam.spans.gaps_ms()
    return report


async def _pump(source: AsyncIterable[Any], outbox: StageQueue[Any]) -> EndOfStream:
    try:
        async for item in source:
            await outbox.put(item)
    except Exception as exc:
        return StreamFailed(StageFailure("source", None, exc))
    return END


async def _feed(source: AsyncIterable[Any], outbox: StageQueue[Any], stop: asyncio.Event) -> None:
    """Move the source's items into `outbox` until it ends or `stop` is set, then the end
    marker. A live source may wait for input forever: `stop` cancels that wait."""
    pump = asyncio.create_task(_pump(source, outbox))
    halt = asyncio.create_task(stop.wait())
    end: EndOfStream = END
    try:
        await asyncio.wait({pump, halt}, return_when=asyncio.FIRST_COMPLETED)
        if pump.done():
            end = pump.result()
    finally:
        halt.cancel()
        pump.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await pump
    await outbox.put(end)


async def run_graph(graph: Graph, stop: asyncio.Event) -> RuntimeReport:
    """Run the pipelined graph to the end of the source, or until `stop` is set (then the
    frame in SLAM finishes and the rest is left). A stage failing before SLAM (a frame that
    cannot be read) ends the stream at that frame: SLAM and the sink finish the frames before
    it, then its StageFailure is raised; so does a failing SLAM step (the sink takes the results
    before it). A failing sink stops everything at once."""
    q = graph.queue_size
    live = graph.source.live  # every queue up to SLAM then holds only the newest item (drops counted)
    q_in = 1 if live else q
    refs: StageQueue[Any] = StageQueue(q_in, graph.source_policy)
    frames: StageQueue[Any] = StageQueue(q_in, graph.source_policy)
    uploaded: StageQueue[Any] = StageQueue(q_in, graph.source_policy)
    results: StageQueue[Any] = StageQueue(4 * q)
    graph.queues.update(source=refs, decoded=frames, uploaded=uploaded, results=results)
    stats = [StageStats("decode"), StageStats("upload"), StageStats(graph.slam.name)]
    pools = [
        ThreadPoolExecutor(graph.decode_workers, thread_name_prefix="decode"),
        ThreadPoolExecutor(1, thread_name_prefix="upload"),
    ]
    start = time.perf_counter()
    try:
        async with asyncio.TaskGroup() as group:
            upstream: list[asyncio.Task[Any]] = [
                group.create_task(_feed(graph.source, refs, stop)),
                group.create_task(transform_stage("decode", graph.decoder, refs, frames, pools[0], stats[0])),
                group.create_task(transform_stage("upload", graph.upload, frames, uploaded, pools[1], stats[1])),
            ]
            slam = group.create_task(DedicatedThread(graph.slam, uploaded, results, stats[2], stop).run())
            group.create_task(graph.sink.drain(results))
            upstream += [group.create_task(service(stop)) for service in graph.services]
            end = await slam
            for task in upstream:
                task.cancel()
    except* StageFailure as failures:
        raise failures.exceptions[0] from None
    finally:
        for pool in pools:
            pool.shutdown(wait=True, cancel_futures=True)
    if isinstance(end, StreamFailed):
        raise end.failure
    wall = time.perf_counter() - start
    report = _finish_report(graph, "pipelined", wall, stop.is_set(), stats)
    report.queues = {name: {"max_depth": q.max_depth, "dropped": q.dropped} for name, q in graph.queues.items()}
    if graph.slam.dropped:
        report.queues[f"{graph.slam.name}_start"] = {"max_depth": 1, "dropped": graph.slam.dropped}
    return report


async def _collect(source: AsyncIterable[Any]) -> list[Any]:
    return [item async for item in source]


def run_sync(graph: Graph, stop: threading.Event) -> RuntimeReport:
    """The plain loop: read, decode, copy, track and map one frame after the other."""
    steps = [("decode", graph.decoder), ("upload", graph.upload), (graph.slam.name, graph.slam.run)]
    stats = {name: StageStats(name) for name, _ in steps}
    items = asyncio.run(_collect(graph.source))
    start = time.perf_counter()
    for item in items:
        if stop.is_set():
            break
        value: Any = item
        for name, fn in steps:
            t0 = time.perf_counter()
            try:
                with record_function(name):
                    value = fn(value)
            except Exception as exc:
                raise StageFailure(name, frame_index(item), exc) from exc
            stats[name].record(time.perf_counter() - t0)
            if value is None:  # an unusable live frame
                break
        else:
            graph.sink.consume(value)
    return _finish_report(graph, "sync", time.perf_counter() - start, stop.is_set(), list(stats.values()))


def catchable_signals() -> tuple[signal.Signals, ...]:
    """SIGINT and SIGTERM where this thread may handle them: the main thread only (Python's
    rule); none elsewhere (a Ray actor's method), whose caller stops the run by other means."""
    return (signal.SIGINT, signal.SIGTERM) if threading.current_thread() is threading.main_thread() else ()


def execute(graph: Graph, loader: str) -> RuntimeReport:
    """Run the graph with SIGINT/SIGTERM handled: the current frame finishes, the run ends cleanly.
    The handlers in place before are back afterwards. Signals reach the main thread only: run in
    another thread (a Ray actor's method), the graph is stopped by one of its services instead
    (app/remote_control.py)."""
    signals = catchable_signals()
    if loader == "sync":
        stop = threading.Event()
        previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in signals}
        try:
            return run_sync(graph, stop)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    async def main() -> RuntimeReport:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        previous = {sig: signal.getsignal(sig) for sig in signals}
        for sig in previous:
            loop.add_signal_handler(sig, stop.set)
        try:
            return await run_graph(graph, stop)
        finally:
            for sig, handler in previous.items():
                loop.remove_signal_handler(sig)  # which leaves the default handler, not the previous one
                signal.signal(sig, handler)

    if HAVE_UVLOOP:
        return uvloop.run(main())
    return asyncio.run(main())
