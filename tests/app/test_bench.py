"""The benchmark's table: ratios that compare, and a stop that ends it promptly and cleanly."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import ROOT

from pipeline.app import bench as bench_module
from pipeline.app.bench import Cell, add_ratios, run_matrix


def _row(preset: str, variant: str, total_ms: float, repeat: int = 0, error: str | None = None) -> dict[str, Any]:
    return {"sequence": "room", "preset": preset, "variant": variant, "repeat": repeat, "total_ms": total_ms,
            "fps_steady": None, "ate_rmse_cm": 1.0, "psnr_db": 30.0, "error": error}  # fmt: skip


def test_ratios_compare_with_the_first_variant_of_the_same_preset() -> None:
    rows = [
        _row("tiny", "default", 100),
        _row("tiny", "packed", 50),
        _row("small", "default", 300),
        _row("small", "packed", 600),
    ]
    assert add_ratios(rows) == "to variant 'default' of the same sequence and preset"
    assert [r["total_ms_ratio"] for r in rows] == [1.0, 0.5, 1.0, 2.0]


def test_with_one_variant_the_presets_are_compared_and_with_one_cell_nothing() -> None:
    rows = [_row("tiny", "default", 100), _row("small", "default", 400)]
    assert add_ratios(rows) == "to preset 'tiny' of the same sequence"
    assert [r["total_ms_ratio"] for r in rows] == [1.0, 4.0]  # no longer 1.00 for every preset
    alone = [_row("tiny", "default", 100)]
    assert add_ratios(alone) == "none (one cell per sequence)" and alone[0]["total_ms_ratio"] is None
    failed = [_row("tiny", "default", 100, error="UserError: x"), _row("tiny", "packed", 50)]
    add_ratios(failed)
    assert failed[1]["total_ms_ratio"] is None  # its reference failed


def test_the_matrix_reports_its_finished_cells_after_each_one(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A matrix killed midway (SIGKILL, a device call's time limit) keeps the cells it finished:
    the report of the cells so far goes out after each cell but the last (whose report is the
    whole matrix's), without the ratios of one report leaking into the next."""
    totals = iter([100.0, 50.0, 25.0])

    def fake_cell(cell: Cell, *args: object) -> dict[str, Any]:
        return {**_row(cell.preset, cell.variant, next(totals)), "interrupted": False}

    monkeypatch.setattr(bench_module, "run_cell_in_child", fake_cell)
    cells = [Cell("room", "tiny", variant, 0) for variant in ("default", "packed", "views2")]
    partial: list[dict[str, Any]] = []
    report = run_matrix(cells, [], tmp_path, torch.device("cpu"), False, on_report=partial.append)
    assert [[r["variant"] for r in p["rows"]] for p in partial] == [["default"], ["default", "packed"]]
    assert partial[0]["rows"][0]["total_ms_ratio"] is None and partial[1]["rows"][1]["total_ms_ratio"] == 0.5
    assert [r["total_ms_ratio"] for r in report["rows"]] == [1.0, 0.5, 0.25]


@pytest.mark.slow
def test_a_bench_stopped_by_sigterm_ends_promptly_with_its_run_folder_whole_and_its_table(tmp_path: Path) -> None:
    out, runs = tmp_path / "res", tmp_path / "runs"
    sizes = ["--set", "synthetic.frames=40", "--set", "synthetic.width=48", "--set", "synthetic.height=32"]
    argv = ["bench", "--presets", "tiny,small", "--out", str(out), "--runs", str(runs), "--quiet", *sizes]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with subprocess.Popen(
        [sys.executable, "-m", "pipeline", *argv], cwd=tmp_path, env=env, stderr=subprocess.PIPE, text=True
    ) as bench:
        first = runs / "synthetic_tiny_default"
        deadline = time.monotonic() + 240  # a hang guard, not a timing threshold
        while not ((first / "frames.csv").is_file() and len((first / "frames.csv").read_text().splitlines()) >= 3):
            assert bench.poll() is None and time.monotonic() < deadline, "the first cell did not start"
            time.sleep(0.2)
        bench.send_signal(signal.SIGTERM)
        _, err = bench.communicate(timeout=120)
    assert bench.returncode == 0, err
    assert "stopped by a signal: 1 of 2 cells in the table" in err
    report = json.loads((out / "bench.json").read_text())
    assert report["interrupted"] is True and [r["preset"] for r in report["rows"]] == ["tiny"]
    assert not (runs / "synthetic_small_default").exists()  # no cell began after the signal
    metrics = json.loads((first / "metrics.json").read_text())  # the interrupted cell's folder: whole
    assert metrics["interrupted"] is True and 2 <= metrics["frames"] < 40
    trajectory = [line for line in (first / "trajectory.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(trajectory) == metrics["frames"] and (first / "checkpoint.safetensors").is_file()
