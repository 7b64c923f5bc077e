"""The checkpoint format: typed, pickle-free, validated on reading."""

from __future__ import annotations

import pathlib
import pickle
from pathlib import Path

import pytest
import torch
from conftest import checkpoint_with_loops, make_checkpoint, tamper_checkpoint

from pipeline.app.cli import main
from pipeline.config import load_config, to_toml, with_value
from pipeline.errors import DataError
from pipeline.io.outputs.checkpoint import read_checkpoint, write_checkpoint
from pipeline.io.outputs.run_description import RunDescription
from pipeline.render.types import Gaussians
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.state import Checkpoint


def _checkpoint(frames: int = 3, prior: bool = True) -> Checkpoint:
    g = torch.Generator().manual_seed(1)
    n = 10
    gaussians = Gaussians(torch.randn(n, 3), torch.randn(n, 4), torch.randn(n, 1), torch.randn(n), torch.rand(n, 3))
    keyframes = [
        Keyframe(i, torch.randint(0, 255, (4, 5, 3), dtype=torch.uint8), torch.rand(4, 5), torch.eye(4)) for i in (0, 2)
    ]
    import random

    return make_checkpoint(
        gaussians,
        keyframes,
        torch.eye(4).repeat(frames, 1, 1),
        scene_radius=1.25,
        loss_history=[0.1, 0.2],
        last_prior=torch.eye(4) * 2 if prior else None,
        rng_state=random.Random(5).getstate(),
        generator=g,
    )


@pytest.mark.parametrize("prior", [True, False])
def test_a_checkpoint_round_trips_every_field(tmp_path: Path, prior: bool) -> None:
    saved = _checkpoint(prior=prior)
    write_checkpoint(tmp_path / "c.safetensors", saved, RunDescription("room", size=(5, 4)))
    loaded, run = read_checkpoint(tmp_path / "c.safetensors")
    assert run == RunDescription("room", size=(5, 4))
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        assert torch.equal(getattr(loaded.gaussians, name), getattr(saved.gaussians, name))
    assert [k.index for k in loaded.keyframes] == [0, 2]
    assert all(
        torch.equal(a.color_u8, b.color_u8) and torch.equal(a.depth, b.depth)
        for a, b in zip(loaded.keyframes, saved.keyframes)
    )
    assert torch.equal(loaded.poses, saved.poses) and loaded.frames_done == 3
    assert loaded.mapping.scene_radius == 1.25 and loaded.tracking.loss_history == [0.1, 0.2]
    assert (loaded.tracking.last_prior is None) == (not prior)
    if prior:
        assert torch.equal(loaded.tracking.last_prior, saved.tracking.last_prior)
    assert loaded.mapping.rng_state == saved.mapping.rng_state
    assert torch.equal(loaded.mapping.generator_state, saved.mapping.generator_state)
    assert loaded.mapping.frames_seen == 3
    assert list(tmp_path.iterdir()) == [tmp_path / "c.safetensors"]  # no temporary file left


@pytest.mark.parametrize("content", [b"", b"\x00" * 7, b"random bytes that are no tensor file", "truncated"])
def test_a_broken_checkpoint_is_a_data_error_naming_the_file(tmp_path: Path, content: bytes | str) -> None:
    path = tmp_path / "checkpoint.safetensors"
    if content == "truncated":
        write_checkpoint(path, _checkpoint(), RunDescription("room"))
        path.write_bytes(path.read_bytes()[:-40])
    else:
        path.write_bytes(content)
    with pytest.raises(DataError, match="checkpoint.safetensors"):
        read_checkpoint(path)


