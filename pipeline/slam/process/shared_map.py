"""Map versions shared between the tracking process and the mapping process, without a copy per
version.

The tracking side allocates the buffers (so that they outlive a mapping process that dies) and
shares them once: on CUDA through CUDA IPC, on the CPU through shared memory. A generation is
three slots of fixed capacity, each able to hold a whole map version (the Gaussians and the
keyframes' poses). Three, not two: the writer never writes the newest slot (the reader may be
about to take it) nor the slot the reader holds, and with three one of them is always free, so
neither side ever waits for the other. A small control block in shared host memory, changed
under one lock, says which slot holds the newest complete version, its number and sizes, and
which slot the reader holds. A version is complete when the writer has synchronised its stream
after the copies: only then is it made the newest.

A map that outgrows its generation's capacity asks the tracking side (by message) for a new,
larger generation; the old one is dropped once the reader has moved on from it.

On the CPU the slots (and the frame ring) live in POSIX shared memory, /dev/shm on Linux, which a
container may keep small (Docker's default is 64 MiB; 64 KiB to 8 MiB are seen). The reader checks
at start that the first generation fits, and an allocation that fails later (a map grown past
what is left) is the same one line (`SharedMemoryShort`): how much is free, how much is needed,
and what to do.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from pipeline.errors import UserError
from pipeline.render.types import Gaussians
from pipeline.slam.gaussian_map import PARAMETER_NAMES
from pipeline.slam.keyframes import KeyframePose
from pipeline.slam.map_version import MapVersion

SLOTS = 3
GROWTH = 1.5  # a new generation holds this many times what outgrew the last one
FIRST_CAPACITY = 1 << 16  # Gaussians in the first generation (grown as the map grows)
FIRST_KEYFRAMES = 64

# The control block's int64 fields; per-slot fields follow at SLOT_FIELDS + slot.
NEWEST_GENERATION, NEWEST_SLOT, READING_GENERATION, READING_SLOT = 0, 1, 2, 3
VERSION, COUNT, KEYFRAMES = 4, 4 + SLOTS, 4 + 2 * SLOTS
CONTROL_FIELDS = 4 + 3 * SLOTS
SHARED_MEMORY = Path("/dev/shm")  # where Linux keeps POSIX shared memory (torch's share_memory_ on the CPU)
MIB = 1 << 20


class SharedMemoryShort(UserError):
    """The shared memory cannot hold what the process schedule shares."""


def shared_memory_free() -> int | None:
    """Bytes free in SHARED_MEMORY (None where there is no such file system to ask)."""
    try:
        info = os.statvfs(SHARED_MEMORY)
    except OSError:
        return None
    return info.f_bavail * info.f_frsize


def shared_memory_advice(needed: int | None = None, when: str = "more now") -> str:
    """What to do about a shared memory too small, with what is free and (if known) how much is
    `needed` (bytes) `when`."""
    free = shared_memory_free()
    has = "" if free is None else f", which has {free / MIB:.1f} MiB free"
    wants = "" if needed is None else f"; it needs {needed / MIB:.1f} MiB {when}, and more as the map grows"
    return (
        f"slam.schedule=process shares its map and frames through {SHARED_MEMORY}{has}{wants}: enlarge it "
        f"(docker run --shm-size=1g; or mount -o remount,size=1g {SHARED_MEMORY}) or run with "
        "--set slam.schedule=sequential, which needs no shared memory"
    )


def share(tensor: torch.Tensor) -> torch.Tensor:
    """`tensor` in shared memory on the CPU (CUDA memory is shared by IPC when sent);
    SharedMemoryShort where the shared memory is full."""
    if tensor.is_cuda:
        return tensor
    try:
        return tensor.share_memory_()
    except RuntimeError as exc:
        if "shared memory" not in str(exc):
            raise
        raise SharedMemoryShort(shared_memory_advice(tensor.nbytes)) from None


def check_shared_memory(needed: int) -> None:
    """SharedMemoryShort, before anything is allocated, where `needed` bytes do not fit."""
    free = shared_memory_free()
    if free is not None and free < needed:
        raise SharedMemoryShort(shared_memory_advice(needed, "to start"))


@dataclass(frozen=True)
class MapSlot:
    """One slot: room for a whole map version."""

    gaussians: Gaussians  # [capacity, ...] per parameter, on the compute device
    keyframe_c2w: torch.Tensor  # [keyframe_capacity, 4, 4] on the compute device
    keyframe_index: torch.Tensor  # [keyframe_capacity, 2] int64 (index, position), in host memory


@dataclass(frozen=True)
class MapGeneration:
    number: int
    capacity: int  # Gaussians a slot holds
    keyframe_capacity: int
    slots: tuple[MapSlot, ...]

    @staticmethod
    def allocate(
        number: int, capacity: int, keyframe_capacity: int, scale_axes: int, device: torch.device
    ) -> MapGeneration:
        """Three empty slots; `scale_axes`: 1 for isotropic Gaussians, 3 for anisotropic."""
        widths = {"means": (3,), "quats": (4,), "log_scales": (scale_axes,), "opacity_logits": (), "colors": (3,)}

        def slot() -> MapSlot:
            tensors = {n: share(torch.zeros(capacity, *widths[n], device=device)) for n in PARAMETER_NAMES}
            return MapSlot(
                Gaussians(**tensors),
                share(torch.zeros(keyframe_capacity, 4, 4, device=device)),
                share(torch.zeros(keyframe_capacity, 2, dtype=torch.int64)),
            )

        return MapGeneration(number, capacity, keyframe_capacity, tuple(slot() for _ in range(SLOTS)))

    def fits(self, gaussians: int, keyframes: int) -> bool:
        return gaussians <= self.capacity and keyframes <= self.keyframe_capacity

    @staticmethod
    def host_bytes(capacity: int, keyframe_capacity: int, scale_axes: int, device: torch.device) -> int:
        """The shared host memory a generation takes (on CUDA only the keyframes' indices)."""
        per_slot = 8 * 2 * keyframe_capacity
        if device.type != "cuda":
            per_slot += 4 * (capacity * (3 + 4 + scale_axes + 1 + 3) + keyframe_capacity * 16)
        return SLOTS * per_slot


@dataclass(frozen=True)
class MapControl:
    """The control block and its lock, shared by both processes (passed at spawn)."""

    fields: torch.Tensor  # [CONTROL_FIELDS] int64 in shared memory
    lock: Any  # a multiprocessing lock of the spawn context

    @staticmethod
    def create(context: Any) -> MapControl:
        fields = share(torch.full((CONTROL_FIELDS,), -1, dtype=torch.int64))
        return MapControl(fields, context.Lock())


class MapWriter:
    """The mapping process's end: publishes versions into the free slot of the newest
    generation it was given. `grow(gaussians, keyframes)` asks the tracking side for a larger
    generation and returns it (a blocking round trip)."""

    def __init__(
        self, control: MapControl, generation: MapGeneration, grow: Callable[[int, int], MapGeneration]
    ) -> None:
        self.control = control
        self.generation = generation
        self.grow = grow
        self.number = 0  # the last version published

    def publish(self, gaussians: Gaussians, keyframes: Sequence[KeyframePose]) -> int:
        """Copy a map version into a free slot, wait for the copies, make it the newest. -> its number."""
        count, kept = len(gaussians), len(keyframes)
        if not self.generation.fits(count, kept):
            self.generation = self.grow(int(count * GROWTH) + 1, int(kept * GROWTH) + 1)
        index = self._free_slot()
        slot = self.generation.slots[index]
        for name in PARAMETER_NAMES:
            getattr(slot.gaussians, name)[:count].copy_(getattr(gaussians, name))
        if kept:
            slot.keyframe_c2w[:kept].copy_(torch.stack([k.c2w for k in keyframes]))
            slot.keyframe_index[:kept] = torch.tensor([(k.index, k.position) for k in keyframes])
        if slot.keyframe_c2w.is_cuda:
            torch.cuda.current_stream().synchronize()  # complete before the reader may take it
        self.number += 1
        fields = self.control.fields
        with self.control.lock:
            fields[VERSION + index], fields[COUNT + index], fields[KEYFRAMES + index] = self.number, count, kept
            fields[NEWEST_GENERATION], fields[NEWEST_SLOT] = self.generation.number, index
        return self.number

    def _free_slot(self) -> int:
        """A slot of this generation that is neither the newest nor held by the reader."""
        fields, generation = self.control.fields, self.generation.number
        with self.control.lock:
            taken = {
                int(fields[slot])
                for owner, slot in ((NEWEST_GENERATION, NEWEST_SLOT), (READING_GENERATION, READING_SLOT))
                if int(fields[owner]) == generation
            }
        return min(set(range(SLOTS)) - taken)


class MapReader:
    """The tracking process's end: allocates the generations, holds one version at a time.

    `hold()` takes the newest version (and lets go of the one held before), so the version
    stays intact while tracking renders it and observers look at it, until the next `hold()`
    or `release()`."""

    def __init__(self, control: MapControl, scale_axes: int, device: torch.device) -> None:
        self.control = control
        self.scale_axes = scale_axes
        self.device = device
        self._generations: dict[int, MapGeneration] = {}
        self._allocating = threading.Lock()  # the listener thread grows while tracking reads
        self.held: MapVersion | None = None
        check_shared_memory(MapGeneration.host_bytes(FIRST_CAPACITY, FIRST_KEYFRAMES, scale_axes, device))
        self.first = self.grow(FIRST_CAPACITY, FIRST_KEYFRAMES)

    def grow(self, capacity: int, keyframe_capacity: int) -> MapGeneration:
        """A new, larger generation (the mapping process asked for it)."""
        with self._allocating:
            number = max(self._generations, default=-1) + 1
            generation = MapGeneration.allocate(number, capacity, keyframe_capacity, self.scale_axes, self.device)
            self._generations[number] = generation
        return generation

    def hold(self, wait_s: float | None = None) -> MapVersion | None:
        """The newest complete version, held until the next call (None before the first). With
        `wait_s`, the control block's lock is waited for that long at most (a writer killed
        while holding it never lets go): the version held before is kept then."""
        fields, lock = self.control.fields, self.control.lock
        if not lock.acquire(timeout=wait_s):
            return self.held
        try:
            generation, index = int(fields[NEWEST_GENERATION]), int(fields[NEWEST_SLOT])
            if generation < 0:
                return None
            fields[READING_GENERATION], fields[READING_SLOT] = generation, index
            number, count, kept = (int(fields[f + index]) for f in (VERSION, COUNT, KEYFRAMES))
        finally:
            lock.release()
        with self._allocating:
            slot = self._generations[generation].slots[index]
            for older in [g for g in self._generations if g < generation]:
                del self._generations[older]  # the writer has moved on, and so has the reader now
        gaussians = Gaussians(*(getattr(slot.gaussians, n)[:count] for n in PARAMETER_NAMES))
        c2w = slot.keyframe_c2w[:kept].clone()  # the slot is written again later; frames keep their anchors' poses
        keyframes = tuple(
            KeyframePose(index, c2w[row], position)
            for row, (index, position) in enumerate(slot.keyframe_index[:kept].tolist())
        )
        self.held = MapVersion(number, gaussians, None, keyframes)
        return self.held

    def release(self) -> None:
        with self.control.lock:
            self.control.fields[READING_GENERATION] = -1
            self.control.fields[READING_SLOT] = -1
        self.held = None
