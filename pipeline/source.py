"""The contract every frame source implements: datasets on disk and live cameras alike.

A source lists references to frames on the event loop (`async for ref in source`) and turns one
reference into a `Frame` in a worker thread (`source.decode(ref)`), so listing never waits for
decoding. The end of the iteration is the end of the stream. Adding a camera is one module that
implements this protocol; the runtime and the commands need no change.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from pipeline.frame import Frame


@dataclass
class SourceCounters:
    """What a source reports about its input (the status endpoint, metrics.json)."""

    received: int = 0  # items taken from the input
    skipped: int = 0  # usable messages without a usable frame (no depth, odd size, all invalid)
    rejected: int = 0  # malformed, duplicate or out-of-order messages
    ignored: int = 0  # frames of another publisher than the one followed (NeRFCapture)
    connected: bool = False  # a live peer is streaming now (always False for files)
    stage: str = ""  # a live connection's progress where the source has stages (Record3D's `Stage`)
    connections: int = 0  # live connections made so far
    last_error: str = ""


@runtime_checkable
class Source(Protocol):
    """Frames entering the pipeline. `live` sources never wait for SLAM: every queue keeps the
    newest item. `last_index` is the index of the final frame when the stream's length is known
    (datasets), else None."""

    name: str
    live: bool
    counters: SourceCounters

    @property
    def last_index(self) -> int | None: ...

    def __aiter__(self) -> AsyncIterator[Any]: ...

    def decode(self, ref: Any) -> Frame | None:
        """One reference -> a frame on the host, or None when it is unusable (counted in
        `counters.skipped`). Runs in a worker thread; may raise `DataError` for bad input."""
        ...
