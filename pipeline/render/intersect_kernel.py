"""Our CUDA kernel for the fixed-capacity tile intersections (csrc/intersect_tiles.cu), built
with torch's extension tools on first use and kept in the user's cache folder per build.

The tensor version in `intersections.py` gives the same list, but it searches and sorts the
whole capacity with 64-bit keys: 28-71% more kernel time per mapping step than gsplat's own
(bench/NOTES.md, Change 11). The kernel writes each Gaussian's entries from its offset and sorts
only the bits a key uses. Where it cannot be built (no compiler, no CUDA), the tensor version
runs, said once in the log.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
from pathlib import Path
from types import ModuleType

import torch

from pipeline.compile_cache import compile_cache_folder

log = logging.getLogger("gsplatam")

SOURCE = Path(__file__).parent / "csrc" / "intersect_tiles.cu"
NAME = "gsplatam_intersect_tiles"
_loaded: dict[str, ModuleType | None] = {}


def intersect_kernel(device: torch.device) -> ModuleType | None:
    """The built extension for `device`, or None where it cannot be built (once per process)."""
    if "module" not in _loaded:
        _loaded["module"] = _build(device)
    return _loaded["module"]


def _build(device: torch.device) -> ModuleType | None:
    """Imported from its build folder (named by the source's hash) where it was built before,
    else built there first."""
    from torch.utils.cpp_extension import load

    digest = hashlib.sha256(SOURCE.read_bytes()).hexdigest()[:12]
    folder = compile_cache_folder(device, "extensions") / f"intersect_tiles-{digest}"
    try:
        built = folder / f"{NAME}.so"
        if built.is_file():
            spec = importlib.util.spec_from_file_location(NAME, built)
            assert spec is not None and spec.loader is not None
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            return module
        folder.mkdir(parents=True, exist_ok=True)
        log.info("building the CUDA intersection kernel (once per build of torch, in %s)", folder)
        return load(name=NAME, sources=[str(SOURCE)], build_directory=str(folder), extra_cuda_cflags=["-O3"])
    except Exception as exc:  # a compiler's or loader's failure of any kind: the tensor version serves
        log.warning("the CUDA intersection kernel could not be built (%s): using the tensor version", exc)
        return None
