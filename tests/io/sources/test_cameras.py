"""The registry of live cameras: a scheme names a camera, anything else a dataset folder, and a
new camera is one entry (the commands learn its prefix and its serve option from it)."""

from __future__ import annotations

import sys
import types

import pytest
import torch

from pipeline.config import LiveConfig
from pipeline.errors import UserError
from pipeline.io.sources import cameras
from pipeline.io.sources.cameras import Camera, camera_of, open_source, source_label


def test_a_scheme_names_a_camera_and_anything_else_is_a_dataset_folder() -> None:
    named = camera_of("record3d:http://192.168.1.20")
    assert named is not None and named[0].scheme == "record3d" and named[1] == "http://192.168.1.20"
    assert camera_of("nerfcapture:") is not None
    assert camera_of("/data/tum/fr1_xyz") is None and camera_of("c:/data") is None and camera_of("record3d") is None
    with pytest.raises(UserError, match="bad DDS domain in 'nerfcapture:x'"):
        open_source("nerfcapture:x", LiveConfig(), torch.device("cpu"))


def test_a_new_camera_is_one_registry_entry(monkeypatch: pytest.MonkeyPatch) -> None:
    from pipeline.app.cli import build_parser

    opened: list[tuple[str, LiveConfig]] = []
    module = types.ModuleType("kinect_camera")
    module.open_kinect = lambda address, live, device: opened.append((address, live)) or "a source"  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "kinect_camera", module)
    kinect = Camera("kinect", "kinect_camera:open_kinect", "SERIAL", "a Kinect by its serial")
    monkeypatch.setitem(cameras.CAMERAS, "kinect", kinect)
    assert open_source("kinect:A12", LiveConfig(), torch.device("cpu")) == "a source"  # type: ignore[comparison-overlap]
    assert opened == [("A12", LiveConfig())] and source_label("kinect:A12") == "kinect-A12"
    args = build_parser().parse_args(["serve", "--kinect", "A12", "--kinect", "B3"])
    assert args.kinect == ["A12", "B3"]
