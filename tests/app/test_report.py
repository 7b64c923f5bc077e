"""What a run prints at its end: the files and the commands that take it further."""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
import torch
from conftest import ROOT, write_gt_run

from pipeline.app import report
from pipeline.extras import CHECKOUT, install_command, pip_command
from pipeline.io.outputs.exports import EXPORTERS
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.outputs.run_metrics import ClosedLoopRow, LoopRecord, RunMetrics


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = write_gt_run(tmp_path_factory.mktemp("a run"))  # a space: every path is quoted
    (run / "groundtruth.txt").write_text((run / "trajectory.txt").read_text())
    return run


def _next(run_dir: Path) -> list[str]:
    return [line.strip() for line in report.next_steps(RunFolder(run_dir))]


def test_next_lines_are_one_command_each_that_a_shell_parses(run_dir: Path) -> None:
    lines = _next(run_dir)
    assert len(lines) == 2 + len(EXPORTERS)  # view, evo, one export per format
    for line in lines:
        command = _command(line)
        assert "|" not in command, line
        assert subprocess.run(["bash", "-n", "-c", command]).returncode == 0, line
    assert [shlex.split(_command(line))[-1] for line in lines if " export " in line] == list(EXPORTERS)


def test_an_extra_installed_but_unable_to_load_is_named_not_offered(
    run_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """open3d installed without the libusb its wheel links: the mesh export's line says so, as a
    comment that a pasted block skips, instead of a command that ends in a traceback."""
    import importlib

    real_import, real_spec = importlib.import_module, importlib.util.find_spec

    def failing(name: str, package: str | None = None):  # type: ignore[no-untyped-def]
        if name == "open3d":
            raise ImportError(
                "libusb-1.0.so.0: cannot open shared object file: No such file or directory", name="open3d"
            )
        return real_import(name, package)

    monkeypatch.setattr(importlib, "import_module", failing)
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: object() if name == "open3d" else real_spec(name))
    (mesh,) = [line for line in _next(run_dir) if "--to mesh" in line]
    assert mesh.startswith("# ") and "libusb-1.0-0" in mesh and "cannot load" in mesh


def test_what_is_not_installed_comes_with_its_install_command(
    run_dir: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.setattr(sysconfig, "get_path", lambda name: str(tmp_path))  # an environment without evo
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None if name in ("open3d", "viser") else real(name))
    lines = _next(run_dir)
    (evo,) = [line for line in lines if "evo_ape" in line]
    (mesh,) = [line for line in lines if line.split("   #")[0].endswith("--to mesh")]
    # evo_ape by the path pip installs it at in this environment: no PATH (no activated venv) needed
    assert evo.startswith(f"{pip_command()} install evo && {shlex.quote(str(tmp_path / 'evo_ape'))} tum ")
    assert mesh.startswith(f"{install_command('mesh')} && ") and " -m pipeline export " in mesh
    assert lines[0].startswith(f"{install_command('viewer')} && ")
    assert "-e" in shlex.split(install_command("mesh")) and f"{CHECKOUT}[mesh]" in shlex.split(install_command("mesh"))
    assert not any(" -m pip " in line for line in lines if line not in (evo, mesh, lines[0]))


