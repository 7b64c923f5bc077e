"""The `align` tracker: known motions, degenerate input, recovery, and its place in SplaTAM."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from pipeline.config import DatasetConfig, SyntheticConfig, load_config, with_dataset_defaults
from pipeline.frame import DeviceFrame
from pipeline.geometry import grid_around, invert_pose, se3_exp
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic import default_intrinsics, make_scene, render_view, trajectory
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.metrics import absolute_trajectory_error
from pipeline.render import Camera, Gaussians, RenderOutput, make_capacity_renderer, make_renderer
from pipeline.slam.gaussian_map import seed_gaussians
from pipeline.slam.sides import kernels_for
from pipeline.slam.splatam import SplaTAM
from pipeline.slam.tracking.align_tracker import (
    AlignTracker,
    best_grid_start,
    fitting_schedule,
    level_params,
    prepare_rgbd,
)
from pipeline.slam.tracking.rgbd_alignment import EAGER_ALIGN, LmState, align, lm_iteration, lm_start, solve_of
from pipeline.slam.tracking.trackers import TrackSettings, make_tracker
from pipeline.stages.upload import host_frame_tensors

CPU = torch.device("cpu")
WIDTH, HEIGHT = 128, 96
SCENE = make_scene(0)
START = trajectory(SyntheticConfig(seed=0), 1)[0]  # [4, 4] camera-to-world, float64


def ray_cast(c2w: np.ndarray, width: int = WIDTH, height: int = HEIGHT) -> tuple[torch.Tensor, torch.Tensor]:
    """The synthetic room seen exactly from camera-to-world `c2w` -> (colour [H, W, 3], depth [H, W])."""
    color, depth = render_view(SCENE, c2w, default_intrinsics(width, height), width, height, supersample=1)
    return torch.from_numpy(color).float() / 255, torch.from_numpy(depth)


def exact_renderer(gaussians: Gaussians, camera: Camera) -> RenderOutput:
    """A renderer of the room itself (the Gaussians are ignored): the map a tracker could wish for."""
    color, depth = ray_cast(invert_pose(camera.w2c.double()).numpy())
    none = torch.zeros(0)
    return RenderOutput(color, depth, (depth > 0).float(), none, none.bool())


def frame_of(color: torch.Tensor, depth: torch.Tensor, intrinsics: torch.Tensor | None = None) -> DeviceFrame:
    k = torch.from_numpy(default_intrinsics(WIDTH, HEIGHT)).float() if intrinsics is None else intrinsics
    return DeviceFrame(1, 0.0, color, depth, k, None)


def motion(translation_m: float, angle_deg: float, seed: int) -> np.ndarray:
    """A rigid motion [4, 4] of the given size along a random axis and direction."""
    gen = np.random.default_rng(seed)
    axis, direction = gen.normal(size=3), gen.normal(size=3)
    twist = np.r_[axis / np.linalg.norm(axis) * math.radians(angle_deg), direction / np.linalg.norm(direction)]
    twist[3:] *= translation_m
    return se3_exp(torch.from_numpy(twist)).numpy()


def pose_error(c2w: torch.Tensor, truth: np.ndarray) -> tuple[float, float]:
    """(translation mm, rotation degrees) between an estimate and the true camera-to-world."""
    error = np.linalg.inv(truth) @ c2w.double().numpy()
    rotation = error[:3, :3]
    sine = np.linalg.norm(
        [rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]]
    )
    angle = math.atan2(sine / 2, (np.trace(rotation) - 1) / 2)  # precise near 0, unlike acos
    return 1000 * float(np.linalg.norm(error[:3, 3])), math.degrees(angle)


def tiny_settings(renderer, method: str) -> TrackSettings:
    config = with_dataset_defaults(load_config("tiny", overrides=[f"tracking.method={method}"]), "replica")
    return TrackSettings(renderer, config.tracking, config.loss, config.render.near, config.render.far)


MOTIONS = [(0.10, 10.0, 0), (0.05, 8.0, 2), (0.10, 10.0, 5)]


@pytest.mark.parametrize("translation_m, angle_deg, seed", MOTIONS)
def test_align_recovers_known_motions_that_adam_cannot(translation_m: float, angle_deg: float, seed: int) -> None:
    """A camera moved by up to 10 cm and 10 degrees from the predicted pose, 128x96.

    align, against an exact render of the room at the prediction: within 2 mm and 0.2 degrees
    (measured: 0.20 mm / 0.002 deg, 0.99 mm / 0.015 deg, 1.28 mm / 0.033 deg). adam (tiny: 4
    iterations) against a map seeded from the room at the prediction moves 11-14 mm and stays
    52-100 mm and 7.8-9.8 degrees away. (align against such a seeded map is limited by the map:
    on these motions it ends 3 to 7 cm away at 128x96, as the seeded map's render lies up to a
    pixel footprint, 2-8 cm here, in front of the surface.)
    """
    truth = START @ motion(translation_m, angle_deg, seed)
    frame = frame_of(*ray_cast(truth))
    c2w_init = torch.from_numpy(START).float()

    aligned = make_tracker(tiny_settings(exact_renderer, "align"))(Gaussians(*[torch.zeros(0)] * 5), frame, c2w_init)
    assert aligned.failure == ""
    millimetres, degrees = pose_error(aligned.c2w, truth)
    assert millimetres < 2.0 and degrees < 0.2

    half = WIDTH // 4, HEIGHT // 4  # adam's reach does not depend on the size: 1/16 of the pixels to render
    half_k = torch.from_numpy(default_intrinsics(*half)).float()
    color, depth = ray_cast(START, *half)
    seeded = seed_gaussians(color, depth, half_k, c2w_init, depth > 0, load_config("tiny").gaussians)
    reference = make_renderer(load_config("tiny").render, load_config("tiny").gaussians, CPU)
    adam = make_tracker(tiny_settings(reference, "adam"))(seeded, frame_of(*ray_cast(truth, *half), half_k), c2w_init)
    millimetres, degrees = pose_error(adam.c2w, truth)
    assert millimetres > 2.0 or degrees > 0.2


def test_a_recorded_tracker_prepares_every_schedule_on_its_first_frame() -> None:
    """Where solves are recorded (CUDA), the first frame also makes the wide (from one start and
    from the grid) and the recovery solves, so that a later frame never waits for their compile;
    the pose is the same."""
    settings = tiny_settings(exact_renderer, "align")
    near, far = settings.near, settings.far
    plain = AlignTracker(exact_renderer, settings.config, near, far)
    warming = AlignTracker(exact_renderer, settings.config, near, far)
    warming._warmed = False  # as a recording (capture=True) tracker starts; the CPU cannot record
    truth = START @ motion(0.02, 1.0, 3)
    frame = frame_of(*ray_cast(truth))
    c2w_init = torch.from_numpy(START).float()
    first = warming(Gaussians(*[torch.zeros(0)] * 5), frame, c2w_init)
    assert len(warming._solvers) == 4 and len(plain._solvers) == 0
    assert torch.equal(first.c2w, plain(Gaussians(*[torch.zeros(0)] * 5), frame, c2w_init).c2w)
    assert len(plain._solvers) == 1
    warming(Gaussians(*[torch.zeros(0)] * 5), frame, c2w_init)
    assert len(warming._solvers) == 4  # made once


def test_a_failed_first_attempt_is_recovered_with_more_coarse_iterations() -> None:
    """One iteration per level cannot follow 10 cm and 10 degrees: the solve says so itself, and
    the recovery attempt (30 coarse-level iterations) brings the pose back."""
    truth = START @ motion(0.10, 10.0, 0)
    frame = frame_of(*ray_cast(truth))
    c2w_init = torch.from_numpy(START).float()
    hasty = replace(tiny_settings(exact_renderer, "align").config, align_iters=(1, 1, 1))
    without = AlignTracker(exact_renderer, replace(hasty, align_recovery_iters=0), 0.01, 100.0)(None, frame, c2w_init)
    assert "pixels on the map fit it" in without.failure
    recovered = AlignTracker(exact_renderer, hasty, 0.01, 100.0)(None, frame, c2w_init)
    assert recovered.failure == ""
    millimetres, degrees = pose_error(recovered.c2w, truth)
    assert millimetres < 10.0 and degrees < 0.2


SMALL = 64, 48  # the size of the reference-renderer tests below: the test suite's usual CPU size


def gaussian_room(width: int, height: int) -> Gaussians:
    """The room as a map: one Gaussian per pixel of the exact view at START (seeded as SLAM
    seeds a first frame)."""
    intrinsics = torch.from_numpy(default_intrinsics(width, height)).float()
    color, depth = ray_cast(START, width, height)
    return seed_gaussians(
        color, depth, intrinsics, torch.from_numpy(START).float(), depth > 0, load_config("tiny").gaussians
    )


REFERENCE = make_renderer(load_config("tiny").render, load_config("tiny").gaussians, CPU)


def seen_in(gaussians: Gaussians, c2w: np.ndarray, width: int, height: int) -> DeviceFrame:
    """A frame of the map itself, as the reference renderer shows it from camera-to-world `c2w`:
    a world that tracking against the same renderer can match exactly, so what remains is the
    solve's. Depth where the map covers a pixel (silhouette over 0.9), none elsewhere."""
    intrinsics = torch.from_numpy(default_intrinsics(width, height)).float()
    camera = Camera(invert_pose(torch.from_numpy(c2w).float()), intrinsics, width, height, 0.01, 100.0)
    out = REFERENCE(gaussians, camera)
    covered = out.silhouette > 0.9
    color = (out.color / out.silhouette.clamp(min=0.9)[..., None]).clamp(0, 1)
    return DeviceFrame(1, 0.0, color, torch.where(covered, out.depth, torch.zeros_like(out.depth)), intrinsics, None)


