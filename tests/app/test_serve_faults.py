"""The daemon under a full disk: reported once (log and status), SLAM goes on, the last
complete save stays."""

from __future__ import annotations

import errno
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch
from live_helpers import free_port

from pipeline.app import serve as serve_module
from pipeline.app.setup import LIVE_LAYOUT, finish_config
from pipeline.config import DatasetConfig, load_config
from pipeline.errors import OutputError
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.source import DatasetSource

CPU = torch.device("cpu")


@pytest.mark.slow
def test_a_full_disk_is_reported_once_slam_goes_on_and_the_last_complete_save_stays(
    replica_seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    saves: list[int] = []
    real_write = RunFolder.write_state

    def full_after_the_first_save(self: RunFolder, *args: Any) -> None:
        saves.append(len(args[2]))
        if len(saves) > 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_write(self, *args)

    monkeypatch.setattr(RunFolder, "write_state", full_after_the_first_save)
    readers: list[Callable[[], dict[str, Any]]] = []
    real_reader = serve_module.status_reader

    def keep_reader(*args: Any) -> Callable[[], dict[str, Any]]:
        readers.append(real_reader(*args))
        return readers[-1]

    monkeypatch.setattr(serve_module, "status_reader", keep_reader)
    settings = [f"run.output={tmp_path}", "run.name=live", "run.device=cpu", "live.save_every_s=0.001",
                f"live.status_port={free_port()}", "tracking.iters=2", "mapping.iters=2"]  # fmt: skip
    config = load_config("tiny", overrides=settings)
    source = DatasetSource(open_dataset(DatasetConfig(path=str(replica_seq))))
    with caplog.at_level(logging.INFO, "gsplatam"):
        with pytest.raises(OutputError, match=r"No space left on device; the last complete save \(1 frames\) is kept"):
            serve_module.serve(finish_config(config, CPU, LIVE_LAYOUT, live=True), source, progress=False)
    reports = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(saves) >= 3 and len(reports) == 1  # periodic saves and the final one failed: one report
    status = readers[0]()
    assert "No space left on device" in status["save_error"] and status["saved_frames"] == 1
    assert status["processed"] == 6  # SLAM went on
    folder = RunFolder(tmp_path / "live")
    assert folder.read_checkpoint()[0].frames_done == 1 and len(folder.frames_csv.read_text().splitlines()) == 7


def test_the_bar_shows_the_daemons_counters_without_computing_the_status() -> None:
    """The progress bar's counters, refreshed every second, are read from the source, the sink
    and the queues directly (the full status computes percentiles and the ATE over all frames)."""
    from types import SimpleNamespace

    from pipeline.source import SourceCounters
    from pipeline.stages.frame_log import FrameLog

    frames = FrameLog()
    frames.results.extend([object()] * 3)  # type: ignore[list-item]
    session = SimpleNamespace(source=SimpleNamespace(counters=SourceCounters(received=7)), log=frames)
    graph = SimpleNamespace(dropped=lambda: {"source": 2, "uploaded": 1})
    counters = serve_module.bar_counters(session, graph)  # type: ignore[arg-type]
    assert counters == {"received": 7, "processed": 3, "dropped": 3, "age": "-"}


@pytest.mark.slow
def test_a_recording_on_a_full_disk_loses_neither_the_sessions_results_nor_what_it_recorded(
    replica_seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import json

    from pipeline.io.sources.live import recording

    real, written = recording.write_color, []

    def full_after_two(path: Path, color: Any) -> None:
        if len(written) >= 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written.append(path)
        real(path, color)

    monkeypatch.setattr(recording, "write_color", full_after_two)
    settings = [f"run.output={tmp_path}", "run.name=live", "run.device=cpu", "live.record=true",
                "live.status_port=0", "tracking.iters=2", "mapping.iters=2"]  # fmt: skip
    config = load_config("tiny", overrides=settings)
    source = DatasetSource(open_dataset(DatasetConfig(path=str(replica_seq))))
    with caplog.at_level(logging.INFO, "gsplatam"):
        result = serve_module.serve(finish_config(config, CPU, LIVE_LAYOUT, live=True), source, progress=False)
    assert result.metrics is not None and result.metrics.frames == 6  # SLAM went on
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "recording" in errors[0].getMessage()
    folder = RunFolder(tmp_path / "live")
    assert "No space left on device" in json.loads(folder.metrics.read_text())["write_error"]
    assert folder.read_checkpoint()[0].frames_done == 6
    assert len(open_dataset(DatasetConfig(path=str(folder.recording)))) == 2  # what was written whole: re-runnable
