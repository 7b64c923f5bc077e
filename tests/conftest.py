from __future__ import annotations

import os
import random
import socket
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from pipeline.config import DatasetConfig, GaussianConfig, SyntheticConfig, load_config
from pipeline.extras import unavailable_extra
from pipeline.io.outputs.intrinsics import CameraIntrinsics, write_intrinsics
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.render.types import Gaussians
from pipeline.slam.gaussian_map import concatenate, seed_gaussians
from pipeline.slam.keyframes import Keyframe
from pipeline.slam.state import BackendState, Checkpoint, FrontendState

if os.environ.get("PYTEST_XDIST_WORKER"):  # one of two workers on two cores: one thread each,
    os.environ["OMP_NUM_THREADS"] = "1"  # and for the commands a test starts
    torch.set_num_threads(1)
else:
    torch.set_num_threads(2)

ROOT = Path(__file__).resolve().parents[1]  # the checkout
SHARED_TUM = ROOT.parent / "shared" / "data" / "tum_fr1_xyz_37"
SHARED_CABINET = ROOT.parent / "shared" / "data" / "tum_fr3_cabinet_kf57"  # a real loop round a cabinet
SMALL_SYNTH = SyntheticConfig(frames=6, width=64, height=48, seed=3)


@pytest.fixture(scope="session")
def replica_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replica") / "room"
    write_synthetic(path, SMALL_SYNTH, progress=False)
    return path


@pytest.fixture(scope="session")
def tum_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("tum") / "room"
    write_synthetic(path, replace(SMALL_SYNTH, layout="tum"), progress=False)
    return path


@pytest.fixture
def tum_sample() -> Path:
    if not (SHARED_TUM / "rgb.txt").exists():
        pytest.skip(f"the shared TUM sample is absent ({SHARED_TUM})")
    return SHARED_TUM


@pytest.fixture
def cabinet_sample() -> Path:
    if not (SHARED_CABINET / "rgb.txt").exists():
        pytest.skip(f"the shared cabinet loop is absent ({SHARED_CABINET})")
    return SHARED_CABINET