@pytest.mark.parametrize("seed", [1, 3, 5])
def test_a_large_step_is_tracked_by_rendering_again_where_one_render_falls_short(seed: int) -> None:
    """A frame 15 cm and 10 degrees from its guess, on the reference renderer (a Gaussian map
    of the room at 64x48, the frame that map's own render at the true pose).

    Today's settings (one render, no wide schedule) fall short by more than 1 cm: the map seen
    from 15 cm away is not the map seen from the frame's pose (occlusions, blending, what is in
    view), and nothing tells it so (measured on seeds 1, 3, 5: 15.9, 275.7, 25.2 mm, none
    flagged). Rendering again at the aligned pose and aligning once more, wide: within 2 mm
    (measured 1.6, 0.2, 1.8 mm)."""
    width, height = SMALL
    room = gaussian_room(width, height)
    truth = START @ motion(0.15, 10.0, seed)
    frame = seen_in(room, truth, width, height)
    c2w_init = torch.from_numpy(START).float()
    config = tiny_settings(None, "align").config
    today = replace(config, align_max_renders=1, align_wide_iters=config.align_iters)

    one_render = AlignTracker(REFERENCE, today, 0.01, 100.0)(room, frame, c2w_init)
    assert pose_error(one_render.c2w, truth)[0] > 10.0

    followed = AlignTracker(REFERENCE, config, 0.01, 100.0)(room, frame, c2w_init)
    assert followed.failure == ""
    millimetres, degrees = pose_error(followed.c2w, truth)
    assert millimetres < 10.0 and degrees < 0.5


