"""Ordinary mistakes on the command line and in the input: one line naming the file, key or
port, exit code 2, no traceback."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import ROOT

from pipeline.app.cli import main
from pipeline.io.outputs.ply import write_ply
from pipeline.render.types import Gaussians


def _last_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    return err[-1]


def _without_root_override(argv: list[str]) -> subprocess.CompletedProcess[str]:
    """The command in a process that file permissions apply to: as root (who may read and write
    anything), without the capabilities that override them."""
    prefix: list[str] = []
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.skip("running as root without setpriv: permissions cannot be made to apply")
        prefix = ["setpriv", "--bounding-set=-dac_override,-dac_read_search", "--"]
    return subprocess.run(
        [*prefix, sys.executable, "-m", "pipeline", *argv], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip


def test_an_unreadable_dataset_folder_is_named(replica_seq: Path, tmp_path: Path) -> None:
    dataset = tmp_path / "room"
    shutil.copytree(replica_seq, dataset)
    dataset.chmod(0)
    try:
        done = _without_root_override(["run", str(dataset), "--output", str(tmp_path / "out"), "--quiet"])
    finally:
        dataset.chmod(0o755)
    assert done.returncode == 2, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last == f"gsplatam: error: cannot read the dataset folder {dataset}: permission denied"


def test_an_unwritable_output_folder_is_named(replica_seq: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir(mode=0o555)
    try:
        done = _without_root_override(["run", str(replica_seq), "--output", str(out), "--quiet"])
    finally:
        out.chmod(0o755)
    assert done.returncode == 2, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last == f"gsplatam: error: cannot write into the output folder {out}: permission denied"


def test_synth_into_a_file_is_refused(tmp_path: Path, capsys) -> None:
    target = tmp_path / "afile"
    target.write_text("x")
    assert main(["synth", str(target), "--frames", "2", "--width", "16", "--height", "12", "--quiet"]) == 2
    assert f"{target} is a file" in _last_error(capsys)


def test_the_fake_phones_port_taken_is_named(replica_seq: Path, capsys) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["fake-record3d", "--dataset", str(replica_seq), "--port", str(port), "--quiet"]) == 2
    assert f"cannot serve on 127.0.0.1:{port}" in _last_error(capsys)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["serve", "--record3d", "ftp://192.168.1.20"], "the app serves http://, not ftp://"),
        (["serve", "--record3d", "http://phone:99999"], "bad phone address 'http://phone:99999'"),
        (["run", "record3d:http://[::1"], "bad phone address"),
        (["serve", "--nerfcapture", "--set", "live.status_port=70000"], "live.status_port must be a port"),
        (["serve", "--nerfcapture", "--set", "live.status_port=-1"], "live.status_port must be a port"),
        (["run", "--viewer", "--viewer-port", "0"], "viewer.port must be a port"),
        (["view", "x.ply", "--viewer-port", "70000"], "--viewer-port 70000 is not a port"),
        (["fake-record3d", "--port", "-3"], "--port -3 is not a port"),
    ],
)
def test_bad_addresses_and_ports_are_named(argv: list[str], message: str, tmp_path: Path, capsys) -> None:
    assert main(argv + (["--output", str(tmp_path)] if argv[0] in ("run", "serve") else [])) == 2
    assert message in _last_error(capsys)


def _ply(path: Path) -> Path:
    """A valid map of 20 Gaussians."""
    n = 20
    write_ply(path, Gaussians(torch.zeros(n, 3), torch.ones(n, 4), torch.zeros(n, 1), torch.zeros(n), torch.rand(n, 3)))
    return path


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda raw: raw[:-100], "element 'vertex': row 18: early end-of-file"),
        (lambda raw: raw.replace(b"element vertex 20", b"element vertex many"), "expected integer count"),
        (lambda raw: raw.replace(b"element vertex 20\n", b""), "is not a PLY file that can be read"),
        (lambda raw: raw.replace(b"property float y\n", b"property float y\nproperty float x\n"), "same name"),
        (lambda raw: b"ply\nformat ascii 1.0\nend_header\n", "no 'element vertex' line"),
        (lambda raw: raw[:-4] + np.float32(np.nan).tobytes(), "holds NaN or infinite values"),
    ],
)
def test_a_truncated_or_malformed_ply_is_named_by_view(damage, message: str, tmp_path: Path, capsys) -> None:
    path = _ply(tmp_path / "map.ply")
    path.write_bytes(damage(path.read_bytes()))
    assert main(["view", str(path)]) == 2
    line = _last_error(capsys)
    assert message in line and str(path) in line


def test_a_preset_beside_a_config_naming_another_says_which_wins(tmp_path: Path, caplog) -> None:
    from pipeline.app.cli import build_parser
    from pipeline.app.commands.options import requested_config

    config_file = tmp_path / "c.toml"
    config_file.write_text('preset = "small"\n')
    args = build_parser().parse_args(["run", "--preset", "tiny", "--config", str(config_file)])
    with caplog.at_level("WARNING", "gsplatam"):
        config, _ = requested_config(args, live=False)
    assert config.preset == "small"
    assert f"--preset tiny is overridden by {config_file}, which names preset 'small'" in caplog.text


def test_a_first_frame_without_depth_is_refused_with_its_file(replica_seq: Path, tmp_path: Path, capsys) -> None:
    dataset = tmp_path / "room"
    shutil.copytree(replica_seq, dataset)
    cv2.imwrite(str(dataset / "results" / "depth000000.png"), np.zeros((48, 64), np.uint16))
    assert main(["run", str(dataset), "--output", str(tmp_path / "out"), "--quiet"]) == 2
    line = _last_error(capsys)
    assert "failed on frame 0" in line and "depth000000.png holds no valid depth" in line


@pytest.mark.parametrize("value", ["0", "-3"])
def test_synth_refuses_a_size_that_is_not_positive(tmp_path: Path, capsys, value: str) -> None:
    assert main(["synth", str(tmp_path / "seq"), "--frames", value, "--quiet"]) == 2
    assert f"--frames must be positive, not {value}" in _last_error(capsys)
    assert not (tmp_path / "seq").exists()


def test_synth_refuses_a_folder_that_holds_anything_unless_overwrite(tmp_path: Path, capsys) -> None:
    small = ["--frames", "2", "--width", "16", "--height", "12", "--quiet"]
    seq = tmp_path / "seq"
    assert main(["synth", str(seq), "--layout", "tum", *small]) == 0
    before = sorted(p.name for p in seq.iterdir())
    assert main(["synth", str(seq), "--layout", "replica", *small]) == 2
    assert f"{seq} holds an earlier sequence: replace it with --overwrite" in _last_error(capsys)
    assert sorted(p.name for p in seq.iterdir()) == before
    assert main(["synth", str(seq), "--layout", "replica", "--overwrite", *small]) == 0
    assert not (seq / "rgb.txt").exists() and (seq / "traj.txt").exists()  # replaced whole: one layout
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    assert main(["synth", str(mine), "--overwrite", *small]) == 2
    assert "holds files that synth did not write" in _last_error(capsys)
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]


def test_a_dataset_whose_rgb_folder_is_unreadable_is_named(tum_seq: Path, tmp_path: Path) -> None:
    dataset = tmp_path / "room"
    shutil.copytree(tum_seq, dataset)
    (dataset / "rgb").chmod(0)
    try:
        done = _without_root_override(["run", str(dataset), "--output", str(tmp_path / "out"), "--quiet"])
    finally:
        (dataset / "rgb").chmod(0o755)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert f"gsplatam: error: cannot read the folder {dataset / 'rgb'} (for " in done.stderr.strip().splitlines()[-1]
    assert "Permission denied" in done.stderr.strip().splitlines()[-1]


def test_an_unreadable_checkpoint_is_named_as_unreadable(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    checkpoint = run / "checkpoint.safetensors"
    checkpoint.write_bytes(b"x")
    checkpoint.chmod(0)
    done = _without_root_override(["export", str(run), "--to", "splat"])
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines()[-1] == f"gsplatam: error: cannot read {checkpoint}: permission denied"


@pytest.mark.parametrize(
    "options, message",
    [
        (["--fps", "0"], "--fps must be > 0"),
        (["--fps", "nan"], "--fps must be > 0"),
        (["--speed", "0", "--loops", "1"], "--speed must be > 0"),
        (["--width", "100000", "--height", "100000"], "--width must be 0 (by device) to 4096 pixels"),
        (["--loops", "100000"], "--loops must be 0 to 1000, not 100000"),
        (["--loops", "200", "--speed", "0.05"], "--loops 200 at --speed 0.05 and --fps 30 makes"),
        (["--holes", "2"], "--holes must be >= 0 and < 1"),
        (["--depth-noise", "-1"], "--depth-noise must be 0 to 1"),
        (["--loops", "-1"], "--loops must be 0 to 1000, not -1"),
        (["--seed", "-1"], "--seed must be >= 0"),
        (["--time-jitter", "0.5"], "--time-jitter must be >= 0 and < 0.08 s"),
        (["--layout", "tun"], "did you mean 'tum'?"),
    ],
)
def test_every_synth_option_is_checked_before_any_work(
    options: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if options[0] == "--layout":  # argparse's own check: it exits
        with pytest.raises(SystemExit) as exit_info:
            main(["synth", str(tmp_path / "seq"), *options])
        assert exit_info.value.code == 2
    else:
        assert main(["synth", str(tmp_path / "seq"), *options, "--quiet"]) == 2
    assert message in _last_error(capsys)
    assert not (tmp_path / "seq").exists()


def test_bench_out_naming_a_file_is_refused_before_any_cell(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    existing = tmp_path / "table.md"
    existing.write_text("mine\n")
    runs = tmp_path / "runs"
    assert main(["bench", "--out", str(existing), "--runs", str(runs), "--quiet"]) == 2
    assert f"--out {existing} is a file: name a folder" in _last_error(capsys)
    (tmp_path / "res" / "bench.json").mkdir(parents=True)
    assert main(["bench", "--out", str(tmp_path / "res"), "--runs", str(runs), "--quiet"]) == 2
    assert f"--out: {tmp_path / 'res' / 'bench.json'} is a folder" in _last_error(capsys)
    assert existing.read_text() == "mine\n" and not runs.exists()  # nothing ran


@pytest.mark.parametrize(
    "options, message",
    [
        (["--repeats", "0"], "--repeats must be at least 1, not 0"),
        (["--gpus-per-cell", "nan"], "--gpus-per-cell must be > 0, not nan"),
        (["--stem", "a/b"], "--stem must be a file name"),
        (["--variants", "defualt"], "unknown variant (--variants) 'defualt': did you mean 'default'?"),
        (["--presets", "tiny,smal"], "unknown preset 'smal': did you mean 'small'?"),
        (["--set", "mapping.final_iters=-5"], "mapping.final_iters must be >= 0"),
    ],
)
def test_every_bench_option_is_checked_before_any_cell(
    options: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    runs = tmp_path / "runs"
    assert main(["bench", "--out", str(tmp_path / "res"), "--runs", str(runs), *options, "--quiet"]) == 2
    assert message in _last_error(capsys)
    assert not runs.exists() and not (tmp_path / "res").exists()


def test_a_rerun_recording_naming_a_folder_is_refused_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    argv = ["run", "--output", str(out), "--viewer", "rerun", "--quiet"]
    assert main([*argv, "--set", f"viewer.rerun_save={tmp_path}"]) == 2
    assert f"viewer.rerun_save: {tmp_path} is a folder" in _last_error(capsys)
    assert main([*argv, "--set", f"viewer.rerun_save={tmp_path / 'no' / 'x.rrd'}"]) == 2
    assert f"viewer.rerun_save: the folder {tmp_path / 'no'} does not exist" in _last_error(capsys)
    assert not out.exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["run", "--set", "tracking.iterz=3"], "did you mean 'tracking.iters'?"),
        (["config", "trackin"], "did you mean 'tracking'?"),
        (["run", "--preset", "tinny"], "did you mean 'tiny'?"),
        (["bench", "--set", "mapping.final_iters=-5"], "mapping.final_iters must be >= 0"),
        (["serve", "--nerfcapture", "--set", "live.stall_timeout_s=0"], "live timeouts must be > 0"),
    ],
)
def test_a_config_mistake_is_answered_before_torch_is_imported(argv: list[str], message: str) -> None:
    """So that it is answered at once (the imports cost seconds): the command runs in a process
    that says afterwards whether torch was loaded."""
    script = (
        "import sys\nfrom pipeline.app.cli import main\ncode = main(sys.argv[1:])\n"
        "print('torch loaded' if 'torch' in sys.modules else 'torch not loaded')\nsys.exit(code)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, *argv], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2 and message in done.stderr.strip().splitlines()[-1], done.stderr
    assert done.stdout.strip() == "torch not loaded"