def test_an_export_line_runs_as_printed(run_dir: Path) -> None:
    (line,) = [line for line in _next(run_dir) if line.endswith("--to splat")]
    done = subprocess.run(["bash", "-c", line], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert RunFolder(run_dir).export("splat").stat().st_size > 0


def test_loop_closure_is_reported_only_where_it_ran() -> None:
    row = ClosedLoopRow(40, [3], 2.5, 1.5, 40.0, 125.0, 500.0)
    loops = RunMetrics("room", frames=100, loops=LoopRecord(detected=8, accepted=3, rejected=5, closed=[row, row]))
    line = "2 closed (3 accepted, 5 rejected of 8 candidates)"
    assert re.search(rf"^  loops +{re.escape(line)}$", report.format_table(loops), re.MULTILINE)
    assert report.run_summary(loops).endswith(f", loops: {line}")
    plain = RunMetrics("room", frames=100)
    assert "loops" not in report.format_table(plain) and "loops" not in report.run_summary(plain)


def test_the_warm_up_is_timed_from_the_pipelines_start() -> None:
    """The first result 2 s after the start, the last warm-up frame's 3 s after it: metrics.json
    states both beside the steady and the whole-run rates."""
    from types import SimpleNamespace

    from pipeline.app.report import WARMUP_FRAMES, timing_summary
    from pipeline.slam.handoff import FrameResult
    from pipeline.stages.frame_log import FrameLog

    frames = FrameLog()
    frames.started_at = 10.0
    for i, arrived in enumerate((12.0, 12.5, 13.0, 13.1, 13.2)):
        seconds = {"tracking": 0.1 * i, "densify": 0.01, "mapping": 1.0 if i == 0 else 0.02}
        frames.add(
            FrameResult(i, i / 30, torch.eye(4), {**seconds, "total": sum(seconds.values())}, 0, 0, 0.0, 1.0), arrived
        )
    timing = timing_summary(frames, SimpleNamespace(frames=5, wall_s=4.0, compile_s=1.5))  # type: ignore[arg-type]
    assert WARMUP_FRAMES == 2 and timing.first_result_s == 2.0 and timing.warmup_s == 3.0
    assert timing.fps_wall == 1.25 and timing.fps_steady == pytest.approx(2 / 0.2)
    # where the warm-up went: frames 0-2's seconds per stage, and torch.compile's share
    assert timing.warmup_stages_s == pytest.approx({"tracking": 0.3, "densify": 0.03, "mapping": 1.04})
    assert timing.compile_s == 1.5


def test_compile_seconds_count_a_compile_in_this_process() -> None:
    """torch.compile's own account grows by a compile made here and not by a call of what it
    compiled (the warm-up's compile share in metrics.json is this difference over a run)."""
    from pipeline.compile_cache import compile_seconds

    scaled = torch.compile(lambda x: 3 * x + 1, backend="eager")  # dynamo's tracing, no codegen: quick
    before = compile_seconds()
    assert before is not None
    scaled(torch.ones(3))
    compiled = compile_seconds()
    assert compiled is not None and compiled > before
    scaled(torch.ones(3))
    assert compile_seconds() == compiled


BARE_PATH = "/usr/bin:/bin"  # a shell's PATH without this Python's environment (no activated venv)


def _command(line: str) -> str:
    """A printed line's command without its comment; a command printed commented out (its extra
    cannot load here) as it will run once installed."""
    return line.removeprefix("# ").split("   #")[0]


def _program(line: str) -> str:
    """The program a printed command runs (after an install step), as the shell finds it."""
    return shlex.split(_command(line).split(" && ")[-1])[0]


@pytest.mark.slow
def test_every_printed_command_runs_as_pasted_into_a_shell_without_the_environment_activated(run_dir: Path) -> None:
    """The lines a run prints at its end ('next:', and the resume line of a stopped run), as a
    run in a shell without its virtual environment on the PATH builds them, each run in such a
    shell: none is 'command not found'."""
    env = {**{k: v for k, v in os.environ.items() if k != "VIRTUAL_ENV"}, "PATH": BARE_PATH, "PYTHONPATH": str(ROOT)}
    script = (
        "import sys\nfrom pathlib import Path\nfrom pipeline.app.report import next_steps, resume_command\n"
        "from pipeline.io.outputs.run_folder import RunFolder\nfolder = RunFolder(Path(sys.argv[1]))\n"
        "print('\\n'.join(line.strip() for line in next_steps(folder)))\nprint(resume_command(folder.path))\n"
    )
    built = subprocess.run([sys.executable, "-c", script, str(run_dir)], env=env, capture_output=True, text=True)
    assert built.returncode == 0, built.stderr
    lines = built.stdout.strip().splitlines()
    for line in lines:  # every program is found in that shell: by its path, or on the bare PATH
        program = _program(line)
        assert os.path.isabs(program) or shutil.which(program, path=BARE_PATH), line
    view, evo = lines[0], next(line for line in lines if "evo_ape" in line)
    splat = next(line for line in lines if line.endswith("--to splat"))
    for line, says in ((evo, "rmse"), (splat, "wrote ")):
        done = subprocess.run(["bash", "-c", line], env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0 and says in done.stdout, (line, done.stderr)
    resumed = subprocess.run(["bash", "-c", lines[-1]], env=env, capture_output=True, text=True, timeout=300)
    assert resumed.returncode in (0, 2) and "gsplatam: " in resumed.stderr, resumed.stderr  # gsplatam ran
    with subprocess.Popen(
        ["bash", "-c", f"exec {view}"], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    ) as shown:
        assert shown.stdout is not None
        printed = []
        for line in iter(shown.stdout.readline, ""):  # viser's banner, then ours
            printed.append(line)
            if line.startswith("showing "):
                break
        shown.send_signal(signal.SIGINT)  # the way to quit it
        assert shown.wait(timeout=60) == 0, "".join(printed)
    assert "Gaussians at http://" in printed[-1], printed
