"""live.record: the frames a live source decodes, kept as a TUM dataset that runs offline."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.config import DatasetConfig
from pipeline.frame import Frame
from pipeline.source import SourceCounters
from pipeline.sources.datasets.loader import open_dataset
from pipeline.sources.live.recording import LISTING_EVERY, RecordingSource


class FakeLive:
    """A live source of decoded frames (what a phone's decoder gives)."""

    name = "fake"
    live = True
    last_index = None

    def __init__(self, frames: list[Frame]) -> None:
        self.frames = frames
        self.counters = SourceCounters()

    async def __aiter__(self) -> AsyncIterator[int]:
        for i in range(len(self.frames)):
            yield i

    def decode(self, ref: int) -> Frame | None:
        return self.frames[ref] if ref % 4 != 3 else None  # every 4th is unusable (no depth)


@pytest.fixture
def frames(replica_seq: Path) -> list[Frame]:
    dataset = open_dataset(DatasetConfig(path=str(replica_seq)))
    decoded = [dataset.decode(ref) for ref in dataset.refs]
    for frame in decoded[::2]:  # a device pose as a tracking prior on some frames, as a reference on others
        frame.c2w_prior, frame.c2w_gt = frame.c2w_gt, None
    return decoded


def test_a_recording_reads_back_as_the_frames_that_were_decoded(frames: list[Frame], tmp_path: Path) -> None:
    source = RecordingSource(FakeLive(frames), tmp_path / "recording")

    async def pump() -> list[Frame]:
        return [f for ref in [r async for r in source] if (f := source.decode(ref)) is not None]

    decoded = asyncio.run(pump())
    source.close()
    source.close()  # idempotent
    recorded = open_dataset(DatasetConfig(path=str(tmp_path / "recording")))
    assert recorded.format == "tum" and len(recorded) == len(decoded)
    first_pose = decoded[0].c2w_prior
    assert first_pose is not None
    for ref, sent in zip(recorded.refs, decoded):
        frame = recorded.decode(ref)
        assert ref.timestamp == pytest.approx(sent.timestamp, abs=1e-6)
        assert np.array_equal(frame.color, sent.color)
        assert np.abs(frame.depth - sent.depth).max() <= 0.5 / 5000 + 1e-6  # TUM's 5000 units per metre
        assert np.allclose(frame.intrinsics, sent.intrinsics)
        device_pose = sent.c2w_gt if sent.c2w_gt is not None else sent.c2w_prior
        assert ref.c2w_gt is not None and device_pose is not None
        assert np.allclose(ref.c2w_gt, np.linalg.inv(first_pose) @ device_pose, atol=1e-6)  # TUM: relative


def test_listings_are_written_while_recording_so_a_killed_session_keeps_its_frames(
    frames: list[Frame], tmp_path: Path
) -> None:
    source = RecordingSource(FakeLive(frames), tmp_path / "recording")
    listing = tmp_path / "recording" / "rgb.txt"
    for i in range(LISTING_EVERY):
        source.recorder.put(replace(frames[i % len(frames)], index=i, timestamp=i / 30))
    deadline = time.monotonic() + 60
    while not listing.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert sum(not line.startswith("#") for line in listing.read_text().splitlines()) == LISTING_EVERY
    source.close()
