"""The end of the graph: each result stamped with its arrival, logged, and handed on."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from pipeline.slam.handoff import FrameResult
from pipeline.stages.frame_log import FrameLog
from pipeline.stages.queues import EndOfStream, StageQueue

ResultConsumer = Callable[[FrameResult], None]  # runs on the event loop: it must be quick


class ResultSink:
    """Takes the results off the graph's last queue: stamps a live frame's age, adds each to
    `log` and hands it to every consumer in order (the run folder's frames.csv, the progress
    bar). A consumer that raises ends the run."""

    def __init__(self, log: FrameLog, consumers: Sequence[ResultConsumer] = ()) -> None:
        self.log = log
        self.consumers = tuple(consumers)

    @property
    def results(self) -> list[FrameResult]:
        return self.log.results

    def consume(self, result: FrameResult) -> None:
        now = time.perf_counter()
        if result.received_at is not None:
            result.age_s = now - result.received_at
        self.log.add(result, now)
        for consumer in self.consumers:
            consumer(result)

    async def drain(self, inbox: StageQueue[FrameResult]) -> None:
        while not isinstance(result := await inbox.get(), EndOfStream):
            self.consume(result)
