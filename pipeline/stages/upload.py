"""Host-to-device transfer: pinned staging buffers and a side CUDA stream.

On CUDA each frame is copied into a reusable pinned buffer, then to the GPU with
`non_blocking=True` on a dedicated copy stream; the consumer makes its stream wait on the
copy's CUDA event instead of blocking the host. Without CUDA the upload is a plain wrap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.frame import DeviceFrame, Frame


@dataclass
class UploadedFrame:
    frame: DeviceFrame
    ready: torch.cuda.Event | None  # the copy stream's event; None on the CPU

    def wait(self) -> DeviceFrame:
        """Make the current stream wait for the copy (no host synchronisation)."""
        if self.ready is not None:
            torch.cuda.current_stream().wait_event(self.ready)
        return self.frame


def host_frame_tensors(frame: Frame) -> DeviceFrame:
    """The CPU path: the same conversion as the GPU path, without a copy."""
    return DeviceFrame(
        index=frame.index,
        timestamp=frame.timestamp,
        color=torch.from_numpy(frame.color).float().div_(255.0),
        depth=torch.from_numpy(np.ascontiguousarray(frame.depth, dtype=np.float32)),
        intrinsics=torch.from_numpy(frame.intrinsics).float(),
        c2w_gt=None if frame.c2w_gt is None else torch.from_numpy(frame.c2w_gt).float(),
        c2w_prior=None if frame.c2w_prior is None else torch.from_numpy(frame.c2w_prior).float(),
        received_at=frame.received_at,
        motion=frame.motion,
    )


class PinnedUploader:
    """Copies frames to a CUDA device through a ring of pinned buffers on a side stream.

    A ring slot is reused only after the copy that last read it has finished (its event is
    waited on by the uploading thread, never by the compute stream).
    """

    def __init__(self, device: torch.device, slots: int) -> None:
        self.device = device
        self.stream = torch.cuda.Stream(device)
        self.slots = slots
        self._buffers: list[tuple[torch.Tensor, torch.Tensor] | None] = [None] * slots
        self._events: list[torch.cuda.Event | None] = [None] * slots
        self._next = 0

    def _slot(self, height: int, width: int) -> tuple[int, torch.Tensor, torch.Tensor]:
        k = self._next
        self._next = (k + 1) % self.slots
        if self._events[k] is not None:
            self._events[k].synchronize()  # type: ignore[union-attr]
        buffers = self._buffers[k]
        if buffers is None or buffers[1].shape != (height, width):
            buffers = (
                torch.empty((height, width, 3), dtype=torch.uint8).pin_memory(),
                torch.empty((height, width), dtype=torch.float32).pin_memory(),
            )
            self._buffers[k] = buffers
        return k, buffers[0], buffers[1]

    def __call__(self, frame: Frame) -> UploadedFrame:
        k, color_host, depth_host = self._slot(frame.height, frame.width)
        color_host.numpy()[...] = frame.color
        depth_host.numpy()[...] = frame.depth
        consumer = torch.cuda.current_stream(self.device)
        with torch.cuda.stream(self.stream):
            color = color_host.to(self.device, non_blocking=True).float().div_(255.0)
            depth = depth_host.to(self.device, non_blocking=True)
            intrinsics = torch.from_numpy(frame.intrinsics).float().to(self.device, non_blocking=True)
            c2w_gt, c2w_prior = (
                None if pose is None else torch.from_numpy(pose).float().to(self.device, non_blocking=True)
                for pose in (frame.c2w_gt, frame.c2w_prior)
            )
            event = torch.cuda.Event()
            event.record(self.stream)
        for tensor in (color, depth, intrinsics, c2w_gt, c2w_prior):
            if tensor is not None:
                tensor.record_stream(consumer)  # allocated on the copy stream, used on the compute stream
        self._events[k] = event
        device_frame = DeviceFrame(
            frame.index, frame.timestamp, color, depth, intrinsics, c2w_gt, c2w_prior, frame.received_at, frame.motion
        )
        return UploadedFrame(device_frame, event)


class HostUploader:
    """The no-copy upload for CPU runs."""

    def __call__(self, frame: Frame) -> UploadedFrame:
        return UploadedFrame(host_frame_tensors(frame), None)


def make_uploader(device: torch.device, slots: int) -> PinnedUploader | HostUploader:
    return PinnedUploader(device, slots) if device.type == "cuda" else HostUploader()
