"""Where torch.compile and our CUDA extension keep what they compiled, so that a second run on
the machine starts warm.

Inductor caches compiled graphs and Triton kernels under TORCHINDUCTOR_CACHE_DIR, by default a
folder in /tmp that a reboot or a tmp cleaner empties. Runs keep theirs in the user's cache
folder instead, one folder per torch and CUDA version and device, so no build ever reads
another's kernels. A folder the user set is kept.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import torch

CACHE_VARIABLE = "TORCHINDUCTOR_CACHE_DIR"


def compile_cache_folder(device: torch.device, kind: str = "inductor") -> Path:
    """$XDG_CACHE_HOME (or ~/.cache)/gsplatam/<kind>/<torch, CUDA and device>: `kind` inductor
    for torch.compile's caches, extensions for our CUDA extension's build."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    build = f"torch-{torch.__version__}-cuda-{torch.version.cuda or 'none'}-{name}"
    return base / "gsplatam" / kind / re.sub(r"[^A-Za-z0-9.+_-]+", "_", build)


def persist_compile_cache(device: torch.device) -> Path:
    """Point inductor at `compile_cache_folder` unless the user chose one; -> the folder used.
    Inductor reads the variable at each compile, so this works until the first one."""
    chosen = os.environ.get(CACHE_VARIABLE)
    if chosen:
        return Path(chosen)
    folder = compile_cache_folder(device)
    folder.mkdir(parents=True, exist_ok=True)
    os.environ[CACHE_VARIABLE] = str(folder)
    return folder


def compile_seconds() -> float | None:
    """torch.compile's own account of the wall time it has spent compiling in this process so far
    (dynamo's tracing, inductor's work, cache hits included: a warm on-disk cache shortens it,
    never to zero, since tracing is redone in every process); None where this torch keeps none."""
    try:
        from torch._dynamo.utils import calculate_time_spent
    except ImportError:
        return None
    return float(calculate_time_spent().get("total_wall_time", 0.0))