def test_a_solve_that_stops_short_is_flagged() -> None:
    """With one iteration per level the solve creeps: after its last render it still moves
    more than a large step, and says so."""
    width, height = SMALL
    room = gaussian_room(width, height)
    truth = START @ motion(0.15, 10.0, 2)
    frame = seen_in(room, truth, width, height)
    config = tiny_settings(None, "align").config
    hasty = replace(config, align_iters=(1, 1, 1), align_wide_iters=(1, 1, 1), align_max_renders=2)
    result = AlignTracker(REFERENCE, hasty, 0.01, 100.0)(room, frame, torch.from_numpy(START).float())
    assert result.failure.startswith("the alignment stopped short: after 2 renders its last solve still moved")
    assert pose_error(result.c2w, truth)[0] > 10.0


def test_the_wide_schedule_keeps_a_coarsest_level_of_a_dozen_pixels() -> None:
    assert fitting_schedule((20, 10, 6, 4), 480, 640) == (20, 10, 6, 4)
    assert fitting_schedule((20, 10, 6, 4), 60, 80) == (20, 6, 4)  # 60 -> 30 -> 15 (-> 7: too few)
    assert fitting_schedule((20, 10, 6, 4), 24, 32) == (20, 4)
    assert fitting_schedule((20, 10, 6, 4), 8, 8) == (20,)


def stub_renderer(color: torch.Tensor, depth: torch.Tensor):
    """A renderer that shows the same images from every pose."""

    def render(gaussians: Gaussians, camera: Camera) -> RenderOutput:
        none = torch.zeros(0)
        return RenderOutput(color, depth, (depth > 0).float(), none, none.bool())

    return render


