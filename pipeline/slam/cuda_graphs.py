"""A function of tensors recorded once per input shape as a CUDA graph, then replayed.

The align tracker's solve is ~100 small kernels whose launch costs more host time than their
GPU time; replaying a recorded graph launches them all at once. Inputs are copied into the
graph's own buffers and the outputs cloned out, so a replay never overwrites what a caller holds.
Recording runs in `thread_local` capture mode, so other threads (the upload's side-stream
copies) may keep working meanwhile; but a wait for the whole device waits on the stream under
capture too, which fails and spoils the recording, so recordings and such waits
(`synchronize_device`) take one lock (`DEVICE_WIDE`): under `slam.schedule=thread` both sides
record graphs and wait. Anything that cannot be recorded (a host read inside, an old driver)
makes it fall back to plain calls, said once in the log.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import torch
from torch.utils._pytree import tree_map

log = logging.getLogger("gsplatam")

T = TypeVar("T")
WARMUP_CALLS = 3  # before recording, on a side stream (compiled code settles, the allocator fills)
# Held while a graph is recorded and around every wait for the whole device (torch.cuda.graph's own
# at its start among them): such a wait fails while another thread's stream is under capture
# ("operation not permitted when stream is capturing", measured at 055e532), and the capture with it.
DEVICE_WIDE = threading.RLock()


def synchronize_device(device: torch.device | None = None) -> None:
    """torch.cuda.synchronize, never while another thread records a graph."""
    with DEVICE_WIDE:
        torch.cuda.synchronize(device)


@dataclass
class _Recorded(Generic[T]):
    graph: torch.cuda.CUDAGraph
    inputs: tuple[torch.Tensor, ...]
    output: T


class GraphCache(Generic[T]):
    def __init__(self, fn: Callable[..., T]) -> None:
        self.fn = fn
        self._recorded: dict[tuple[Any, ...], _Recorded[T]] = {}
        self.failed = False  # recording failed once: plain calls from then on

    def __call__(self, *inputs: torch.Tensor) -> T:
        if self.failed:
            return self.fn(*inputs)
        key = tuple((tuple(t.shape), t.dtype, t.device) for t in inputs)
        recorded = self._recorded.get(key)
        if recorded is None:
            try:
                recorded = self._record(inputs)
            except RuntimeError as exc:
                self.failed = True
                log.warning("CUDA graph of the alignment could not be recorded (%s): running it uncaptured", exc)
                return self.fn(*inputs)
            self._recorded[key] = recorded
        for static, new in zip(recorded.inputs, inputs):
            static.copy_(new)
        recorded.graph.replay()
        return tree_map(lambda x: x.clone() if isinstance(x, torch.Tensor) else x, recorded.output)

    def _record(self, inputs: tuple[torch.Tensor, ...]) -> _Recorded[T]:
        static = tuple(t.clone() for t in inputs)
        graph, output = record(lambda: self.fn(*static))
        return _Recorded(graph, static, output)


def record(fn: Callable[[], T], warmup: int = WARMUP_CALLS) -> tuple[torch.cuda.CUDAGraph, T]:
    """`fn` called `warmup` times on a side stream, then recorded once -> (the graph, the
    recording's output, whose memory each replay rewrites). The warm-up calls run for real (an
    optimiser step moves its parameters). Recording is `thread_local`: other threads of the
    process (the upload's side-stream copies) go on meanwhile, which the global mode refuses."""
    with DEVICE_WIDE:  # (the warm-up calls too: torch.cuda.graph's start waits for the device)
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(warmup):
                fn()
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, capture_error_mode="thread_local"):
            output = fn()
    return graph, output
