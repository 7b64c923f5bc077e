"""The checkpoint file: tensors in safetensors, everything else as JSON in its header.

Loading it never executes anything from the file (no pickle): a downloaded run folder cannot
run code on `--resume`. Keyframe images are stored as they are kept (colour uint8, depth
float32 metres), so a checkpoint of hundreds of keyframes stays a plain tensor file.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save

from pipeline.errors import DataError
from pipeline.io.files.atomic import atomic_write_bytes
from pipeline.io.outputs.run_description import RunDescription
from pipeline.render.types import Gaussians
from pipeline.slam.gaussian_map import PARAMETER_NAMES
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.loops.detection import ClosedLoop, LoopTally
from pipeline.slam.loops.pose_graph import Edge, MotionSize
from pipeline.slam.state import BackendState, Checkpoint, FrontendState, LoopState

FORMAT = "gsplatam.checkpoint"
VERSION = 1
LEGACY_NAME = "checkpoint.pt"  # the pickle checkpoints of gsplatam 0.1, never loaded


def write_checkpoint(path: Path, checkpoint: Checkpoint, run: RunDescription) -> None:
    """Write `checkpoint` atomically; `run` describes the run it belongs to, so that a resume
    can check it continues the same dataset, size and map kind."""
    atomic_write_bytes(path, checkpoint_bytes(checkpoint, run))


def checkpoint_bytes(checkpoint: Checkpoint, run: RunDescription) -> bytes:
    """The checkpoint file's bytes (see `write_checkpoint`)."""
    tracking, mapping = checkpoint.tracking, checkpoint.mapping
    tensors = {f"gaussians.{n}": getattr(mapping.gaussians, n).contiguous() for n in PARAMETER_NAMES}
    for i, k in enumerate(mapping.keyframes):
        tensors.update(
            {f"keyframes.{i}.color_u8": k.color_u8, f"keyframes.{i}.depth": k.depth, f"keyframes.{i}.c2w": k.c2w}
        )
    tensors["poses"] = tracking.poses
    tensors["generator_state"] = mapping.generator_state
    if tracking.last_prior is not None:
        tensors["last_prior"] = tracking.last_prior
    if tracking.tracked_poses is not None:
        tensors["tracked_poses"] = tracking.tracked_poses
    if mapping.intrinsics is not None:
        tensors["intrinsics"] = mapping.intrinsics
    if mapping.loops is not None:
        tensors.update(_loop_tensors(mapping.loops))
    header = {
        "format": FORMAT,
        "version": VERSION,
        "run": run.to_json(),
        "frames_done": checkpoint.frames_done,
        "frames_mapped": mapping.frames_seen,
        "keyframe_indices": [k.index for k in mapping.keyframes],
        "keyframe_positions": [k.position for k in mapping.keyframes],
        "scene_radius": mapping.scene_radius,
        "loss_history": tracking.loss_history,
        "lost_frames": tracking.lost_frames,
        "relocalised_frames": tracking.relocalised_frames,
        "rng_state": _json_rng_state(mapping.rng_state),
    }
    if mapping.loops is not None:
        header["loops"] = _loop_header(mapping.loops)
    return save({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, {"gsplatam": json.dumps(header)})


def read_checkpoint(path: Path) -> tuple[Checkpoint, RunDescription]:
    """-> (the checkpoint, the run it was written by). Raises DataError naming
    the file for anything that is not a complete checkpoint of this format."""
    if path.is_file() and not os.access(path, os.R_OK):  # safetensors reads it as missing
        raise DataError(f"cannot read {path}: permission denied")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {key: f.get_tensor(key) for key in f.keys()}
    except FileNotFoundError:
        raise DataError(f"no checkpoint at {path}") from None
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise DataError(f"{path} is not a readable checkpoint (truncated or corrupt?): {exc}") from None
    try:
        header = json.loads(meta["gsplatam"])
        if header.get("format") != FORMAT:
            raise ValueError(f"format {header.get('format')!r}")
        if header.get("version") != VERSION:
            raise ValueError(f"version {header.get('version')!r}, this gsplatam reads version {VERSION}")
        run = RunDescription.from_json(header["run"])
        checkpoint = _checkpoint_of(header, tensors)
        check_tensors(checkpoint, run)
        return checkpoint, run
    except (
        KeyError,
        ValueError,
        TypeError,
        IndexError,
        AttributeError,
    ) as exc:  # AttributeError: JSON of another shape
        raise DataError(f"{path} is not a gsplatam checkpoint ({exc.__class__.__name__}: {exc})") from None


def read_description(path: Path) -> RunDescription | None:
    """The run a checkpoint was written by, from its header alone (no tensor is read); None where
    there is no readable header (`read_checkpoint` then says what is wrong)."""
    try:
        with safe_open(str(path), framework="pt") as f:
            header = json.loads((f.metadata() or {})["gsplatam"])
        return RunDescription.from_json(header["run"])
    except (SafetensorError, OSError, ValueError, RuntimeError, KeyError, TypeError, AttributeError):
        return None


def _checkpoint_of(header: dict[str, Any], tensors: dict[str, torch.Tensor]) -> Checkpoint:
    indices = header["keyframe_indices"]
    positions = header.get("keyframe_positions", [-1] * len(indices))  # absent: written before they were kept
    keyframes = [
        Keyframe(
            index,
            tensors[f"keyframes.{i}.color_u8"],
            tensors[f"keyframes.{i}.depth"],
            tensors[f"keyframes.{i}.c2w"],
            int(position),
        )
        for i, (index, position) in enumerate(zip(indices, positions, strict=True))
    ]
    tracking = FrontendState(
        poses=tensors["poses"],
        loss_history=[float(v) for v in header["loss_history"]],
        last_prior=tensors.get("last_prior"),
        lost_frames=[int(v) for v in header.get("lost_frames", [])],  # absent: written before they were kept
        relocalised_frames=[int(v) for v in header.get("relocalised_frames", [])],
        tracked_poses=tensors.get("tracked_poses"),  # absent: written before they were kept apart
    )
    if tracking.frames_done != header["frames_done"]:
        raise ValueError(f"{tracking.frames_done} poses for {header['frames_done']} frames")
    mapping = BackendState(
        gaussians=Gaussians(**{n: tensors[f"gaussians.{n}"] for n in PARAMETER_NAMES}),
        keyframes=keyframes,
        scene_radius=float(header["scene_radius"]),
        rng_state=_rng_state_of(header["rng_state"]),
        generator_state=tensors["generator_state"],
        frames_seen=int(header.get("frames_mapped", header["frames_done"])),  # absent: mapping saw every frame
        loops=_loop_state_of(header["loops"], tensors) if "loops" in header else None,
        intrinsics=tensors.get("intrinsics"),  # absent: written before it was kept
    )
    if not 0 <= mapping.frames_seen <= tracking.frames_done:
        raise ValueError(f"{mapping.frames_seen} frames mapped of {tracking.frames_done}")
    return Checkpoint(tracking, mapping)


def _loop_tensors(loops: LoopState) -> dict[str, torch.Tensor]:
    tensors = {
        "loops.creator": loops.creator,
        "loops.node_c2w": loops.node_c2w,
        "loops.odometry_information": loops.odometry_information,
    }
    if loops.loops:
        tensors["loops.edges.relative"] = torch.stack([edge.relative for edge in loops.loops])
        tensors["loops.edges.information"] = torch.stack([edge.information for edge in loops.loops])
    return tensors


def _loop_header(loops: LoopState) -> dict[str, Any]:
    return {
        "node_positions": loops.node_positions,
        "edges": [[edge.first, edge.second] for edge in loops.loops],
        "tally": asdict(loops.tally),
        "closed": [asdict(loop) for loop in loops.closed],
    }


def _loop_state_of(header: dict[str, Any], tensors: dict[str, torch.Tensor]) -> LoopState:
    pairs = header["edges"]
    relative = tensors.get("loops.edges.relative", torch.zeros(0, 4, 4, dtype=torch.float64))
    information = tensors.get("loops.edges.information", torch.zeros(0, 6, 6, dtype=torch.float64))
    if len(relative) != len(pairs) or len(information) != len(pairs):
        raise ValueError(
            f"{len(pairs)} loop edges with {len(relative)} relative poses, {len(information)} informations"
        )
    edges = [Edge(int(a), int(b), relative[i], information[i], loop=True) for i, (a, b) in enumerate(pairs)]
    closed = [
        ClosedLoop(
            int(c["frame"]), tuple(int(f) for f in c["matched"]), MotionSize(**c["correction"]),
            float(c["detect_s"]), float(c["correct_s"]), float(c["published_s"]),
        )
        for c in header["closed"]
    ]  # fmt: skip
    return LoopState(
        creator=tensors["loops.creator"],
        node_c2w=tensors["loops.node_c2w"],
        node_positions=[int(p) for p in header["node_positions"]],
        odometry_information=tensors["loops.odometry_information"],
        loops=edges,
        tally=_tally_of(header["tally"]),
        closed=closed,
    )


def _tally_of(table: dict[str, Any]) -> LoopTally:
    """Loop closure's counts from the header (ValueError for a count it does not know, or one
    negative or not finite; counts missing, from an older version, are 0)."""
    if not isinstance(table, dict):
        raise ValueError(f"loops.tally is a {type(table).__name__}, not an object of counts")
    kinds = {item.name: type(getattr(LoopTally(), item.name)) for item in fields(LoopTally)}
    if unknown := sorted(set(table) - set(kinds)):
        raise ValueError(f"loops.tally holds {unknown[0]!r}, not a count loop closure keeps")
    counts = {name: kinds[name](value) for name, value in table.items()}
    if bad := [name for name, value in counts.items() if not (math.isfinite(value) and value >= 0)]:
        raise ValueError(f"loops.tally's {bad[0]} is {counts[bad[0]]}, not a count")
    return LoopTally(**counts)


def check_tensors(checkpoint: Checkpoint, run: RunDescription) -> None:
    """ValueError naming the first tensor of `checkpoint` whose dtype, shape (against the other
    tensors and `run`'s frame size and Gaussian kind) or values (NaN, infinite) are not what a
    run writes: a tampered or damaged checkpoint is refused before anything uses it."""
    gaussians, n = checkpoint.gaussians, len(checkpoint.gaussians)
    axes = _scale_axes(run, gaussians.log_scales)
    shapes = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, axes), "opacity_logits": (n,), "colors": (n, 3)}
    for name in PARAMETER_NAMES:
        _check(f"gaussians.{name}", getattr(gaussians, name), shapes[name])
    _check("poses", checkpoint.poses, (checkpoint.frames_done, 4, 4))
    if checkpoint.tracking.last_prior is not None:
        _check("last_prior", checkpoint.tracking.last_prior, (4, 4))
    state = checkpoint.mapping.generator_state
    _check("generator_state", state, (state.numel(),), torch.uint8)
    size = _keyframe_size(checkpoint, run)
    for i, k in enumerate(checkpoint.keyframes):
        _check(f"keyframes.{i}.color_u8", k.color_u8, (*size, 3), torch.uint8)
        _check(f"keyframes.{i}.depth", k.depth, size)
        _check(f"keyframes.{i}.c2w", k.c2w, (4, 4))
    if checkpoint.mapping.intrinsics is not None:
        _check("intrinsics", checkpoint.mapping.intrinsics, (3, 3))
    if checkpoint.tracking.tracked_poses is not None:
        _check("tracked_poses", checkpoint.tracking.tracked_poses, (checkpoint.frames_done, 4, 4))
    if (loops := checkpoint.mapping.loops) is not None:
        _check_loops(loops, n, checkpoint.frames_done)


