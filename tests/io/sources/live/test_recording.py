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
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.live.recording import LISTING_EVERY, RecordingSource
from pipeline.source import SourceCounters


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
    while source.recorder.listed < LISTING_EVERY and time.monotonic() < deadline:
        time.sleep(0.05)
    assert sum(not line.startswith("#") for line in listing.read_text().splitlines()) == LISTING_EVERY
    source.close()


def test_a_full_disk_is_reported_once_and_the_recording_lists_what_was_written_whole(
    frames: list[Frame], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import errno
    import logging
    import os

    from pipeline.io.sources.live import recording

    real = recording.write_color
    written: list[Path] = []

    def full_after_two(path: Path, color: np.ndarray) -> None:
        if len(written) >= 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written.append(path)
        real(path, color)

    monkeypatch.setattr(recording, "write_color", full_after_two)
    recorder = recording.TumRecorder(tmp_path / "recording")
    with caplog.at_level(logging.INFO, "gsplatam"):
        for i in range(6):
            recorder.put(replace(frames[0], index=i, timestamp=i / 30))
        recorder.close()  # the listings of the frames written whole; nothing raised
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "No space left on device" in errors[0].getMessage()
    assert "No space left on device" in recorder.error and recorder.listed == 2
    again = open_dataset(DatasetConfig(path=str(tmp_path / "recording")))
    assert len(again) == 2 and all(again.decode(ref) is not None for ref in again.refs)


def test_a_recording_whose_listing_cannot_be_written_at_the_end_keeps_the_last_listing(
    frames: list[Frame], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno
    import os

    from pipeline.io.sources.live import recording

    recorder = recording.TumRecorder(tmp_path / "recording")
    recorder.put(replace(frames[0], index=0, timestamp=0.0))
    deadline = time.monotonic() + 60
    while recorder.listed == 0 and time.monotonic() < deadline:  # the first frame's listing
        time.sleep(0.05)

    def full(*args: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(recording, "atomic_write_text", full)
    recorder.put(replace(frames[1], index=1, timestamp=1 / 30))
    recorder.close()
    assert "the listings" in recorder.error
    assert len(open_dataset(DatasetConfig(path=str(tmp_path / "recording")))) == 1
