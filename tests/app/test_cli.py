from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import cv2
import pytest
from conftest import ROOT

from pipeline.app.cli import main
from pipeline.config import DatasetConfig
from pipeline.extras import unavailable_extra
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.io.outputs.exports import EXPORTERS
from pipeline.io.sources.datasets.loader import open_dataset


@pytest.mark.parametrize("command", [[], ["run"], ["synth"], ["bench"], ["serve"], ["view"], ["export"], ["config"]])
def test_help_everywhere(command: list[str], capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(command + ["--help"])
    assert exit_info.value.code == 0
    assert "usage: gsplatam" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["run", "--set", "tracking.nope=1"], "unknown config key 'tracking.nope'"),
        (["run", "--set", "tracking.iters=x"], "bad value for 'tracking.iters'"),
        (["run", "--preset", "huge"], "unknown preset 'huge'"),
        (["run", "/no/such/folder"], "dataset folder not found: /no/such/folder"),
        (["run", "--config", "/no/such.toml"], "config file not found"),
        (["synth", "x", "--layout", "replica", "--holes", "0.1"], "apply to the TUM layout only"),
        (["serve", "--record3d", "x", "--set", "live.retry_max_s=0"], "retry_initial_s <= retry_max_s"),
        (["run", "record3d:"], "needs the phone's address"),
        (["run", "nerfcapture:", "--loader", "sync"], "a live input takes none of"),
    ],
)
def test_user_errors_are_one_line_and_exit_2(argv: list[str], message: str, capsys, tmp_path: Path) -> None:
    code = main(argv + (["--output", str(tmp_path)] if argv[0] == "run" else []))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("gsplatam: error: ") and message in err[-1]
    assert "Traceback" not in "\n".join(err)