class _RunsCode:
    """Unpickling this writes a file: what a crafted checkpoint would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):  # type: ignore[no-untyped-def]
        return (pathlib.Path.write_text, (self.marker, "code ran"))


def _run_folder(tmp_path: Path, dataset: Path) -> Path:
    folder = tmp_path / "run"
    folder.mkdir()
    config = with_value(load_config("tiny"), "dataset.path", str(dataset))
    (folder / "config.toml").write_text(to_toml(config))
    return folder


@pytest.mark.parametrize("name", ["checkpoint.safetensors", "checkpoint.pt"])
def test_resume_never_runs_code_from_a_crafted_pickle(replica_seq: Path, tmp_path: Path, capsys, name: str) -> None:
    folder = _run_folder(tmp_path, replica_seq)
    marker = tmp_path / "pwned"
    (folder / name).write_bytes(pickle.dumps({"slam": _RunsCode(marker)}))
    code = main(["run", "--resume", str(folder), "--device", "cpu", "--quiet", "--output", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and not marker.exists()
    assert err[-1].startswith("gsplatam: error: ") and name in err[-1] and "Traceback" not in "\n".join(err)
    if name == "checkpoint.pt":
        assert "never loaded" in err[-1]


@pytest.mark.parametrize(
    "name, change, message",
    [
        ("gaussians.means", "int32", "gaussians.means is torch.int32, not a floating-point tensor"),
        ("gaussians.means", "one axis fewer", r"gaussians.means has shape \(10, 2\), not \(10, 3\)"),
        ("gaussians.means", "nan", "gaussians.means holds NaN or infinite values"),
        ("gaussians.colors", "one row fewer", r"gaussians.colors has shape \(9, 3\), not \(10, 3\)"),
        ("gaussians.log_scales", "nan", "gaussians.log_scales holds NaN"),
        ("poses", "nan", "poses holds NaN"),
        ("keyframes.1.depth", "one axis fewer", r"keyframes.1.depth has shape \(4, 4\), not \(4, 5\)"),
        ("keyframes.0.color_u8", "int32", "keyframes.0.color_u8 is torch.int32, not torch.uint8"),
        ("last_prior", "nan", "last_prior holds NaN"),
    ],
)
def test_every_tensor_is_checked_for_dtype_shape_and_finite_values(
    tmp_path: Path, name: str, change: str, message: str
) -> None:
    path = tmp_path / "c.safetensors"
    write_checkpoint(path, _checkpoint(), RunDescription("room", size=(5, 4), isotropic=True))
    tamper_checkpoint(path, name, change)
    with pytest.raises(DataError, match=rf"{path} is not a gsplatam checkpoint \(ValueError: {message}"):
        read_checkpoint(path)


def test_anisotropic_scales_are_refused_for_an_isotropic_run(tmp_path: Path) -> None:
    saved = _checkpoint()
    saved.gaussians.log_scales = saved.gaussians.log_scales.repeat(1, 3)
    write_checkpoint(tmp_path / "c.safetensors", saved, RunDescription("room", isotropic=True))
    with pytest.raises(DataError, match=r"gaussians.log_scales has shape \(10, 3\), not \(10, 1\)"):
        read_checkpoint(tmp_path / "c.safetensors")
    write_checkpoint(tmp_path / "c.safetensors", saved, RunDescription("room", isotropic=False))
    assert read_checkpoint(tmp_path / "c.safetensors")[0].gaussians.log_scales.shape == (10, 3)


def test_loop_closures_state_and_the_poses_as_tracked_round_trip(tmp_path: Path) -> None:
    checkpoint = checkpoint_with_loops(9)
    write_checkpoint(tmp_path / "c.safetensors", checkpoint, RunDescription("room"))
    read, _ = read_checkpoint(tmp_path / "c.safetensors")
    loops, saved = read.mapping.loops, checkpoint.mapping.loops
    assert loops is not None and saved is not None
    assert torch.equal(loops.creator, saved.creator) and torch.equal(loops.node_c2w, saved.node_c2w)
    assert loops.node_positions == saved.node_positions and loops.tally == saved.tally and loops.closed == saved.closed
    assert [(e.first, e.second, e.loop) for e in loops.loops] == [(0, 2, True)]
    assert torch.equal(loops.loops[0].information, saved.loops[0].information)
    assert read.tracking.tracked_poses is not None and torch.equal(read.tracking.tracked_poses, 2 * read.poses)
    assert read.mapping.intrinsics is not None and torch.equal(read.mapping.intrinsics, torch.eye(3))


@pytest.mark.parametrize("change", ["int32", "one row fewer"])
def test_a_tampered_creator_is_refused(tmp_path: Path, change: str) -> None:
    path = tmp_path / "c.safetensors"
    write_checkpoint(path, checkpoint_with_loops(9), RunDescription("room"))
    tamper_checkpoint(path, "loops.creator", change)
    with pytest.raises(DataError, match="loops.creator"):
        read_checkpoint(path)
