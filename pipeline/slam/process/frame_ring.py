"""Tracked frames handed from the tracking process to the mapping process through a ring of
slots allocated once (CUDA IPC or shared memory), so a frame crosses without being pickled.

The tracking side takes a free slot, copies the frame and its pose in, waits for the copies and
sends the slot's number in a message; the mapping side copies the slot out and frees it. A
semaphore counts the free slots: offline, tracking waits for one (a bound on its lead over
mapping); live, it never waits (no free slot: the frame is tracked, not mapped).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from pipeline.frame import DeviceFrame
from pipeline.slam.process.shared_map import share


@dataclass(frozen=True)
class FrameSlot:
    color: torch.Tensor  # [H, W, 3] float32 in [0, 1], on the compute device
    depth: torch.Tensor  # [H, W] metres
    intrinsics: torch.Tensor  # [3, 3]
    c2w: torch.Tensor  # [4, 4] the tracked camera-to-world


@dataclass(frozen=True)
class RingBookkeeping:
    """Which slots are free: made before the mapping process starts and given to it at spawn
    (multiprocessing's semaphores and locks cannot travel in messages)."""

    busy: torch.Tensor  # [slots] int64 in shared memory: 1 while a slot holds a frame not yet copied out
    free: Any  # a multiprocessing semaphore of the spawn context: the number of free slots
    lock: Any  # guards `busy`

    @staticmethod
    def create(count: int, context: Any) -> RingBookkeeping:
        return RingBookkeeping(share(torch.zeros(count, dtype=torch.int64)), context.Semaphore(count), context.Lock())


@dataclass(frozen=True)
class FrameRing:
    """The slots (allocated at the first frame, when its size is known, and sent once) and their
    bookkeeping."""

    slots: tuple[FrameSlot, ...]
    books: RingBookkeeping

    @staticmethod
    def allocate(books: RingBookkeeping, height: int, width: int, device: torch.device) -> FrameRing:
        def slot() -> FrameSlot:
            return FrameSlot(
                share(torch.zeros(height, width, 3, device=device)),
                share(torch.zeros(height, width, device=device)),
                share(torch.zeros(3, 3, device=device)),
                share(torch.zeros(4, 4, device=device)),
            )

        return FrameRing(tuple(slot() for _ in range(int(books.busy.shape[0]))), books)

    def fits(self, frame: DeviceFrame) -> bool:
        return tuple(self.slots[0].depth.shape) == (frame.height, frame.width)

    def put(self, frame: DeviceFrame, c2w: torch.Tensor, timeout_s: float | None) -> int | None:
        """Copy `frame` and its pose into a free slot, waiting at most `timeout_s` for one (None:
        as long as it takes; 0: not at all). -> the slot, or None when none came free."""
        books = self.books
        acquired = books.free.acquire(False) if timeout_s == 0 else books.free.acquire(timeout=timeout_s)
        if not acquired:
            return None
        with books.lock:
            index = int(torch.nonzero(books.busy == 0)[0, 0])
            books.busy[index] = 1
        slot = self.slots[index]
        for target, source in zip(
            (slot.color, slot.depth, slot.intrinsics, slot.c2w), (frame.color, frame.depth, frame.intrinsics, c2w)
        ):
            target.copy_(source)
        if slot.depth.is_cuda:
            torch.cuda.current_stream().synchronize()  # complete before the mapping process reads it
        return index

    def take(self, index: int) -> FrameSlot:
        """The mapping side: a copy of the slot's contents, and the slot freed."""
        slot = self.slots[index]
        copy = FrameSlot(slot.color.clone(), slot.depth.clone(), slot.intrinsics.clone(), slot.c2w.clone())
        if slot.depth.is_cuda:
            torch.cuda.current_stream().synchronize()  # copied out before the slot is reused
        with self.books.lock:
            self.books.busy[index] = 0
        self.books.free.release()
        return copy
