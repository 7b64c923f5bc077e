"""The optional parts of the install: which extra brings which module, and the line that says so."""

from __future__ import annotations

import importlib
import re
import shlex
import sys
import traceback
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

# A system library an extra's wheel links (the loader's "cannot open shared object file") ->
# the Debian/Ubuntu package that brings it (Open3D's wheel: libusb, GL and EGL).
SYSTEM_PACKAGE_OF_LIBRARY = {
    "libusb-1.0.so.0": "libusb-1.0-0",
    "libGL.so.1": "libgl1",
    "libEGL.so.1": "libegl1",
    "libgomp.so.1": "libgomp1",
    "libX11.so.6": "libx11-6",
}
_MISSING_LIBRARY = re.compile(r"(\S+\.so[.\d]*): cannot open shared object file")


def missing_extra(exc: ImportError) -> str | None:
    """One line when `exc` comes from a module of an extra: not installed (its pip command), or
    installed but unable to load (the system library it lacks and the package that brings it,
    or the loader's own words); None for any other import error."""
    module = (exc.name or "").split(".")[0]
    if module in EXTRA_OF_MODULE and isinstance(exc, ModuleNotFoundError):
        extra = EXTRA_OF_MODULE[module]
        return (
            f"this needs {module}, from the '{extra}' extra: pip install 'gsplatam[{extra}]' "
            f"(in a checkout: pip install -e '.[{extra}]')"
        )
    module = _extra_raising(exc) or (module if module in EXTRA_OF_MODULE else "")
    if not module:
        return None
    return (
        f"this needs {module} (the '{EXTRA_OF_MODULE[module]}' extra), which is installed but cannot load: {_why(exc)}"
    )


def unavailable_extra(module: str) -> str | None:
    """None when `module` (of an extra) imports; else the line `missing_extra` gives for it."""
    try:
        importlib.import_module(module)
    except ImportError as exc:
        return missing_extra(exc) or f"{module} cannot be imported: {exc}"
    return None


def _extra_raising(exc: ImportError) -> str | None:
    """The extra's module whose own code raised `exc` (the innermost such frame), if any: an
    installed module failing to load its compiled part names no module in the error itself."""
    names = [frame.f_globals.get("__name__", "") for frame, _ in traceback.walk_tb(exc.__traceback__)]
    found = [name.split(".")[0] for name in names if name.split(".")[0] in EXTRA_OF_MODULE]
    return found[-1] if found else None


def _why(exc: ImportError) -> str:
    """What keeps an installed module from loading, in words a user can act on."""
    library = _MISSING_LIBRARY.search(str(exc))
    if library is None:
        return str(exc)
    name = library.group(1)
    package = SYSTEM_PACKAGE_OF_LIBRARY.get(name)
    if package is None:
        return f"the system library {name} is missing (install it with the system's package manager)"
    return f"the system library {name} is missing; Debian's and Ubuntu's package {package} brings it: apt-get install {package}"


def pip_command() -> str:
    """pip of this interpreter, as a shell calls it (a virtual environment need not be activated)."""
    return f"{shlex.quote(sys.executable)} -m pip"


def install_command(extra: str) -> str:
    """The shell command that installs `extra` into this interpreter: from the checkout this
    package was installed from (an editable install), else from the package index."""
    if (CHECKOUT / "pyproject.toml").is_file():
        return f"{pip_command()} install -e {shlex.quote(f'{CHECKOUT}[{extra}]')}"
    return f"{pip_command()} install 'gsplatam[{extra}]'"
