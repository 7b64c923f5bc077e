"""The progress bar: frames/s, map size, lost frames, the ATE so far and a daemon's counters."""

from __future__ import annotations

import torch

from pipeline.slam.handoff import FrameResult
from pipeline.stages.frame_log import FrameLog
from pipeline.stages.sinks import ResultSink
from pipeline.ui.progress import ProgressBar


def test_the_progress_bar_shows_rate_map_size_lost_frames_and_the_ate_so_far() -> None:
    rows: list[FrameResult] = []
    log = FrameLog()
    bar = ProgressBar(log, total=5, enabled=True)
    sink = ResultSink(log, [rows.append, bar])
    for i in range(5):
        c2w, truth = torch.eye(4), torch.eye(4)
        c2w[0, 3], truth[0, 3] = 0.1 * i, 0.1 * i + (0.02 if i == 2 else 0.0)  # 2 cm off on one frame
        seconds = {"tracking": 0.01, "densify": 0.0, "mapping": 0.01, "total": 0.02}
        lost = "map covers only 4% of the valid pixels" if i == 3 else ""
        sink.consume(FrameResult(i, i / 30, c2w, seconds, 100 + i, 1, 0.0, 1.0, lost, c2w_gt=truth))
    bar.show({"received": 9, "dropped": 2})
    postfix = bar.bar.postfix
    bar.close()
    assert "gaussians=104" in postfix and "lost=1" in postfix and "fps=" in postfix
    assert "received=9" in postfix and "dropped=2" in postfix
    assert "ate=" in postfix and 0.0 < float(postfix.split("ate=")[1].split("cm")[0]) < 2.0  # rigid alignment lowers it
    assert len(rows) == 5
