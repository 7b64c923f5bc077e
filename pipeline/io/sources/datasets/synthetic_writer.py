"""Writing generated synthetic sequences to disk in the Replica or TUM layout."""

from __future__ import annotations

import contextlib
import json
import shutil
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import torch
from tqdm import tqdm

from pipeline.config import SyntheticConfig
from pipeline.errors import UserError
from pipeline.io.files.atomic import temporary_folder
from pipeline.io.files.folders import atomic_folder, make_folder
from pipeline.io.sources.datasets.replica import write_replica
from pipeline.io.sources.datasets.synthetic import CPU, sequence
from pipeline.io.sources.datasets.tum import write_tum

MANIFEST = "synthetic.json"


def _with_progress(frames: Iterator, total: int, progress: bool) -> Iterator:
    yield from tqdm(frames, total=total, unit="frame", desc="synth", disable=not progress, dynamic_ncols=True)


def write_synthetic(path: Path, config: SyntheticConfig, progress: bool = True, device: torch.device = CPU) -> int:
    """Generate `config.frames` frames (ray cast on `device`) and write them under `path` in
    `config.layout`; -> frames written. A manifest records the parameters, so a cached folder is
    reused only when it matches."""
    if config.frames <= 0 or config.width <= 0 or config.height <= 0:
        raise UserError("synthetic frames, width and height must be positive")
    if config.loops < 0:
        raise UserError("synthetic loops must be >= 0")
    if config.layout not in ("replica", "tum"):
        raise UserError(f"unknown layout '{config.layout}' (choose replica or tum)")
    if config.layout == "replica" and (config.depth_noise or config.holes or config.time_jitter):
        raise UserError("depth noise, holes and timestamp jitter apply to the TUM layout only")
    make_folder(path, "the sequence's folder")
    intrinsics, frames = sequence(config, device)
    frames = _with_progress(frames, config.frames, progress)
    if config.layout == "replica":
        count = write_replica(path, frames, intrinsics)
    else:
        count = write_tum(
            path, frames, intrinsics, config.fps, config.depth_noise, config.holes, config.time_jitter, config.seed
        )
    (path / MANIFEST).write_text(json.dumps(asdict(config), indent=2) + "\n")
    return count


def write_synthetic_folder(
    path: Path, config: SyntheticConfig, overwrite: bool = False, progress: bool = True, device: torch.device = CPU
) -> int:
    """`gsplatam synth`: the sequence into `path`, which must be absent or empty; with `overwrite`
    it may also be an earlier sequence of synth (it holds MANIFEST), which is then replaced as a
    whole (never mixed: a folder holding one layout's files and another's does not open right).
    The sequence is written beside its place and renamed into it. -> frames written."""
    if path.exists() and not path.is_dir():
        raise UserError(f"the sequence's folder {path} is a file, not a folder")
    if path.is_dir() and any(path.iterdir()):
        if not (path / MANIFEST).is_file():
            raise UserError(f"{path} holds files that synth did not write: choose an empty or new folder")
        if not overwrite:
            raise UserError(f"{path} holds an earlier sequence: replace it with --overwrite, or choose another folder")
    make_folder(path.parent, "the sequence's parent folder")
    count = 0

    def fill(staged: Path) -> None:
        nonlocal count
        count = write_synthetic(staged, config, progress, device)

    try:
        atomic_folder(path, fill)
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None
    return count


def cached_synthetic(root: Path, config: SyntheticConfig, progress: bool = True, device: torch.device = CPU) -> Path:
    """The folder of the synthetic sequence for `config`, generated on first use. It is written
    beside its place and renamed into it, so processes that want the same sequence at once (the
    cells of a bench on one node) each see it whole: the first rename wins, the others' copies go."""
    key = f"room_s{config.seed}_{config.width}x{config.height}_{config.frames}f_v{config.speed:g}_j{config.jitter:g}"
    if config.loops or config.trap:
        key += f"_l{config.loops}" + ("_trap" if config.trap else "")
    if config.layout == "tum":
        key += f"_tum_n{config.depth_noise:g}_h{config.holes:g}_t{config.time_jitter:g}"
    path = root / key
    if _matches(path, config):
        return path
    root.mkdir(parents=True, exist_ok=True)
    partial = temporary_folder(root, key)
    try:
        write_synthetic(partial, config, progress, device)
        if path.exists() and not _matches(path, config):
            shutil.rmtree(path)  # written for other parameters (an older version)
        with contextlib.suppress(OSError):  # another process renamed its copy first
            partial.rename(path)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return path


def _matches(path: Path, config: SyntheticConfig) -> bool:
    manifest = path / MANIFEST
    return manifest.exists() and json.loads(manifest.read_text()) == json.loads(json.dumps(asdict(config)))
