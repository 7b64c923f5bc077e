"""gsplat on the GPU: against the reference renderer, and the fixed-capacity render against
gsplat's own rasterisation, eager and replayed as a CUDA graph. Skipped without CUDA."""

from __future__ import annotations

import pytest
import torch
from gpu_scenes import TOLERANCE, leaves, loss_of, random_pose, random_scene, rel

from pipeline.geometry import invert_pose
from pipeline.render.reference import render_reference
from pipeline.render.types import Camera, Gaussians, RenderOutput
from pipeline.slam.cuda_graphs import record

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]
WIDTH, HEIGHT = 320, 240


def _scene(n: int, isotropic: bool, seed: int) -> tuple[Gaussians, Camera, tuple[torch.Tensor, ...]]:
    device = torch.device("cuda")
    generator = torch.Generator().manual_seed(seed)
    k = torch.tensor([[0.8 * WIDTH, 0, WIDTH / 2], [0, 0.8 * WIDTH, HEIGHT / 2], [0, 0, 1]], device=device)
    c2w = random_pose(generator, device)
    scene = random_scene(n, isotropic, c2w, k, WIDTH, HEIGHT, generator)
    weights = tuple(
        torch.rand(*shape, generator=generator).to(device)
        for shape in ((HEIGHT, WIDTH, 3), (HEIGHT, WIDTH), (HEIGHT, WIDTH))
    )
    return scene, Camera(invert_pose(c2w), k, WIDTH, HEIGHT), weights


def _with_grads(render, scene: Gaussians, camera: Camera, weights) -> tuple[RenderOutput, dict[str, torch.Tensor]]:
    g = leaves(scene)
    view = camera.w2c.clone().requires_grad_(True)
    out = render(g, Camera(view, camera.intrinsics, camera.width, camera.height))
    loss_of(out, weights).backward()
    grads = {"means": g.means.grad, "colors": g.colors.grad, "opacities": g.opacity_logits.grad}
    grads |= {"scales": g.log_scales.grad, "viewmat": view.grad[:3]}
    return out, grads


@pytest.mark.parametrize("isotropic", [True, False])
def test_gsplat_matches_the_reference_renderer_in_images_and_gradients(isotropic: bool) -> None:
    from pipeline.render.gsplat_backend import render_gsplat_3d

    scene, camera, weights = _scene(2_000, isotropic, seed=11 + isotropic)
    gs, gs_grads = _with_grads(render_gsplat_3d, scene, camera, weights)
    ref, ref_grads = _with_grads(render_reference, scene, camera, weights)
    assert int(ref.visible.sum()) > 1_000
    for image in ("color", "depth", "silhouette"):
        assert rel(getattr(gs, image), getattr(ref, image)) < TOLERANCE["image"], image
    for name in gs_grads:
        assert rel(gs_grads[name], ref_grads[name]) < TOLERANCE["grad"], name


def _capacity_render(capacity: int, check: bool = True):
    """The fixed-capacity render of one camera (`check`: assert that the intersections fit,
    a host read, so not while recording a graph)."""
    from pipeline.render.gsplat_backend import render_gsplat_3d_capacity

    def render(gaussians: Gaussians, camera: Camera) -> RenderOutput:
        outputs, hits = render_gsplat_3d_capacity(gaussians, [camera], capacity)
        assert not check or not bool(hits.overflowed())
        return outputs[0]

    return render


def _count(scene: Gaussians, cameras: list[Camera]) -> int:
    from pipeline.render.gsplat_backend import render_gsplat_3d_capacity

    with torch.no_grad():
        return int(render_gsplat_3d_capacity(scene, cameras, 1)[1].count)


def test_the_fixed_capacity_render_equals_gsplats_rasterisation() -> None:
    from pipeline.render.gsplat_backend import render_gsplat_3d

    scene, camera, weights = _scene(20_000, isotropic=False, seed=5)
    count = _count(scene, [camera])
    eager, eager_grads = _with_grads(render_gsplat_3d, scene, camera, weights)
    for capacity in (count, int(1.5 * count)):
        fixed, fixed_grads = _with_grads(_capacity_render(capacity), scene, camera, weights)
        for image in ("color", "depth", "silhouette"):
            assert torch.allclose(getattr(fixed, image), getattr(eager, image), atol=1e-6), (capacity, image)
        assert torch.equal(fixed.radii, eager.radii)
        for name in eager_grads:
            assert rel(fixed_grads[name], eager_grads[name]) < 1e-5, (capacity, name)


