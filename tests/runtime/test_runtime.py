from __future__ import annotations

import asyncio
import random
import threading
import time
from dataclasses import dataclass

import pytest
import torch

from pipeline.errors import StageFailure
from pipeline.runtime import Graph, run_graph, run_sync
from pipeline.source import SourceCounters
from pipeline.stages.gpu_spans import GpuSpans
from pipeline.stages.queues import END, EndOfStream, StageQueue
from pipeline.stages.worker import ThreadedStage


@dataclass
class Item:
    index: int
    received_at: float = 0.0


class ListSource:
    """A Source of `n` items whose decode is `decode`."""

    name = "list"
    live = False

    def __init__(self, n: int, decode=None) -> None:
        self.n = n
        self.decode = decode or jittery
        self.counters = SourceCounters()

    @property
    def last_index(self) -> int:
        return self.n - 1

    async def __aiter__(self):
        for i in range(self.n):
            yield Item(i)


class FakeSlam:
    """Stands in for SlamStep: records the order and can be slow or fail."""

    def __init__(self, delay: float = 0.0, fail_at: int | None = None) -> None:
        self.delay, self.fail_at, self.seen = delay, fail_at, []

    def __call__(self, item: Item) -> Item:
        if item.index == self.fail_at:
            raise RuntimeError("boom")
        time.sleep(self.delay)
        self.seen.append(item.index)
        return item


class CollectSink:
    def __init__(self) -> None:
        self.results: list[Item] = []

    def consume(self, item: Item) -> None:
        self.results.append(item)

    async def drain(self, inbox: StageQueue) -> None:
        while not isinstance(item := await inbox.get(), EndOfStream):
            self.consume(item)


def jittery(item: Item) -> Item:
    time.sleep(random.random() * 0.003)
    return item


def graph(n: int, slam: FakeSlam, decode=jittery, queue_size: int = 3) -> Graph:
    stage = ThreadedStage("slam", slam, GpuSpans(torch.device("cpu")))
    return Graph(ListSource(n, decode), jittery, stage, CollectSink(), queue_size=queue_size, decode_workers=2)  # type: ignore[arg-type]


def run(g: Graph, stop: asyncio.Event | None = None, timeout: float = 30.0):
    async def main():
        return await asyncio.wait_for(run_graph(g, stop or asyncio.Event()), timeout)

    return asyncio.run(main())


def test_frames_reach_slam_in_order_and_none_is_lost() -> None:
    slam = FakeSlam()
    g = graph(60, slam)
    report = run(g)
    assert slam.seen == list(range(60))
    assert [r.index for r in g.sink.results] == list(range(60))
    assert report.frames == 60 and not report.interrupted
    assert report.stages["decode"]["items"] == 60


def test_a_slow_consumer_bounds_every_queue() -> None:
    slam = FakeSlam(delay=0.01)
    g = graph(30, slam, queue_size=2)
    report = run(g)
    assert slam.seen == list(range(30))
    assert all(q["max_depth"] <= 2 for name, q in report.queues.items() if name != "results")
    assert all(q["dropped"] == 0 for q in report.queues.values())


def test_keep_newest_drops_the_oldest_and_counts() -> None:
    async def main():
        queue: StageQueue[int] = StageQueue(3, "keep_newest")
        for i in range(10):
            await queue.put(i)
        await queue.put(END)  # the end marker waits for room instead of dropping
        return queue

    async def with_consumer():
        queue: StageQueue[int] = StageQueue(3, "keep_newest")
        for i in range(10):
            await queue.put(i)
        got = [await queue.get() for _ in range(3)]
        return queue, got

    queue, got = asyncio.run(with_consumer())
    assert got == [7, 8, 9] and queue.dropped == 7
    with pytest.raises(asyncio.TimeoutError):
        asyncio.run(asyncio.wait_for(main(), 0.2))


@pytest.mark.parametrize("where", ["decode", "slam"])
def test_a_failing_stage_stops_the_graph_and_names_stage_and_frame(where: str) -> None:
    def failing_decode(item: Item) -> Item:
        if item.index == 7:
            raise ValueError("boom")
        return item

    slam = FakeSlam(fail_at=7 if where == "slam" else None)
    g = graph(100, slam, decode=failing_decode if where == "decode" else jittery)
    with pytest.raises(StageFailure, match=f"stage '{where}' failed on frame 7: boom"):
        run(g, timeout=10.0)
    if where == "decode":  # the stream ends at the bad frame: every frame before it is processed
        assert slam.seen == list(range(7)) and [r.index for r in g.sink.results] == list(range(7))
    else:
        assert len(slam.seen) <= 7


