"""Live sources named on the command line: `record3d:URL` and `nerfcapture:[DOMAIN]`."""

from __future__ import annotations

import re

from pipeline.config import Config
from pipeline.devices import live_max_width, resolve_device
from pipeline.errors import UserError
from pipeline.source import Source


def live_source(spec: str, config: Config) -> Source:
    """`record3d:URL` or `nerfcapture:` (DDS domain `live.dds_domain`), `nerfcapture:DOMAIN` -> the live source."""
    if spec.startswith("nerfcapture:"):
        from pipeline.sources.live.nerfcapture import NeRFCaptureSource

        return NeRFCaptureSource(config.live.device_pose, nerfcapture_domain(spec, config))
    from pipeline.sources.live.record3d import Record3DSource

    url = spec.removeprefix("record3d:")
    if not url:
        raise UserError("record3d: needs the phone's address, e.g. record3d:http://192.168.1.20")
    size = (config.live.width, config.live.height) if config.live.width else None
    return Record3DSource(url, config.live, size, live_max_width(resolve_device(config.run.device)))


def nerfcapture_domain(spec: str, config: Config) -> int:
    """The DDS domain of `nerfcapture:[DOMAIN]` (none given: `live.dds_domain`)."""
    domain = spec.removeprefix("nerfcapture:")
    if not domain:
        return config.live.dds_domain
    if not domain.isdigit() or not 0 <= int(domain) <= 232:
        raise UserError(f"bad DDS domain in '{spec}': a whole number 0-232, e.g. nerfcapture:1")
    return int(domain)


def source_label(spec: str) -> str:
    """A short name for a source, fit for a folder: record3d-192.168.1.20, nerfcapture, nerfcapture-d3."""
    if spec.startswith("nerfcapture:"):
        domain = spec.removeprefix("nerfcapture:")
        return f"nerfcapture-d{domain}" if domain else "nerfcapture"
    address = re.sub(r"^[a-z]+://", "", spec.removeprefix("record3d:")).rstrip("/")
    return "record3d-" + re.sub(r"[^A-Za-z0-9.]+", "-", address)
