"""The GPU paths of the pipeline against their plain twins: the pinned side-stream upload, the
`align` solve replayed as a CUDA graph, the compiled kernels. Skipped without CUDA."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.config import SyntheticConfig, load_config, with_dataset_defaults
from pipeline.frame import DeviceFrame, Frame
from pipeline.geometry import invert_pose, se3_exp
from pipeline.io.sources.datasets.synthetic import default_intrinsics, make_scene, render_view, trajectory
from pipeline.package_builds import BUILDS
from pipeline.render import Camera, RenderOutput, make_capacity_renderer, make_renderer
from pipeline.slam.gaussian_map import seed_gaussians
from pipeline.slam.kernels import EAGER, make_kernels
from pipeline.slam.precompiled import Precompiled
from pipeline.slam.process.schedule import start_process_slam
from pipeline.slam.splatam import SplaTAM
from pipeline.slam.tracking.align_tracker import AlignTracker
from pipeline.stages.upload import PinnedUploader, host_frame_tensors

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]
CUDA = torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
WIDTH, HEIGHT = 160, 120
SCENE = make_scene(0)


def _frame(index: int, c2w: np.ndarray) -> Frame:
    k = default_intrinsics(WIDTH, HEIGHT)
    color, depth = render_view(SCENE, c2w, k, WIDTH, HEIGHT, supersample=1)
    return Frame(index, 0.1 * index, color, depth.astype(np.float32), k, c2w)


def test_the_pinned_side_stream_upload_equals_a_plain_copy() -> None:
    poses = trajectory(SyntheticConfig(seed=0), 6)
    uploader = PinnedUploader(CUDA, slots=2)  # fewer slots than frames: each slot is reused
    frames = [_frame(i, pose) for i, pose in enumerate(poses)]
    uploaded = [uploader(frame) for frame in frames]
    for frame, upload in zip(frames, uploaded):
        got = upload.wait()
        want = host_frame_tensors(frame)
        for name in ("depth", "intrinsics", "c2w_gt"):
            assert torch.equal(getattr(got, name).cpu(), getattr(want, name)), name
        # The same bytes, divided by 255 on the GPU and on the CPU: equal to the last bit or one off.
        torch.testing.assert_close(got.color.cpu(), want.color, rtol=0, atol=2**-23)


def _exact_renderer(gaussians: object, camera: Camera) -> RenderOutput:
    """The room itself, seen from the camera (the Gaussians are ignored): a map without error."""
    c2w = invert_pose(camera.w2c.double()).cpu().numpy()
    color, depth = render_view(SCENE, c2w, default_intrinsics(WIDTH, HEIGHT), WIDTH, HEIGHT, supersample=1)
    color_t = torch.from_numpy(color).float().div(255).to(CUDA)
    depth_t = torch.from_numpy(depth).float().to(CUDA)
    none = torch.zeros(0, device=CUDA)
    return RenderOutput(color_t, depth_t, (depth_t > 0).float(), none, none.bool())


@pytest.mark.parametrize("wide", [False, True], ids=["one start", "grid of starts"])
def test_the_align_solve_replayed_as_a_cuda_graph_equals_the_eager_solve(
    wide: bool, caplog: pytest.LogCaptureFixture
) -> None:
    config = with_dataset_defaults(load_config("tiny", overrides=["tracking.method=align"]), "replica")
    start = trajectory(SyntheticConfig(seed=0), 1)[0]
    truth = start @ se3_exp(torch.tensor([0.02, -0.01, 0.015, 0.03, 0.01, -0.02], dtype=torch.float64)).numpy()
    upload = host_frame_tensors(_frame(1, truth))
    frame = type(upload)(**{k: (v.to(CUDA) if isinstance(v, torch.Tensor) else v) for k, v in vars(upload).items()})
    init = torch.from_numpy(start).float().to(CUDA)
    variants = {"eager": (EAGER, False), "graphed": (EAGER, True)}
    variants["compiled and graphed"] = (make_kernels(compiled=True), True)  # as the presets run on CUDA
    variants["compiled, the grid's iteration not, graphed"] = (make_kernels(True, compile_grid=False), True)
    near, far = config.render.near, config.render.far
    building = make_kernels(True, precompile=True)  # this solve's packages built (the fallback runs meanwhile)
    AlignTracker(_exact_renderer, config.tracking, near, far, building.align, capture=False)(
        None, frame, init, wide=wide
    )  # type: ignore[arg-type]
    assert BUILDS.wait()
    precompiled = make_kernels(True, precompile=True)  # as a later run: the packages loaded
    variants["precompiled (AOTInductor) and graphed"] = (precompiled, True)
    results = {}
    for name, (kernels, capture) in variants.items():
        tracker = AlignTracker(_exact_renderer, config.tracking, near, far, kernels.align, capture=capture)
        for _ in range(2):  # a graph is recorded on the first call and replayed on the second
            results[name] = tracker(None, frame, init, wide=wide)  # type: ignore[arg-type]
    assert "could not be recorded" not in caplog.text  # replayed, not run uncaptured after a failed recording
    assert "could not be compiled ahead of time" not in caplog.text
    assert isinstance(precompiled.align.one, Precompiled) and precompiled.align.one.loaded > 0  # the packages ran
    assert not wide or (isinstance(precompiled.align.batch, Precompiled) and precompiled.align.batch.loaded > 0)
    eager = results["eager"]
    assert eager.failure == ""
    assert float(torch.linalg.norm(eager.c2w[:3, 3].double().cpu() - torch.from_numpy(truth[:3, 3]))) < 0.005
    for name in list(variants)[1:]:
        assert results[name].failure == "", name
        assert torch.allclose(results[name].c2w, eager.c2w, atol=1e-5), name
        assert torch.allclose(results[name].coverage, eager.coverage), name


def _images(seed: int) -> tuple[torch.Tensor, ...]:
    generator = torch.Generator().manual_seed(seed)
    color = torch.rand(HEIGHT, WIDTH, 3, generator=generator)
    depth = torch.rand(HEIGHT, WIDTH, generator=generator) * 4
    depth[torch.rand(HEIGHT, WIDTH, generator=generator) < 0.1] = 0
    silhouette = torch.rand(HEIGHT, WIDTH, generator=generator)
    render_color = (color + 0.1 * torch.rand(HEIGHT, WIDTH, 3, generator=generator)).clamp(0, 1)
    render_depth = depth + 0.05 * torch.rand(HEIGHT, WIDTH, generator=generator)
    return tuple(t.to(CUDA) for t in (render_color, render_depth, silhouette, color, depth))


def test_the_compiled_losses_equal_the_eager_ones_in_value_and_gradient() -> None:
    """Eager, torch.compile'd, and from packages (the mapping loss's joint package, built beside
    a first call: the tracking loss stays compiled)."""
    render_color, render_depth, silhouette, color, depth = _images(0)
    building = make_kernels(compiled=True, precompile=True)
    rc, rd = render_color.clone().requires_grad_(True), render_depth.clone().requires_grad_(True)
    building.mapping_loss(rc, rd, color, depth, 0.2, 1.0, 0.5)
    assert BUILDS.wait()
    packaged = make_kernels(compiled=True, precompile=True)
    values, grads = [], []
    for kernels in (EAGER, make_kernels(compiled=True), packaged):
        rc = render_color.clone().requires_grad_(True)
        rd = render_depth.clone().requires_grad_(True)
        mapping = kernels.mapping_loss(rc, rd, color, depth, 0.2, 1.0, 0.5)
        tracking, pixels = kernels.tracking_loss(rc, rd, silhouette, color, depth, 0.99, 1.0, 0.5)
        (mapping + 1e-3 * tracking).backward()
        values.append((mapping.detach(), tracking.detach(), pixels))
        grads.append((rc.grad, rd.grad))
    assert isinstance(packaged.mapping_loss, Precompiled) and packaged.mapping_loss.loaded == 1
    (m0, t0, p0), *others = values
    for m1, t1, p1 in others:
        assert torch.allclose(m0, m1, rtol=1e-5) and torch.allclose(t0, t1, rtol=1e-5) and torch.equal(p0, p1)
    for other in grads[1:]:
        for g0, g1 in zip(grads[0], other):
            assert torch.allclose(g0, g1, rtol=1e-4, atol=1e-8)


def _device_frames(count: int) -> list[DeviceFrame]:
    poses = trajectory(SyntheticConfig(seed=0), count)
    frames = []
    for i, pose in enumerate(poses):
        upload = host_frame_tensors(_frame(i, pose))
        frames.append(
            type(upload)(**{k: (v.to(CUDA) if isinstance(v, torch.Tensor) else v) for k, v in vars(upload).items()})
        )
    return frames


def test_sequential_at_keyframe_rate_on_the_gpu_maps_keyframes_and_refines_between() -> None:
    """gsplat's renderer, compiled kernels and graphed mapping: a pose per frame, densified at
    keyframes only, each frame between them a new (refined) map version, the track close."""
    config = with_dataset_defaults(
        load_config("tiny", overrides=["mapping.rate=keyframe", "mapping.refine_between=1", "keyframes.every=3"]),
        "replica",
    )
    slam = SplaTAM(config, make_renderer(config.render, config.gaussians, CUDA), CUDA)
    frames = _device_frames(8)
    results = [slam.step(frame, is_last=frame.index == len(frames) - 1) for frame in frames]
    assert not any(r.lost for r in results) and len(slam.poses) == len(frames)
    assert results[0].mapped and results[-1].mapped and any(r.between_keyframes for r in results)
    assert all(r.added == 0 and not r.mapped for r in results if r.between_keyframes)
    versions = [r.map_version for r in results]
    assert versions == sorted(versions) and len(set(versions)) == len(versions)  # every frame publishes
    start = invert_pose(frames[0].c2w_gt.cpu().float())  # SLAM's world is the first camera's
    for pose, frame in zip(slam.poses, frames):
        reference = start @ frame.c2w_gt.cpu().float()
        # the track close, not exact: `tiny` on this small render of the room measured 4.7 cm worst (H200, 4214548)
        assert float(torch.linalg.norm(pose[:3, 3].cpu() - reference[:3, 3])) < 0.08


def test_the_process_schedule_warms_its_tracker_while_mapping_starts() -> None:
    """On CUDA the tracker's first call is made on the first frame, beside the mapping process's
    start-up, and the start is reported in parts."""
    config = with_dataset_defaults(load_config("tiny", overrides=["slam.schedule=process"]), "replica")
    slam = start_process_slam(config, CUDA, live=False)
    try:
        frames = _device_frames(3)
        results = [slam.step(frame, is_last=frame.index == 2) for frame in frames]
        assert not any(r.lost for r in results)
        slam.finish(0)
        start = slam.mapping_summary()["start_up"]
        assert all(value is not None and value > 0 for value in start.values()), start
    finally:
        slam.close()


def test_the_thread_schedule_maps_beside_tracking_on_a_stream_of_its_own() -> None:
    """Mapping's graphs recorded and replayed in a thread of this process while tracking's run
    in the main thread: a pose per frame, keyframes mapped, the track as close as sequential's."""
    overrides = ["slam.schedule=thread", "keyframes.every=3"]
    config = with_dataset_defaults(load_config("tiny", overrides=overrides), "replica")
    slam = start_process_slam(config, CUDA, live=False)
    try:
        frames = _device_frames(8)
        results = [slam.step(frame, is_last=frame.index == len(frames) - 1) for frame in frames]
        slam.finish(0)
        assert not any(r.lost for r in results) and len(slam.poses) == len(frames)
        assert slam.mapping_summary()["frames_mapped"] >= 3 and not slam.failure
        start = invert_pose(frames[0].c2w_gt.cpu().float())
        for pose, frame in zip(slam.poses, frames):
            reference = start @ frame.c2w_gt.cpu().float()
            assert float(torch.linalg.norm(pose[:3, 3].cpu() - reference[:3, 3])) < 0.08
    finally:
        slam.close()


def test_the_tracker_at_a_fixed_capacity_equals_gsplats_own_render() -> None:
    """gsplat's kernels around our intersection list, at a capacity that overflows first: the
    align tracker's pose equals the one from gsplat's eager render."""
    config = with_dataset_defaults(load_config("tiny"), "replica")
    frames = _device_frames(2)
    first, second = frames
    start = first.c2w_gt.float()
    seeded = seed_gaussians(first.color, first.depth, first.intrinsics, start, first.depth > 0, config.gaussians)
    near, far = config.render.near, config.render.far
    renderer = make_renderer(config.render, config.gaussians, CUDA)
    plain = AlignTracker(renderer, config.tracking, near, far)(seeded, second, start)
    capacity_renderer = make_capacity_renderer(config.render, config.gaussians, CUDA)
    fixed_tracker = AlignTracker(
        renderer, config.tracking, near, far, capacity_renderer=capacity_renderer, capacity=1024
    )
    fixed = fixed_tracker(seeded, second, start)
    assert fixed_tracker.capacity > 1024 and fixed.failure == plain.failure
    assert torch.allclose(fixed.c2w, plain.c2w, atol=1e-4)
