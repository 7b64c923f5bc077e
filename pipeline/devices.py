"""Choosing the compute device and the sizes that suit it."""

from __future__ import annotations

import os
import socket

import torch

from pipeline.config import DEFAULT_PRESET_CPU, Config
from pipeline.errors import UserError

LIVE_MAX_WIDTH_CPU = 128  # live frames are halved to this width for CPU runs (0: full size on a GPU)


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        if not torch.cuda.is_available():
            raise UserError("run.device=cuda but no CUDA device is available")
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device(name)


def live_max_width(device: torch.device) -> int:
    return 0 if device.type == "cuda" else LIVE_MAX_WIDTH_CPU


def default_preset(device: torch.device, live: bool = False) -> str:
    """base on a GPU for datasets; tiny on the CPU, and for live input everywhere (the only preset
    near camera rate: see the README's table of presets)."""
    return "base" if device.type == "cuda" and not live else DEFAULT_PRESET_CPU


def describe(device: torch.device, config: Config) -> str:
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)} (torch {torch.__version__}, CUDA {torch.version.cuda})"
    return f"CPU, {torch.get_num_threads()} threads (torch {torch.__version__}), renderer {config.render.backend}"


def placement() -> dict[str, str | None]:
    """Where this process computes: the host's name and, with CUDA, its GPU as the machine
    numbers it (through CUDA_VISIBLE_DEVICES, which Ray sets for its workers) and its model."""
    gpu = None
    if torch.cuda.is_available():
        index = torch.cuda.current_device()
        visible = [d for d in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if d.strip()]
        physical = visible[index] if index < len(visible) else str(index)
        gpu = f"{physical}: {torch.cuda.get_device_name(index)}"
    return {"node": socket.gethostname(), "gpu": gpu}