def test_the_handlers_in_place_before_a_run_are_back_after_it() -> None:
    import signal

    from pipeline.runtime import execute

    def mine(signum, frame) -> None:  # type: ignore[no-untyped-def]
        pass

    previous = {sig: signal.signal(sig, mine) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        for loader in ("pipelined", "sync"):
            execute(graph(3, FakeSlam()), loader)
            assert signal.getsignal(signal.SIGINT) is mine and signal.getsignal(signal.SIGTERM) is mine
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@pytest.mark.parametrize("stop_after", [0.0, 0.013, 0.05, 0.107, 0.2])
def test_stop_finishes_the_current_frame_and_ends_cleanly(stop_after: float) -> None:
    """At any moment (asyncio.run also waits for every helper thread, so a hang shows here)."""
    slam = FakeSlam(delay=0.02)
    g = graph(1000, slam)

    async def main():
        stop = asyncio.Event()
        asyncio.get_running_loop().call_later(stop_after, stop.set)
        return await asyncio.wait_for(run_graph(g, stop), 10.0)

    report = asyncio.run(main())
    assert report.interrupted and report.frames < 1000
    assert slam.seen == list(range(len(slam.seen))) and len(g.sink.results) == len(slam.seen)


def test_the_sync_loop_processes_the_same_frames() -> None:
    import threading

    slam = FakeSlam()
    g = graph(20, slam)
    report = run_sync(g, threading.Event())
    assert slam.seen == list(range(20)) and report.loader == "sync"


def test_after_a_stop_request_no_new_frame_starts() -> None:
    """Stop asked while frame 3 is in SLAM: frame 3 finishes, frame 4 (already handed over to
    the SLAM thread) never starts."""
    started_3, release = threading.Event(), threading.Event()

    class HeldSlam(FakeSlam):
        def __call__(self, item: Item) -> Item:
            if item.index == 3:
                started_3.set()
                assert release.wait(10)
            return super().__call__(item)

    slam = HeldSlam()
    g = graph(50, slam)

    async def main():
        stop = asyncio.Event()

        async def stop_during_frame_3() -> None:
            assert await asyncio.to_thread(started_3.wait, 10)
            await asyncio.sleep(0.05)  # frame 4 reaches the SLAM thread's hand-off meanwhile
            stop.set()
            await asyncio.sleep(0.05)
            release.set()

        asyncio.get_running_loop().create_task(stop_during_frame_3())
        return await asyncio.wait_for(run_graph(g, stop), 20.0)

    report = asyncio.run(main())
    assert report.interrupted and slam.seen == [0, 1, 2, 3]


class LiveSource(ListSource):
    """A live source: items arrive every `period_s` whatever the consumer does, each stamped."""

    live = True

    def __init__(self, n: int, period_s: float) -> None:
        super().__init__(n, lambda item: item)
        self.period_s = period_s

    async def __aiter__(self):
        for i in range(self.n):
            await asyncio.sleep(self.period_s)
            yield Item(i, time.perf_counter())


def test_a_live_graph_starts_only_the_newest_frame_and_counts_the_rest() -> None:
    """Frames arrive 5x faster than SLAM takes them: every queue keeps the newest item and SLAM
    never starts a frame while a newer one waits, so a frame's age at the start of SLAM stays
    within two SLAM steps, and every frame is either processed or counted as dropped."""
    starts: list[tuple[int, float, float]] = []

    def slam(item: Item) -> Item:
        started = time.perf_counter()
        time.sleep(0.05)
        starts.append((item.index, started - item.received_at, time.perf_counter() - started))
        return item

    source = LiveSource(60, 0.01)
    stage = ThreadedStage("slam", slam, GpuSpans(torch.device("cpu")))
    stage.pass_over = stage.drop
    g = Graph(source, jittery, stage, CollectSink(), queue_size=4)  # type: ignore[arg-type]
    report = run(g)
    seen = [index for index, _, _ in starts]
    assert seen == sorted(seen) and len(seen) < 40
    assert len(seen) + sum(q["dropped"] for q in report.queues.values()) == 60
    ages = sorted(age for _, age, _ in starts)
    steps = sorted(step for _, _, step in starts)
    assert ages[len(ages) // 2] <= 2 * steps[len(steps) // 2]
