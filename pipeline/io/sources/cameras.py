"""Live cameras by the scheme that names them: `record3d:URL`, `nerfcapture:[DOMAIN]`,
`realsense:[SERIAL]`; anything
else a command is given is a dataset folder. A new camera is its module, with a function that
opens it, and one entry in CAMERAS: commands never learn a camera's prefix."""

from __future__ import annotations

import importlib
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

from pipeline.errors import UserError

if TYPE_CHECKING:  # the command line reads this registry: it imports no torch, and no camera's extra
    import torch

    from pipeline.config import LiveConfig
    from pipeline.source import Source

# (the address after "scheme:", the live settings, the compute device) -> the source
SourceOpener = Callable[[str, "LiveConfig", "torch.device"], "Source"]


def _any_address(address: str) -> None:
    """Every address is one (the camera checks it as it opens)."""


def _slug(address: str) -> str:
    """A URL or a name fit for a folder: its scheme gone, other characters than letters, digits and dots as '-'."""
    return re.sub(r"[^A-Za-z0-9.]+", "-", re.sub(r"^[a-z]+://", "", address).rstrip("/"))


@dataclass(frozen=True)
class Camera:
    """One kind of live camera: its scheme, where the function that opens it is (imported only
    then: its extra may be missing), how `serve --<scheme>` takes its address, how the address
    is checked before anything starts (UserError) and named in a run folder's name."""

    scheme: str
    opener: str  # "module:function", a SourceOpener
    metavar: str
    help: str  # of serve's --<scheme> option
    address_optional: bool = False  # serve --<scheme> without an address: the camera's default
    check: Callable[[str], None] = _any_address
    label: Callable[[str], str] = _slug

    def open(self, address: str, live: LiveConfig, device: torch.device) -> Source:
        self.check(address)
        module, _, name = self.opener.partition(":")
        opener = cast(SourceOpener, getattr(importlib.import_module(module), name))
        return opener(address, live, device)


def _phone_address(address: str) -> None:
    if not address:
        raise UserError("record3d: needs the phone's address, e.g. record3d:http://192.168.1.20")


def _dds_domain(address: str) -> None:
    if address and not (address.isdigit() and 0 <= int(address) <= 232):
        raise UserError(f"bad DDS domain in 'nerfcapture:{address}': a whole number 0-232, e.g. nerfcapture:1")


def _domain_label(address: str) -> str:
    return f"d{address}" if address else ""


def _serial_number(address: str) -> None:
    if address and not address.isalnum():
        raise UserError(f"bad serial number in 'realsense:{address}': letters and digits, e.g. realsense:123456789012")


CAMERAS = {
    camera.scheme: camera
    for camera in (
        Camera(
            "record3d", "pipeline.io.sources.live.record3d:open_record3d", "URL",
            "Record3D app's Wi-Fi stream, e.g. http://192.168.1.20 (repeatable with --ray)",
            check=_phone_address,
        ),
        Camera(
            "nerfcapture", "pipeline.io.sources.live.nerfcapture:open_nerfcapture", "DOMAIN",
            "NeRFCapture app over DDS (topic Frames, domain live.dds_domain: 0, or DOMAIN; repeatable with --ray, "
            "a domain each); its pose per --set live.device_pose=...",
            address_optional=True, check=_dds_domain, label=_domain_label,
        ),
        Camera(
            "realsense", "pipeline.io.sources.live.realsense:open_realsense", "SERIAL",
            "Intel RealSense camera over USB (pyrealsense2), the one of serial number SERIAL or the first connected; "
            "depth aligned to colour by the SDK",
            address_optional=True, check=_serial_number,
        ),
    )
}  # fmt: skip


def camera_of(spec: str) -> tuple[Camera, str] | None:
    """(the camera, its address) that `scheme:address` names; None for anything else (a dataset folder)."""
    scheme, colon, address = spec.partition(":")
    camera = CAMERAS.get(scheme) if colon else None
    return None if camera is None else (camera, address)


def live_camera(spec: str) -> tuple[Camera, str]:
    """As `camera_of`, for a spec that must name a camera (UserError otherwise)."""
    named = camera_of(spec)
    if named is None:
        schemes = ", ".join(f"{scheme}:" for scheme in CAMERAS)
        raise UserError(f"'{spec}' names no live camera (the schemes: {schemes})")
    return named


def open_source(spec: str, live: LiveConfig, device: torch.device) -> Source:
    """The live source `spec` names."""
    camera, address = live_camera(spec)
    return camera.open(address, live, device)


def source_label(spec: str) -> str:
    """A short name for a live source, fit for a folder: record3d-192.168.1.20, nerfcapture, nerfcapture-d3."""
    camera, address = live_camera(spec)
    label = camera.label(address)
    return f"{camera.scheme}-{label}" if label else camera.scheme
