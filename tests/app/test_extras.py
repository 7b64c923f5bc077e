"""The base install: offline datasets run without the extras; a missing extra is one line naming
its pip command. The extras' modules are hidden from a subprocess by an import hook."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT

from pipeline.extras import EXTRA_OF_MODULE

HIDE_EXTRAS = f"""
import importlib.abc, sys
class HideExtras(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {sorted(EXTRA_OF_MODULE)!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None
sys.meta_path.insert(0, HideExtras())
from pipeline.app.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _gsplatam_without_extras(*argv: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-c", HIDE_EXTRAS, *argv], env=env, capture_output=True, text=True, timeout=600
    )


@pytest.mark.parametrize(
    "argv, extra",
    [
        (["serve", "--record3d", "http://127.0.0.1:9"], "live"),
        (["run", "SEQUENCE", "--viewer", "--set", "dataset.end=1", "--output", "OUT"], "viewer"),
        (["view", "MAP"], "viewer"),
        (["run", "SEQUENCE", "--viewer", "rerun", "--set", "viewer.rerun_save=OUT/r.rrd", "--output", "OUT"], "rerun"),
        (["view", "MAP", "--rerun"], "rerun"),
        (["bench", "--ray", "--presets", "tiny", "--out", "OUT"], "cluster"),
    ],
)
def test_a_missing_extra_is_one_line_naming_its_pip_command(
    argv: list[str], extra: str, replica_seq: Path, tmp_path: Path
) -> None:
    if argv[0] == "view":
        argv = ["view", str(_a_map(tmp_path)), *argv[2:]]
    done = _gsplatam_without_extras(
        *[a.replace("SEQUENCE", str(replica_seq)).replace("OUT", str(tmp_path)) for a in argv]
    )
    err = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr[-2000:]
    assert err[-1].startswith("gsplatam: error: this needs ") and f"pip install 'gsplatam[{extra}]'" in err[-1]
    assert "Traceback" not in done.stderr


def _a_map(folder: Path) -> Path:
    import torch

    from pipeline.io.outputs.ply import write_ply
    from pipeline.render import Gaussians

    one = Gaussians(
        torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.zeros(1, 1), torch.zeros(1), torch.zeros(1, 3)
    )
    write_ply(folder / "map.ply", one)
    return folder / "map.ply"


@pytest.mark.slow
def test_the_base_install_runs_a_dataset_and_exports_it(replica_seq: Path, tmp_path: Path) -> None:
    done = _gsplatam_without_extras(
        "run", str(replica_seq), "--preset", "tiny", "--output", str(tmp_path), "--name", "base", "--quiet",
        "--set", "dataset.end=3",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "base" / "metrics.json").is_file()
    exported = _gsplatam_without_extras("export", str(tmp_path / "base"), "--to", "splat")
    assert exported.returncode == 0 and (tmp_path / "base" / "map.splat").is_file()
    mesh = _gsplatam_without_extras("export", str(tmp_path / "base"), "--to", "mesh")
    assert mesh.returncode == 2 and "pip install 'gsplatam[mesh]'" in mesh.stderr.strip().splitlines()[-1]


UNLOADABLE = 'raise ImportError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")\n'


def test_an_extra_installed_but_unable_to_load_is_one_line_naming_the_system_library(tmp_path: Path) -> None:
    """Open3D's wheel links libusb, which a fresh Debian lacks: `import open3d` then fails in its
    own __init__ with the loader's message and no module name. A stand-in open3d that fails so
    (the test runs the same on a machine with libusb and one without)."""
    from conftest import write_gt_run

    fake = tmp_path / "fake"
    (fake / "open3d").mkdir(parents=True)
    (fake / "open3d" / "__init__.py").write_text(UNLOADABLE)
    run = write_gt_run(tmp_path / "runs")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(fake), str(ROOT)])}
    done = subprocess.run(
        [sys.executable, "-m", "pipeline", "export", str(run), "--to", "mesh"],
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("gsplatam: error: this needs open3d (the 'mesh' extra), which is installed but cannot load")
    assert "libusb-1.0.so.0" in line and "apt-get install libusb-1.0-0" in line
    assert not (run / "mesh.ply").exists()


def test_an_unloadable_extra_is_told_apart_from_a_missing_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from pipeline.extras import missing_extra, unavailable_extra

    missing = ModuleNotFoundError("No module named 'gtsam'", name="gtsam")
    assert "pip install 'gsplatam[loops]'" in (missing_extra(missing) or "")
    assert missing_extra(ModuleNotFoundError("No module named 'yaml'", name="yaml")) is None
    (tmp_path / "gsply").mkdir()
    (tmp_path / "gsply" / "__init__.py").write_text(
        'raise ImportError("libfoo.so.3: cannot open shared object file")\n'
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "gsply", raising=False)
    line = unavailable_extra("gsply") or ""
    assert "gsply (the 'spz' extra), which is installed but cannot load" in line and "libfoo.so.3" in line
    assert "package manager" in line and unavailable_extra("json") is None
