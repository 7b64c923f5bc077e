"""`bench --ray` and `serve --ray` on a local Ray cluster of 2 CPUs, started once for the module."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import ROOT
from live_helpers import free_port, read_status, wait_for

from pipeline.app.bench import cells_of, report_of, run_cell
from pipeline.app.cli import main
from pipeline.config import DatasetConfig
from pipeline.io.datasets.loader import open_dataset
from pipeline.io.live.fake_record3d import FakePhone

ray = pytest.importorskip("ray")

CHEAP = ["--set", "tracking.iters=2", "--set", "mapping.iters=2"]  # the SLAM is not under test here
DETERMINISTIC = ("sequence", "preset", "variant", "frames", "gaussians", "lost_frames", "error")


@pytest.fixture(scope="module")
def cluster() -> Iterator[str]:
    """A local cluster for the module -> its address; the commands run here use it as it is."""
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


def _bench(argv: list[str], out: Path) -> tuple[int, dict[str, Any]]:
    code = main(argv + ["--out", str(out), "--runs", str(out / "runs"), "--stem", "b", "--quiet"])
    return code, json.loads((out / "b.json").read_text())


@pytest.mark.slow
def test_a_bench_through_ray_gives_the_rows_of_the_sequential_run(
    cluster: str, replica_seq: Path, tmp_path: Path
) -> None:
    """Two cells through Ray and the same two here, one after the other, plus a cell whose
    dataset is missing: the same keys, the same deterministic results, the failure as a row."""
    matrix = ["bench", str(replica_seq), str(tmp_path / "missing"), "--presets", "tiny"]
    matrix += ["--variants", "default,3d-anisotropic", "--set", "dataset.end=2", *CHEAP]
    code_ray, on_ray = _bench(matrix + ["--ray", "--gpus-per-cell", "0.5"], tmp_path / "ray")
    code_here, here = _bench(matrix, tmp_path / "here")
    assert code_ray == code_here == 1  # a cell failed, and the table says which
    assert set(on_ray) == set(here)
    assert on_ray["cluster"]["address"] == cluster and here["cluster"] is None
    assert [[r.get(k) for k in DETERMINISTIC] for r in on_ray["rows"]] == [
        [r.get(k) for k in DETERMINISTIC] for r in here["rows"]
    ]
    for ray_row, local_row in zip(on_ray["rows"], here["rows"]):
        assert set(ray_row) == set(local_row)
        assert ray_row["node"] and ray_row["wall_s"] > 0
    good, missing = on_ray["rows"][0], on_ray["rows"][2]
    assert good["frames"] == 2 and good["gaussians"] > 0 and good["error"] is None
    assert "dataset folder not found" in missing["error"] and "frames" not in missing
    table = (tmp_path / "ray" / "b.md").read_text()
    assert "| node | gpu | error |" in table and "Ray cluster" in table


def test_a_cell_that_fails_is_a_row_with_its_error(tmp_path: Path) -> None:
    (cell,) = cells_of([str(tmp_path / "absent")], ["tiny"], ["default"])
    row = run_cell(cell, [], tmp_path, progress=False, profile=False)
    assert row["error"] == f"UserError: dataset folder not found: {tmp_path / 'absent'}"
    report = report_of([row], [], False, 1.0, None)
    assert report["rows"][0]["total_ms_ratio"] is None


def test_bad_ray_options_are_one_line_errors(capsys) -> None:
    """Reported before any cluster is reached."""
    assert main(["bench", "--ray", "--gpus-per-cell", "1.5", "--quiet"]) == 2
    assert "fraction up to 1 or a whole number" in capsys.readouterr().err
    assert main(["serve", "--record3d", "http://a", "--record3d", "http://b"]) == 2
    assert "several sources need --ray" in capsys.readouterr().err
    assert main(["serve", "--nerfcapture", "x", "--ray"]) == 2
    assert "bad DDS domain in 'nerfcapture:x'" in capsys.readouterr().err


class Phones:
    """Fake Record3D phones on one event loop in a thread, as devices apart from the daemon."""

    def __init__(self, dataset_path: Path, count: int) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        dataset = open_dataset(DatasetConfig(path=str(dataset_path)))
        self.phones = [FakePhone(dataset, fps=5, loop=True) for _ in range(count)]
        self.urls = [f"http://127.0.0.1:{self.call(lambda p=p: p.start('127.0.0.1', 0))}" for p in self.phones]

    def call(self, coro_fn: Callable[[], Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(coro_fn(), self.loop).result(timeout=30)

    def close(self) -> None:
        for phone in self.phones:
            self.call(phone.stop)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=10)


def _sessions(port: int) -> dict[str, dict[str, Any]]:
    return {s["source"]: s for s in (read_status(port) or {}).get("sessions", [])}


def _processed(session: dict[str, Any] | None) -> int:
    return ((session or {}).get("live") or {}).get("processed", 0)


@pytest.mark.slow
@pytest.mark.live
def test_serve_on_ray_maps_two_phones_and_survives_a_killed_session(
    cluster: str, replica_seq: Path, tmp_path: Path
) -> None:
    phones = Phones(replica_seq, 2)
    status_port = free_port()
    log_path = tmp_path / "driver.log"
    command = [sys.executable, "-m", "pipeline", "serve", "--ray", cluster, "--gpus-per-session", "0.5"]
    command += [arg for url in phones.urls for arg in ("--record3d", url)]
    command += [
        "--device", "cpu", "--preset", "tiny", "--output", str(tmp_path), "--quiet",
        "--set", f"live.status_port={status_port}", "--set", "live.save_every_s=0.5",
        "--set", "live.retry_initial_s=0.2", "--set", "live.stall_timeout_s=2",
    ]  # fmt: skip
    with open(log_path, "w") as log_file:
        driver = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT, cwd=ROOT)
    first, second = (f"record3d:{url}" for url in phones.urls)
    try:
        both = lambda: all(_processed(_sessions(status_port).get(s)) >= 2 for s in (first, second))  # noqa: E731
        wait_for(both, 240, "two frames in each session", log_path)
        sessions = _sessions(status_port)
        assert sessions[first]["folder"] != sessions[second]["folder"] and sessions[first]["node"]
        ray.kill(ray.get_actor(f"gsplatam:{sessions[first]['name']}", namespace="gsplatam"), no_restart=False)
        restarted = lambda: _sessions(status_port)[first]["restarts"] == 1  # noqa: E731
        wait_for(restarted, 60, "the killed session's restart", log_path)
        before = _processed(_sessions(status_port)[second])
        wait_for(lambda: _processed(_sessions(status_port)[second]) > before, 120, "frames after the kill", log_path)
        assert _sessions(status_port)[second]["state"] == "running"
    finally:
        driver.send_signal(signal.SIGINT)
        code = driver.wait(timeout=120)
        phones.close()
    assert code == 0, log_path.read_text()[-3000:]
    folders = [tmp_path / sessions[s]["folder"] for s in (first, second)]
    for folder in folders:
        assert (folder / "map.ply").stat().st_size > 1000 and (folder / "checkpoint.safetensors").exists()
    metrics = json.loads((folders[1] / "metrics.json").read_text())  # the survivor's final save
    assert metrics["frames"] > before and metrics["counters"]["connections"] >= 1
    assert (tmp_path / f"{sessions[first]['name']}_restart1" / "config.toml").exists()
