"""Each benchmark cell in a process of its own: a crashed cell costs its row only, and a signal to
the bench's whole process group (a terminal's Ctrl-C, `timeout`) reaches the cell once.

The bench runs as a user starts it, in a session of its own (the group the test signals); waits
poll files with generous timeouts, never wall-clock speed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import ROOT
from live_helpers import spawned_children, wait_for

SIZES = ["--set", "synthetic.frames=40", "--set", "synthetic.width=48", "--set", "synthetic.height=32"]
FAST = ["--set", "tracking.iters=2", "--set", "mapping.iters=2", "--set", "run.eval_every=100"]
WAIT_S = 300  # a hang guard: two cores shared with other test workers


class Bench:
    """`gsplatam bench` in a session of its own, its output in a file; killed with its group on exit."""

    def __init__(self, tmp_path: Path, argv: list[str]) -> None:
        self.out, self.runs, self.log = tmp_path / "res", tmp_path / "runs", tmp_path / "bench.log"
        command = [
            sys.executable,
            "-m",
            "pipeline",
            "bench",
            "--quiet",
            "--out",
            str(self.out),
            "--runs",
            str(self.runs),
        ]
        with open(self.log, "w") as log:
            self.proc = subprocess.Popen(
                [*command, *SIZES, *FAST, *argv], cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)},
                stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip

    def wait_until_running(self, cell: str) -> int:
        """The pid of the process running `cell`, once its run has written a few frames."""
        rows = self.runs / cell / "frames.csv"
        wait_for(
            lambda: rows.is_file() and len(rows.read_text().splitlines()) >= 3, WAIT_S, f"{cell} running", self.log
        )
        (pid,) = spawned_children(self.proc.pid)
        return pid

    def ended(self) -> int:
        return self.proc.wait(WAIT_S)

    def report(self) -> list[dict[str, object]]:
        rows: list[dict[str, object]] = json.loads((self.out / "bench.json").read_text())["rows"]
        return rows

    def close(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()


@pytest.fixture
def benches() -> Iterator[list[Bench]]:
    started: list[Bench] = []
    yield started
    for bench in started:
        bench.close()


@pytest.mark.slow
def test_a_cell_whose_process_crashes_gives_a_row_saying_how_and_the_matrix_goes_on(
    tmp_path: Path, benches: list[Bench]
) -> None:
    bench = Bench(tmp_path, ["--repeats", "2"])
    benches.append(bench)
    os.kill(bench.wait_until_running("synthetic_tiny_default"), signal.SIGSEGV)  # as a CUDA library's crash
    assert bench.ended() == 1, bench.log.read_text()  # a cell failed
    crashed, second = bench.report()
    assert "ended with signal SIGSEGV before giving its row" in str(crashed["error"])
    assert crashed["interrupted"] is False
    assert second["error"] is None and second["repeat"] == 1 and second["frames"] == 40
    assert "1 of 2 cells failed" in bench.log.read_text()


@pytest.mark.slow
def test_ctrl_c_to_the_bench_group_stops_the_cell_once_and_the_matrix_after_it(
    tmp_path: Path, benches: list[Bench]
) -> None:
    """Under the process schedule a second signal would abandon the mapping process ("again"):
    the cell, a process group of its own, gets the one its parent forwards."""
    bench = Bench(tmp_path, ["--presets", "tiny,small", "--set", "slam.schedule=process"])
    benches.append(bench)
    bench.wait_until_running("synthetic_tiny_default")
    os.killpg(bench.proc.pid, signal.SIGINT)
    assert bench.ended() == 0, bench.log.read_text()
    said = bench.log.read_text()
    assert "stopped by a signal: 1 of 2 cells in the table" in said and "again" not in said
    (row,) = bench.report()
    assert row["interrupted"] is True and row["error"] is None
    metrics = json.loads((bench.runs / "synthetic_tiny_default" / "metrics.json").read_text())
    assert metrics["interrupted"] is True and 2 <= metrics["frames"] < 40
    assert not (bench.runs / "synthetic_small_default").exists()