def _check_loops(loops: LoopState, gaussians: int, frames: int) -> None:
    """ValueError naming the first of loop closure's tensors or node positions (among the run's
    `frames` poses, in the order the keyframes were kept) that is not what a run writes."""
    nodes = len(loops.node_positions)
    positions = loops.node_positions
    if any(not 0 <= p < frames for p in positions) or positions != sorted(set(positions)):
        wrong = next((p for p in positions if not 0 <= p < frames), positions)
        raise ValueError(
            f"loops.node_positions names frame position(s) {wrong}: not keyframes of {frames} frames in order"
        )
    _check("loops.creator", loops.creator, (gaussians,), torch.int64)
    if gaussians and not bool(((loops.creator >= -1) & (loops.creator < nodes)).all()):
        raise ValueError(f"loops.creator names a node outside -1..{nodes - 1}")
    _check("loops.node_c2w", loops.node_c2w, (nodes, 4, 4))
    _check("loops.odometry_information", loops.odometry_information, (nodes, 6, 6))
    for i, edge in enumerate(loops.loops):
        if not (0 <= edge.first < nodes and 0 <= edge.second < nodes):
            raise ValueError(f"loop edge {i} joins nodes {edge.first} and {edge.second} of {nodes}")
        _check(f"loops.edges.relative[{i}]", edge.relative, (4, 4))
        _check(f"loops.edges.information[{i}]", edge.information, (6, 6))