SMALL_K = torch.tensor([[40.0, 0.0, 32.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]])
_V, _U = torch.meshgrid(torch.arange(48) + 0.5, torch.arange(64) + 0.5, indexing="ij")
WALL = torch.full((48, 64), 2.0)  # a plane facing the camera, 2 m away
GREY = torch.full((48, 64, 3), 0.5)
PATTERN = (0.5 + 0.5 * torch.sin(_U / 2) * torch.cos(_V / 3))[..., None].expand(48, 64, 3).contiguous()


@pytest.mark.parametrize(
    "render_color, frame_color, frame_depth, failure",
    [
        (GREY, GREY, torch.zeros(48, 64), "no valid depth to align (0 pixels)"),
        (GREY, GREY, WALL, "the alignment is ill-conditioned"),  # a single plane and no texture
        (PATTERN, GREY, WALL, "intensity residual"),  # a textureless frame where the map has texture
    ],
    ids=["no valid depth", "single plane", "textureless frame"],
)
def test_degenerate_input_is_flagged_with_a_finite_pose(render_color, frame_color, frame_depth, failure) -> None:
    tracker = AlignTracker(stub_renderer(render_color, WALL), tiny_settings(None, "align").config, 0.01, 100.0)
    c2w_init = torch.eye(4)
    result = tracker(None, frame_of(frame_color, frame_depth, SMALL_K), c2w_init)
    assert result.failure.startswith(failure)
    assert torch.isfinite(result.c2w).all() and torch.isfinite(result.coverage)
    assert np.linalg.norm(result.c2w[:3, 3]) < 0.1  # no wild step along the directions nothing fixes


def test_a_single_textured_plane_is_not_degenerate() -> None:
    """Point-to-plane alone fixes 3 of 6 degrees of freedom on a plane; the texture fixes the rest."""
    tracker = AlignTracker(stub_renderer(PATTERN, WALL), tiny_settings(None, "align").config, 0.01, 100.0)
    result = tracker(None, frame_of(PATTERN, WALL, SMALL_K), torch.eye(4))
    assert result.failure == ""
    torch.testing.assert_close(result.c2w, torch.eye(4), atol=1e-4, rtol=0)


def test_the_iteration_traces_as_one_graph_that_matches_the_eager_one() -> None:
    """The per-level Levenberg-Marquardt iteration is what run.compile compiles: it must trace
    whole (no graph break, so no host sync: capturable as a CUDA graph) and agree with its plain
    twin. Traced by dynamo and run as traced (backend "eager"); inductor's code generation (the
    GPU's fused kernels) is compared with eager on the GPU by bench/align_cost.py."""
    tracker = AlignTracker(stub_renderer(PATTERN, WALL), tiny_settings(None, "align").config, 0.01, 100.0)
    frame = frame_of(torch.roll(PATTERN, 1, dims=1), WALL * 1.01, SMALL_K)  # a little off: steps to take
    sources, targets = tracker.prepare(frame, tracker._render(None, frame, torch.eye(4))[0])
    compiled = torch.compile(lm_iteration, backend="eager", fullgraph=True, dynamic=False)
    eager = lm_start(torch.eye(4, dtype=torch.float64))
    fast = eager
    for _ in range(3):
        eager = lm_iteration(eager, sources[0], targets[0], tracker.params[0])
        fast = compiled(fast, sources[0], targets[0], tracker.params[0])
    torch.testing.assert_close(fast.pose, eager.pose, atol=1e-6, rtol=0)
    torch.testing.assert_close(fast.fit.cost, eager.fit.cost, rtol=1e-5, atol=0)
    assert not torch.equal(eager.pose, torch.eye(4, dtype=torch.float64))


@pytest.mark.slow
def test_tiny_with_align_beats_adam_on_a_fast_sequence(tmp_path) -> None:
    """8 frames of the generated room at 1 m/s (3.3 cm a frame), 64x48, the tiny preset.

    Measured: align ATE RMSE 3.0 cm and no frame lost; adam 3.9 cm, and from frame 3 on its
    map covers under 5% of the pixels above its silhouette threshold, so 5 frames are lost
    (and not mapped). Adam's 4 iterations move ~2 mm each: it trails the camera.
    """
    path = tmp_path / "fast"
    write_synthetic(path, SyntheticConfig(frames=8, width=64, height=48, seed=3, speed=1.0), progress=False)
    dataset = open_dataset(DatasetConfig(path=str(path)))
    frames = [host_frame_tensors(f) for f in dataset.frames()]
    outcome = {}
    for method in ("align", "adam"):
        config = with_dataset_defaults(load_config("tiny", overrides=[f"tracking.method={method}"]), "replica")
        slam = SplaTAM(config, make_renderer(config.render, config.gaussians, CPU), CPU)
        results = [slam.step(f, is_last=i == len(frames) - 1) for i, f in enumerate(frames)]
        estimate = np.stack([r.c2w.double().numpy() for r in results])
        reference = np.stack([r.c2w_gt.double().numpy() for r in results])
        outcome[method] = (absolute_trajectory_error(estimate, reference).rmse_m, sum(bool(r.lost) for r in results))
    assert outcome["align"][1] == 0
    assert outcome["align"][0] < outcome["adam"][0]