def needs_extra(module: str) -> None:
    """Skip the test, saying why (its pip command, or the system library it lacks), where
    `module` of an extra is not installed or cannot load."""
    if (why := unavailable_extra(module)) is not None:
        pytest.skip(why)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Whole runs and live peers first: a worker handed a long test last keeps the other waiting."""
    items.sort(key=lambda item: (item.get_closest_marker("slow") is None, item.get_closest_marker("live") is None))


DOMAIN_LOCK_PORT = 47000  # + domain id: a TCP port on loopback held while a test uses that DDS domain


@pytest.fixture
def dds_domain() -> Iterator[int]:
    """A DDS domain id that no other test, of this suite or another on the machine, uses now.

    DDS traffic of one domain reaches every process on the machine in that domain, so each test
    takes its own: the domain is held by binding TCP port DOMAIN_LOCK_PORT + id on loopback
    (TCP, so the DDS sockets, which are UDP, never meet it) for the test's duration.
    """
    start = random.randrange(232)
    for k in range(232):
        domain = 1 + (start + k) % 232
        lock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            lock.bind(("127.0.0.1", DOMAIN_LOCK_PORT + domain))
        except OSError:
            lock.close()
            continue
        try:
            yield domain
        finally:
            lock.close()
        return
    raise RuntimeError("every DDS domain id is held by another test")


def make_checkpoint(
    gaussians: Gaussians,
    keyframes: list[Keyframe],
    poses: torch.Tensor,
    scene_radius: float = 1.0,
    loss_history: list[float] | None = None,
    last_prior: torch.Tensor | None = None,
    rng_state: tuple[object, ...] | None = None,
    generator: torch.Generator | None = None,
) -> Checkpoint:
    """A checkpoint of `poses` [F, 4, 4] frames, every one of them mapped."""
    tracking = FrontendState(poses, list(loss_history or []), last_prior)
    rng = rng_state or random.Random(0).getstate()
    state = (generator or torch.Generator()).get_state()
    mapping = BackendState(gaussians, keyframes, scene_radius, rng, state, frames_seen=int(poses.shape[0]))
    return Checkpoint(tracking, mapping)


def tamper_checkpoint(path: Path, name: str, change: str) -> None:
    """Rewrite one tensor of the checkpoint at `path`, keeping its header."""
    with safe_open(str(path), framework="pt") as f:
        meta, tensors = f.metadata(), {key: f.get_tensor(key) for key in f.keys()}
    tensor = tensors[name]
    if change == "int32":
        tensors[name] = tensor.to(torch.int32)
    elif change == "one axis fewer":
        tensors[name] = tensor[..., :-1].contiguous()
    elif change == "nan":
        tensors[name] = torch.full_like(tensor, float("nan"))
    else:
        tensors[name] = tensor[:-1].contiguous()  # "one row fewer"
    save_file(tensors, str(path), meta)


GT_ROOM = SyntheticConfig(frames=6, width=64, height=48, seed=5)
GT_KEYFRAMES = (0, 3, 5)


def checkpoint_with_loops(gaussians: int) -> Checkpoint:
    """A checkpoint of 12 frames with loop closure's state: 3 nodes, a loop edge, a loop closed."""
    from dataclasses import replace as replaced

    from pipeline.slam.loops.detection import ClosedLoop, LoopTally
    from pipeline.slam.loops.pose_graph import Edge, MotionSize
    from pipeline.slam.state import LoopState

    n = gaussians
    means = torch.randn(n, 3, generator=torch.Generator().manual_seed(0))
    map_ = Gaussians(means, torch.ones(n, 4), torch.zeros(n, 3), torch.zeros(n), torch.rand(n, 3))
    checkpoint = make_checkpoint(map_, [], torch.eye(4).repeat(12, 1, 1))
    f64 = torch.float64
    loops = LoopState(
        creator=torch.arange(n) % 3 - 1,  # nodes 0 and 1, and none (-1)
        node_c2w=torch.eye(4, dtype=f64).repeat(3, 1, 1),
        node_positions=[0, 5, 11],
        odometry_information=torch.eye(6, dtype=f64).repeat(3, 1, 1),
        loops=[Edge(0, 2, torch.eye(4, dtype=f64), 2 * torch.eye(6, dtype=f64), loop=True)],
        tally=LoopTally(detected=4, verified=3, accepted=1, rejected=3, searches=3, search_s=0.25),
        closed=[ClosedLoop(11, (0,), MotionSize(0.02, 1.0), 0.1, 0.05, 0.2)],
    )
    mapping = replaced(checkpoint.mapping, loops=loops, intrinsics=torch.eye(3))
    tracking = replaced(checkpoint.tracking, tracked_poses=torch.eye(4).repeat(12, 1, 1) * 2)
    return Checkpoint(tracking, mapping)


def write_gt_run(root: Path, room: SyntheticConfig = GT_ROOM) -> Path:
    """A run folder whose map is seeded from the room's exact depth at its exact poses (no SLAM):
    exports are checked against known geometry, not against tracking error."""
    write_synthetic(root / "room", room, progress=False)
    dataset = open_dataset(DatasetConfig(path=str(root / "room")))
    frames = [dataset.decode(ref) for ref in dataset.refs]
    keyframes, gaussians = [], None
    for frame in frames:
        color = torch.from_numpy(frame.color).float() / 255
        depth, c2w = torch.from_numpy(frame.depth), torch.from_numpy(frame.c2w_gt).float()
        k = torch.from_numpy(frame.intrinsics).float()
        if frame.index in GT_KEYFRAMES:
            keyframes.append(Keyframe.of(frame.index, color, depth, c2w))
        if frame.index in (0, len(frames) - 1):
            seeds = seed_gaussians(color, depth, k, c2w, depth > 0, GaussianConfig())
            gaussians = seeds if gaussians is None else concatenate(gaussians, seeds)
    assert gaussians is not None
    checkpoint = make_checkpoint(
        gaussians, keyframes, torch.stack([torch.from_numpy(f.c2w_gt).float() for f in frames])
    )
    (root / "run").mkdir()
    folder = RunFolder(root / "run")
    folder.write_config(replace(load_config("tiny"), dataset=DatasetConfig(path=str(root / "room"))))
    folder.write_state(checkpoint, RunDescription("room"), np.array([r.timestamp for r in dataset.refs]), None)
    write_intrinsics(folder.intrinsics, CameraIntrinsics.of_matrix(frames[0].intrinsics, room.width, room.height))
    return folder.path