def _scale_axes(run: RunDescription, log_scales: torch.Tensor) -> int:
    """1 (isotropic) or 3 scale axes per Gaussian: as the run records, else as stored."""
    if run.isotropic is not None:
        return 1 if run.isotropic else 3
    stored = log_scales.shape[-1] if log_scales.dim() == 2 else 0
    return stored if stored in (1, 3) else 3


def _keyframe_size(checkpoint: Checkpoint, run: RunDescription) -> tuple[int, ...]:
    """(height, width) of every keyframe: the run's frame size, else the first keyframe's."""
    if run.size is not None:
        return run.size[1], run.size[0]
    return tuple(checkpoint.keyframes[0].depth.shape[:2]) if checkpoint.keyframes else ()


def _check(name: str, tensor: torch.Tensor, shape: tuple[int, ...], dtype: torch.dtype | None = None) -> None:
    """ValueError unless `tensor` has `shape` and `dtype` (None: any floating dtype, finite values)."""
    if dtype is not None and tensor.dtype != dtype:
        raise ValueError(f"{name} is {tensor.dtype}, not {dtype}")
    if dtype is None and not tensor.is_floating_point():
        raise ValueError(f"{name} is {tensor.dtype}, not a floating-point tensor")
    if tuple(tensor.shape) != shape:
        raise ValueError(f"{name} has shape {tuple(tensor.shape)}, not {shape}")
    if dtype is None and not bool(torch.isfinite(tensor).all()):
        raise ValueError(f"{name} holds NaN or infinite values")


def _json_rng_state(state: tuple[Any, ...]) -> list[Any]:
    """random.Random.getstate() (version, 625 ints, gauss_next) as JSON values."""
    version, internal, gauss_next = state
    return [version, list(internal), gauss_next]


def _rng_state_of(value: list[Any]) -> tuple[Any, ...]:
    version, internal, gauss_next = value
    if not (isinstance(version, int) and all(isinstance(v, int) for v in internal)):
        raise ValueError("malformed random state")
    return (version, tuple(internal), gauss_next)