def test_the_fixed_capacity_render_tracks_as_the_plain_one_and_grows_past_an_overflow() -> None:
    """A map seeded from the start view, the frame 1 cm and 1 degree away: tracked with the
    reference renderer at a capacity far below the render's intersections (the first pass
    overflows, runs again at a grown capacity) the pose equals the plain render's; at a capacity
    that holds them, no pass runs twice."""
    config = with_dataset_defaults(load_config("tiny"), "replica")
    k = torch.from_numpy(default_intrinsics(WIDTH, HEIGHT)).float()
    c2w_init = torch.from_numpy(START).float()
    color, depth = ray_cast(START)
    seeded = seed_gaussians(color, depth, k, c2w_init, depth > 0, config.gaussians)
    frame = frame_of(*ray_cast(START @ motion(0.01, 1.0, 1)))
    renderer = make_renderer(config.render, config.gaussians, CPU)
    capacity_renderer = make_capacity_renderer(config.render, config.gaussians, CPU)
    near, far = config.render.near, config.render.far
    plain = AlignTracker(renderer, config.tracking, near, far)(seeded, frame, c2w_init)
    passes: list[int] = []

    def counted(gaussians: Gaussians, cameras: list[Camera], capacity: int):  # type: ignore[no-untyped-def]
        passes.append(capacity)
        return capacity_renderer(gaussians, cameras, capacity)  # type: ignore[misc]

    small = AlignTracker(renderer, config.tracking, near, far, capacity_renderer=counted, capacity=64)
    fixed = small(seeded, frame, c2w_init)
    assert passes[0] == 64 and passes[1] > 64 and small.capacity == passes[-1]
    assert fixed.failure == plain.failure and torch.allclose(fixed.c2w, plain.c2w, atol=1e-5)
    passes.clear()
    again = small(seeded, frame, c2w_init)
    assert passes and all(p == small.capacity for p in passes)  # no overflow: each render once, at the grown capacity
    assert torch.allclose(again.c2w, plain.c2w, atol=1e-5)


def test_a_large_real_step_is_solved_from_the_grid_start_of_least_residual(cabinet_sample) -> None:
    """The cabinet loop's first 28 real steps (17 cm and 7 degrees a frame at 0.67 s; 160x120),
    each frame aligned to the frame before as its view, from the frame before's pose (the whole
    step to find). From that one start the wide solve often turns the camera nearly right and
    takes the rest as a sideways step (measured: 3.5 cm mean, 6 steps over 5 cm); from the
    grid's best start 2.3 cm, 2 over 5 cm (all 56 steps: 4.0 -> 2.6 cm, 16 -> 7; at 640x480 from
    constant velocity's guess 4.3 -> 1.7 cm, 15 -> 3 of 55; bench/NOTES.md, Change 25)."""
    width, height = 160, 120
    sample = DatasetConfig(str(cabinet_sample), width=width, height=height, end=29)
    frames = [host_frame_tensors(f) for f in open_dataset(sample).frames()]
    config = load_config("tiny").tracking
    tracker = AlignTracker(REFERENCE, config, 0.01, 100.0)
    schedule = fitting_schedule(config.align_wide_iters, height, width)
    errors: dict[float, list[float]] = {0.0: [], config.align_grid_m: []}
    for before, frame in zip(frames, frames[1:]):
        assert before.c2w_gt is not None and frame.c2w_gt is not None
        truth = invert_pose(before.c2w_gt.double()) @ frame.c2w_gt.double()
        view = (before.color, before.depth, (before.depth > 0).float())
        for grid_m, found in errors.items():
            starts = grid_around(torch.eye(4, dtype=torch.float64), grid_m) if grid_m else None
            state, _ = tracker.solve_images(frame.color, frame.depth, frame.intrinsics, *view, schedule, starts)
            found.append(100 * float(torch.linalg.norm((invert_pose(state.pose) @ truth)[:3, 3])))
    single, grid = (np.array(found) for found in errors.values())
    assert grid.mean() < 0.75 * single.mean() and (grid > 5).sum() < 0.6 * (single > 5).sum()