def test_help_points_to_the_config_command_and_synth_shows_its_sizes(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "gsplatam config" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["synth", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "default: 1200 with CUDA, 128 on the CPU" in out and "default: 200 with CUDA, 20 on the CPU" in out


def test_version(capsys) -> None:
    import pipeline

    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0 and capsys.readouterr().out.strip() == f"gsplatam {pipeline.__version__}"


@pytest.mark.parametrize("argv, level", [([], "INFO"), (["-v"], "DEBUG"), (["--log-level", "warning"], "WARNING")])
def test_log_level_options(argv: list[str], level: str, capsys) -> None:
    import logging

    logger = logging.getLogger("gsplatam")
    try:
        assert main(["config", "run", *argv]) == 0
        assert logging.getLevelName(logger.level) == level
    finally:
        logger.setLevel(logging.NOTSET)


def test_argparse_errors_exit_2_in_one_line(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "--loader", "fast"])
    assert exit_info.value.code == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_synth_writes_a_readable_tum_sequence_with_noise(tmp_path: Path) -> None:
    out = tmp_path / "seq"
    argv = ["synth", str(out), "--layout", "tum", "--frames", "4", "--width", "32", "--height", "24"]
    assert main(argv + ["--depth-noise", "0.01", "--holes", "0.05", "--time-jitter", "0.01", "--quiet"]) == 0
    dataset = open_dataset(DatasetConfig(path=str(out)))
    frames = list(dataset.frames())
    assert len(frames) == 4 and frames[0].depth.shape == (24, 32)
    assert (frames[1].depth == 0).mean() > 0.0


def run_folder(tmp_path: Path, name: str) -> Path:
    return tmp_path / "out" / name


@pytest.mark.slow
def test_run_then_resume_on_a_small_synthetic_sequence(
    replica_seq: Path, tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The run command end to end: the pipelined runtime, metrics, outputs, pictures; then
    --resume from another directory (the dataset was named by a relative path)."""
    monkeypatch.chdir(replica_seq.parent)
    base = ["run", replica_seq.name, "--preset", "tiny", "--output", str(tmp_path / "out"), "--name", "r", "--quiet"]
    assert main(base + ["--set", "dataset.end=4", "--set", "run.eval_every=2"]) == 0
    printed = capsys.readouterr().out
    assert "ATE RMSE / mean" in printed and "outputs:" in printed
    assert "  intrinsics.json" in printed and "evo_ape tum" in printed
    assert " export " in printed and "--to nerfstudio\n" in printed  # by python -m pipeline without gsplatam on PATH
    folder = run_folder(tmp_path, "r")
    for name in (
        "config.toml",
        "metrics.json",
        "frames.csv",
        "trajectory.txt",
        "groundtruth.txt",
        "map.ply",
        "checkpoint.safetensors",
    ):
        assert (folder / name).exists(), name
    assert len(read_tum_trajectory(folder / "trajectory.txt")[0]) == 4
    recorded = tomllib.loads((folder / "config.toml").read_text())["dataset"]
    assert recorded["path"] == str(replica_seq) and recorded["path_as_given"] == replica_seq.name
    renders = sorted(p.name for p in (folder / "renders").iterdir())
    assert renders == ["frame000000.png", "frame000002.png"]  # the evaluated frames, input beside render
    assert cv2.imread(str(folder / "renders" / renders[0])).shape == (2 * 48, 2 * 64, 3)
    assert cv2.imread(str(folder / "trajectory.png")) is not None
    render = json.loads((folder / "metrics.json").read_text())["render"]
    assert render["depth_rmse_cm"] >= render["depth_l1_cm"] > 0  # a root mean square is at least the mean

    monkeypatch.chdir(tmp_path)  # elsewhere: the run folder names its dataset by its absolute path
    assert main(["run", "--resume", str(folder), "--set", "dataset.end=-1", "--quiet"]) == 0
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["frames"] == 6 and metrics["frames_this_run"] == 2
    assert len(read_tum_trajectory(folder / "trajectory.txt")[0]) == 6
    assert len((folder / "frames.csv").read_text().splitlines()) == 1 + 6
    with open(folder / "frames.csv", newline="") as table:
        tracked = list(csv.DictReader(table))[1:]  # tiny tracks by alignment; the first frame is not tracked
    assert all(0 < float(row["inlier_fraction"]) <= 1 and int(row["renders"]) >= 1 for row in tracked)

    camera = json.loads((folder / "intrinsics.json").read_text())  # what exports need, from the run itself
    assert (camera["width"], camera["height"]) == (64, 48)
    for fmt, exporter in EXPORTERS.items():
        if exporter.NEEDS is not None and unavailable_extra(exporter.NEEDS):
            continue  # its extra is absent or cannot load (tests/io/outputs/test_exports.py says why)
        assert main(["export", str(folder), "--to", fmt]) == 0
        assert (folder / exporter.DEFAULT_NAME).exists(), fmt


@pytest.mark.slow
def test_twenty_frame_run_has_a_bounded_trajectory_error(tmp_path: Path) -> None:
    """20 frames of the synthetic room at 64x48 with the tiny preset, through the whole CLI."""
    sequence = tmp_path / "seq"
    assert main(["synth", str(sequence), "--frames", "20", "--width", "64", "--height", "48", "--quiet"]) == 0
    assert (
        main(["run", str(sequence), "--preset", "tiny", "--output", str(tmp_path / "out"), "--name", "t", "--quiet"])
        == 0
    )
    metrics = json.loads((run_folder(tmp_path, "t") / "metrics.json").read_text())
    assert metrics["frames"] == 20 and metrics["lost_frames"] == 0
    assert metrics["ate"]["rmse_cm"] < 5.0  # the camera moves ~20 cm over these frames
    assert metrics["render"]["psnr_db"] > 18.0


def test_a_bad_frame_stops_the_run_with_its_name(replica_seq: Path, tmp_path: Path, capsys) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(replica_seq, broken)
    (broken / "results" / "frame000003.jpg").write_bytes(b"truncated")
    code = main(["run", str(broken), "--preset", "tiny", "--output", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "stage 'decode' failed on frame 3: unreadable image" in err and "frame000003.jpg" in err


@pytest.mark.slow
def test_sigterm_finishes_the_frame_and_writes_the_run_folder(tmp_path: Path) -> None:
    sequence = tmp_path / "seq"
    assert main(["synth", str(sequence), "--frames", "60", "--width", "64", "--height", "48", "--quiet"]) == 0
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "run", str(sequence), "--preset", "tiny", "--output", str(out), "--name", "s", "--quiet"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    csv = out / "s" / "frames.csv"
    deadline = time.time() + 120
    while time.time() < deadline and (not csv.exists() or len(csv.read_text().splitlines()) < 3):
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr
    metrics = json.loads((out / "s" / "metrics.json").read_text())
    assert metrics["interrupted"] is True and 2 <= metrics["frames"] < 60
    assert (out / "s" / "map.ply").exists() and (out / "s" / "checkpoint.safetensors").exists()
    assert len(read_tum_trajectory(out / "s" / "trajectory.txt")[0]) == metrics["frames"]


def test_bench_writes_its_table_and_json(tmp_path: Path, capsys) -> None:
    """The benchmark harness at CPU size: the output schema, not the timings."""
    sizes = ["--set", "synthetic.frames=3", "--set", "synthetic.width=48", "--set", "synthetic.height=32"]
    argv = ["bench", "--presets", "tiny", "--variants", "default,3d-anisotropic", "--out", str(tmp_path / "res")]
    assert main(argv + ["--runs", str(tmp_path / "runs"), "--stem", "b", "--quiet", *sizes]) == 0
    report = json.loads((tmp_path / "res" / "b.json").read_text())
    assert {"device", "driver", "versions", "overrides", "profiled", "rows"} <= set(report)
    assert {"torch", "gsplat", "cuda", "commit", "python"} <= set(report["versions"])
    rows = report["rows"]
    assert [r["variant"] for r in rows] == ["default", "3d-anisotropic"]
    expected = {
        "tracking_ms",
        "densify_ms",
        "mapping_ms",
        "total_ms",
        "fps_steady",
        "gaussians",
        "ate_rmse_cm",
        "psnr_db",
        "depth_l1_cm",
        "total_ms_ratio",
    }
    assert all(expected <= set(r) for r in rows)
    assert rows[0]["total_ms_ratio"] == 1.0 and rows[0]["frames"] == 3
    table = (tmp_path / "res" / "b.md").read_text()
    assert "| sequence | preset | variant |" in table and table.count("\n| room_") == 2
    assert main(["bench", "--variants", "fast"]) == 2


def test_bench_generates_the_tum_like_sequence(tmp_path: Path) -> None:
    sizes = ["--set", "synthetic.frames=3", "--set", "synthetic.width=48", "--set", "synthetic.height=32"]
    argv = [
        "bench",
        "synthetic-tum",
        "--presets",
        "tiny",
        "--out",
        str(tmp_path / "res"),
        "--runs",
        str(tmp_path / "runs"),
    ]
    assert main(argv + ["--stem", "t", "--quiet", *sizes]) == 0
    (row,) = json.loads((tmp_path / "res" / "t.json").read_text())["rows"]
    assert "_tum_n0.0015_h0.02" in row["sequence"] and row["frames"] == 3
    generated = next((tmp_path / "runs" / "synthetic").iterdir())
    assert (generated / "rgb.txt").exists() and (generated / "groundtruth.txt").exists()


@pytest.mark.slow
def test_profiled_run_writes_a_trace_and_per_stage_host_times(replica_seq: Path, tmp_path: Path) -> None:
    argv = ["run", str(replica_seq), "--preset", "tiny", "--output", str(tmp_path / "out"), "--name", "p"]
    few_events = ["--set", "dataset.end=3", "--set", "mapping.iters=2"]  # parsing the profile takes most of the time
    assert main(argv + [*few_events, "--profile", "--quiet"]) == 0
    folder = run_folder(tmp_path, "p")
    assert json.loads((folder / "trace.json").read_text())["traceEvents"]
    stages = json.loads((folder / "metrics.json").read_text())["runtime"]["profile"]["stages"]
    assert {"decode", "tracking", "densify", "mapping"} <= set(stages)
    assert stages["mapping"]["count"] == 3 and stages["mapping"]["cpu_ms"] > 0
    assert "per stage:" in (folder / "profile.txt").read_text()


def test_stage_times_merge_the_host_and_device_rows_of_a_range() -> None:
    """With CUDA the profiler reports a range once on the host and once on the device."""
    from types import SimpleNamespace

    from pipeline.app.profiling import stage_times

    rows = [
        SimpleNamespace(key="mapping", count=60, cpu_time_total=4_187_000.0, device_time_total=527_000.0),
        SimpleNamespace(key="mapping", count=60, cpu_time_total=0.0, device_time_total=3_998_000.0),
        SimpleNamespace(key="aten::add", count=9, cpu_time_total=1.0, device_time_total=1.0),
    ]
    times = stage_times(rows)
    assert times == {"mapping": {"count": 60, "cpu_ms": 4187.0, "device_ms": 3998.0}}


def test_output_into_a_closed_pipe_ends_quietly_with_141() -> None:
    """`gsplatam config | head -1`, the reader gone before the first write: no traceback."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "pipeline", "config"], stdout=write_end, stderr=subprocess.PIPE, text=True, cwd=ROOT
        )
    finally:
        os.close(write_end)
    assert (done.returncode, done.stderr) == (141, "")


def test_a_shell_pipeline_into_head_prints_the_first_line_only() -> None:
    shell = f"set -o pipefail; {sys.executable} -m pipeline config | head -1"
    done = subprocess.run(["bash", "-c", shell], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode in (0, 141) and len(done.stdout.splitlines()) == 1
    assert "Traceback" not in done.stderr and "BrokenPipeError" not in done.stderr


@pytest.mark.parametrize("verbose", [True, False], ids=["-v", "default"])
def test_verbose_logs_each_frames_stage_times_tracker_verdict_and_the_saves(
    verbose: bool, replica_seq: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    import logging

    argv = ["run", str(replica_seq), "--preset", "tiny", "--output", str(tmp_path), "--quiet", "--set", "dataset.end=3"]
    try:
        assert main(argv + (["-v"] if verbose else [])) == 0
    finally:
        logging.getLogger("gsplatam").setLevel(logging.NOTSET)
    debug = [r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG and r.name == "gsplatam"]
    if not verbose:
        assert debug == []
        return
    frames = [line for line in debug if line.startswith("frame ")]
    assert [line.split(":")[0] for line in frames] == ["frame 0", "frame 1", "frame 2"]
    assert all("tracking " in line and " ms" in line and "tracker: ok" in line for line in frames[1:]), frames
    assert any(line.startswith("saving trajectory, map and checkpoint of 3 frames") for line in debug)


def test_libraries_info_lines_are_not_shown(caplog: pytest.LogCaptureFixture) -> None:
    """NumExpr (imported by pandas, which Ray imports) says how many threads it uses at INFO;
    matplotlib says it built its font cache: neither is the user's business."""
    import logging

    from pipeline.app.logs import configure_logging

    configure_logging()
    with caplog.at_level("INFO"):
        logging.getLogger("numexpr.utils").info("NumExpr defaulting to 2 threads.")
        logging.getLogger("matplotlib.font_manager").info("generated new fontManager")
        logging.getLogger("gsplatam").info("ours")
    assert [r.getMessage() for r in caplog.records] == ["ours"]
