"""The optional parts of the install: which extra brings which module, and the line that says so."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

CHECKOUT = Path(__file__).resolve().parent.parent  # holds pyproject.toml when installed from a clone

# top-level module -> the extra of pyproject.toml that installs it
EXTRA_OF_MODULE = {
    "aiortc": "live",
    "aioice": "live",
    "av": "live",
    "aiohttp": "live",
    "cyclonedds": "live",
    "viser": "viewer",
    "open3d": "mesh",
    "ray": "cluster",
    "rerun": "rerun",
    "gtsam": "loops",
    "gsply": "spz",
    "pyrealsense2": "realsense",
    "rosbags": "rosbag",
}


def missing_extra(exc: ImportError) -> str | None:
    """One line naming the pip command when `exc` is a module of an extra that is not installed;
    None for any other import error."""
    module = (exc.name or "").split(".")[0]
    extra = EXTRA_OF_MODULE.get(module)
    if extra is None:
        return None
    return (
        f"this needs {module}, from the '{extra}' extra: pip install 'gsplatam[{extra}]' "
        f"(in a checkout: pip install -e '.[{extra}]')"
    )


def pip_command() -> str:
    """pip of this interpreter, as a shell calls it (a virtual environment need not be activated)."""
    return f"{shlex.quote(sys.executable)} -m pip"


def install_command(extra: str) -> str:
    """The shell command that installs `extra` into this interpreter: from the checkout this
    package was installed from (an editable install), else from the package index."""
    if (CHECKOUT / "pyproject.toml").is_file():
        return f"{pip_command()} install -e {shlex.quote(f'{CHECKOUT}[{extra}]')}"
    return f"{pip_command()} install 'gsplatam[{extra}]'"