def test_the_grid_start_is_the_least_residual_of_those_that_fit_enough() -> None:
    def solves(*fits: tuple[float, int, int, float]) -> LmState:
        """A batch of solves, each (RMS residual metres, inliers, associated, pose's x)."""
        rms_m, inliers, associated, x = zip(*fits)
        rms_m, x = torch.tensor(rms_m, dtype=torch.float64), torch.tensor(x, dtype=torch.float64)
        inliers, associated = torch.tensor(inliers), torch.tensor(associated)
        pose = torch.eye(4, dtype=torch.float64).repeat(len(fits), 1, 1)
        pose[:, 0, 3] = x
        state = lm_start(pose)
        fit = state.fit._replace(geometric_sq=rms_m**2 * inliers, inliers=inliers, associated=associated)
        return state._replace(fit=fit)

    # the least residual fits only 30% of what it sees: the next least is taken
    grid = solves((0.010, 900, 1000, 0.0), (0.002, 300, 1000, 0.15), (0.005, 800, 1000, -0.15))
    assert float(best_grid_start(grid, 0.5)[0, 3]) == -0.15
    assert float(best_grid_start(grid, 0.2)[0, 3]) == 0.15
    nothing = solves((0.01, 0, 1000, 0.1), (0.01, 10, 1000, 0.2))
    assert float(best_grid_start(nothing, 0.5)[0, 3]) == 0.1  # none fits: the first


def test_solves_from_a_batch_of_starts_equal_those_from_each_start() -> None:
    """The grid's coarse solves run batched (one kernel per operation for all starts, `batched`):
    the same poses and fits as one solve per start."""
    color, depth = ray_cast(START)
    moved_color, moved_depth = ray_cast(START @ motion(0.08, 6.0, 1))
    k = torch.from_numpy(default_intrinsics(WIDTH, HEIGHT)).float()
    sources, targets = prepare_rgbd(moved_color, moved_depth, k, color, depth, (depth > 0).float(), 3, 0.5)
    config = tiny_settings(None, "align").config
    params, schedule = level_params(config, 3), (3, 2, 1)  # short: the starts end apart
    starts = grid_around(torch.eye(4, dtype=torch.float64), 0.05)
    together = align(sources, targets, params, schedule, EAGER_ALIGN.batch, starts)
    for index, start in enumerate(starts):
        alone, one_of = align(sources, targets, params, schedule, lm_iteration, start), solve_of(together, index)
        assert torch.allclose(one_of.pose, alone.pose, atol=1e-9)
        assert torch.allclose(one_of.fit.cost, alone.fit.cost, rtol=1e-9)
        assert int(one_of.fit.inliers) == int(alone.fit.inliers)
    assert len({round(float(cost), 3) for cost in together.fit.cost}) > 1  # the starts did differ


def test_a_grid_of_starts_holds_the_prediction_first_and_moves_the_camera_in_its_own_axes() -> None:
    relative = se3_exp(torch.tensor([0.1, -0.2, 0.3, 0.5, 0.0, -1.0], dtype=torch.float64))
    starts = grid_around(relative, 0.15)
    assert starts.shape == (9, 4, 4) and torch.equal(starts[0], relative)
    moves = {tuple(round(float(v), 6) for v in (invert_pose(relative) @ s)[:3, 3]) for s in starts}
    assert moves == {(x, 0.0, z) for x in (-0.15, 0.0, 0.15) for z in (-0.15, 0.0, 0.15)}


def test_the_grids_iteration_is_left_uncompiled_when_asked() -> None:
    """`run.compile_grid=false`: the one-start iteration compiled, the grid's batched one not
    (made, never called: no compile happens here)."""

    def compiled(fn: object) -> bool:
        return hasattr(fn, "_torchdynamo_orig_callable")

    for grid in (True, False):
        config = load_config("tiny", overrides=["run.compile=on", f"run.compile_grid={str(grid).lower()}"])
        kernels = kernels_for(config, torch.device("cpu"))
        assert compiled(kernels.align.one) and compiled(kernels.align.batch) == grid
    assert not compiled(
        kernels_for(load_config("tiny", overrides=["run.compile=off"]), torch.device("cpu")).align.batch
    )