def test_a_capacity_too_small_is_reported_and_the_grown_one_renders_right() -> None:
    from pipeline.render.gsplat_backend import render_gsplat_3d_capacity, render_gsplat_3d_views

    scene, camera, _ = _scene(5_000, isotropic=True, seed=7)
    moved = invert_pose(invert_pose(camera.w2c) @ _small_motion(camera.w2c.device))
    cameras = [camera, Camera(moved, camera.intrinsics, WIDTH, HEIGHT)]
    count = _count(scene, cameras)
    with torch.no_grad():
        _, short = render_gsplat_3d_capacity(scene, cameras, count // 2)
        assert bool(short.overflowed()) and int(short.count) == count
        grown, hits = render_gsplat_3d_capacity(scene, cameras, count + 1024)
        expected = render_gsplat_3d_views(scene, cameras)
    assert not bool(hits.overflowed())
    for got, want in zip(grown, expected):
        assert torch.allclose(got.color, want.color, atol=1e-6) and torch.allclose(got.depth, want.depth, atol=1e-6)


def test_the_fixed_capacity_render_replays_as_a_cuda_graph() -> None:
    """Forward and backward recorded once, replayed at a new pose: the same images and
    gradients as an eager call at that pose."""
    scene, camera, weights = _scene(20_000, isotropic=False, seed=9)
    capacity = 2 * _count(scene, [camera])
    render = _capacity_render(capacity, check=False)
    g = leaves(scene)
    view = camera.w2c.clone().requires_grad_(True)

    def step() -> torch.Tensor:
        for tensor in (view, *vars(g).values()):
            tensor.grad = None  # the recorded backward writes fresh gradients in the graph's memory
        out = render(g, Camera(view, camera.intrinsics, WIDTH, HEIGHT))
        loss_of(out, weights).backward()
        return out.color

    graph, color = record(step, warmup=2)
    moved = invert_pose(invert_pose(camera.w2c) @ _small_motion(camera.w2c.device))
    with torch.no_grad():
        view.copy_(moved)  # the recorded backward writes the gradients afresh: nothing to zero
    graph.replay()
    replayed = {"color": color.clone(), "means": g.means.grad.clone(), "viewmat": view.grad[:3].clone()}
    eager, eager_grads = _with_grads(
        _capacity_render(capacity), scene, Camera(moved, camera.intrinsics, WIDTH, HEIGHT), weights
    )
    assert torch.allclose(replayed["color"], eager.color, atol=1e-6)
    assert rel(replayed["means"], eager_grads["means"]) < 1e-5
    assert rel(replayed["viewmat"], eager_grads["viewmat"]) < 1e-5


def _small_motion(device: torch.device) -> torch.Tensor:
    """A camera motion [4, 4] of about 2 cm and 1 degree."""
    from pipeline.geometry import se3_exp

    return se3_exp(torch.tensor([0.01, -0.015, 0.005, 0.02, -0.01, 0.01], dtype=torch.float64)).float().to(device)


@pytest.mark.parametrize("images, capacity_share", [(1, 1.3), (2, 1.0), (2, 0.5)])
def test_the_cuda_intersection_kernel_gives_the_tensor_versions_list(images: int, capacity_share: float) -> None:
    """Our kernel (csrc/intersect_tiles.cu) against the tensor version: the same sorted keys and
    ids, with room to spare, exactly full, and overflowing."""
    from pipeline.render.intersect_kernel import intersect_kernel
    from pipeline.render.intersections import TileGrid, intersect_tiles

    device = torch.device("cuda")
    assert intersect_kernel(device) is not None, "the extension did not build (see the log)"
    generator = torch.Generator().manual_seed(images)
    n = 30_000
    means2d = (torch.rand(images, n, 2, generator=generator) * torch.tensor([700.0, 540.0]) - 30).to(device)
    radii = torch.randint(0, 40, (images, n, 2), generator=generator, dtype=torch.int32).to(device)
    depths = (torch.rand(images, n, generator=generator) * 5 + 0.1).to(device)
    grid = TileGrid(images, 640, 480)
    full = intersect_tiles(means2d, radii, depths, grid, 1 << 22, kernel=False)
    capacity = int(capacity_share * int(full.count))
    tensor = intersect_tiles(means2d, radii, depths, grid, capacity, kernel=False)
    cuda = intersect_tiles(means2d, radii, depths, grid, capacity, kernel=True)
    assert torch.equal(cuda.count, tensor.count)
    assert torch.equal(cuda.keys, tensor.keys) and torch.equal(cuda.flatten_ids, tensor.flatten_ids)
