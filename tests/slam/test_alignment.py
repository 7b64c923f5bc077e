"""The dense RGB-D alignment's maths: the se(3) exponential, the analytic Jacobians, the pyramid."""

from __future__ import annotations

import math

import pytest
import torch

from pipeline.errors import UserError
from pipeline.geometry import se3_exp, skew
from pipeline.slam.tracking.pyramid import check_pyramid_fits, halve_depth, halve_intrinsics, rgbd_pyramid
from pipeline.slam.tracking.rgbd_alignment import (
    damped_step,
    photometric_jacobian,
    point_to_plane_jacobian,
    project_points,
    sample_bilinear,
    solve_positive_definite,
)

F64 = torch.float64


def twist_matrix(twist: torch.Tensor) -> torch.Tensor:
    """The [4, 4] element of se(3) whose matrix exponential is se3_exp(twist)."""
    m = torch.zeros(4, 4, dtype=twist.dtype)
    m[:3, :3] = skew(twist[:3])
    m[:3, 3] = twist[3:]
    return m


@pytest.mark.parametrize("angle", [0.0, 1e-5, 1e-3, 0.3, 2.5])
def test_se3_exp_is_the_matrix_exponential(angle: float) -> None:
    gen = torch.Generator().manual_seed(1)
    axis = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=F64), dim=0)
    twist = torch.cat([axis * angle, torch.randn(3, generator=gen, dtype=F64)])
    torch.testing.assert_close(se3_exp(twist), torch.linalg.matrix_exp(twist_matrix(twist)), atol=1e-12, rtol=0)


def _random_points(count: int, gen: torch.Generator) -> torch.Tensor:
    """Points [count, 3] in front of a camera, 1 to 3 m away."""
    xy = torch.rand(count, 2, generator=gen, dtype=F64) - 0.5
    z = 1 + 2 * torch.rand(count, 1, generator=gen, dtype=F64)
    return torch.cat([xy * z, z], dim=1)


def _finite_differences(residual, count: int, step: float = 1e-6) -> torch.Tensor:
    """d residual(exp(xi) ...) / d xi at 0 by central differences -> [count, 6]."""
    columns = []
    for k in range(6):
        xi = torch.zeros(6, dtype=F64)
        xi[k] = step
        columns.append((residual(se3_exp(xi)) - residual(se3_exp(-xi))) / (2 * step))
    return torch.stack(columns, dim=1)


def test_point_to_plane_jacobian_matches_finite_differences() -> None:
    gen = torch.Generator().manual_seed(2)
    points = _random_points(50, gen)
    normals = torch.nn.functional.normalize(torch.randn(50, 3, generator=gen, dtype=F64), dim=1)
    anchors = points + 0.05 * torch.randn(50, 3, generator=gen, dtype=F64)  # q: the target's vertices

    def residual(motion: torch.Tensor) -> torch.Tensor:
        moved = points @ motion[:3, :3].T + motion[:3, 3]
        return ((moved - anchors) * normals).sum(-1)

    torch.testing.assert_close(point_to_plane_jacobian(points, normals), _finite_differences(residual, 50))


def test_photometric_jacobian_matches_finite_differences() -> None:
    """Against a smooth image whose gradient is known exactly: I(u, v) = sin(u / 7) cos(v / 5)."""
    gen = torch.Generator().manual_seed(3)
    points = _random_points(50, gen)
    intrinsics = torch.tensor([[300.0, 0.0, 160.0], [0.0, 280.0, 120.0], [0.0, 0.0, 1.0]], dtype=F64)

    def image(uv: torch.Tensor) -> torch.Tensor:
        return torch.sin(uv[:, 0] / 7) * torch.cos(uv[:, 1] / 5)

    def residual(motion: torch.Tensor) -> torch.Tensor:
        return image(project_points(points @ motion[:3, :3].T + motion[:3, 3], intrinsics))

    uv = project_points(points, intrinsics)
    gradients = torch.stack(
        [torch.cos(uv[:, 0] / 7) * torch.cos(uv[:, 1] / 5) / 7, -torch.sin(uv[:, 0] / 7) * torch.sin(uv[:, 1] / 5) / 5],
        dim=1,
    )
    analytic = photometric_jacobian(points, gradients, intrinsics)
    torch.testing.assert_close(analytic, _finite_differences(residual, 50), rtol=1e-5, atol=1e-7)


def test_bilinear_sampling_uses_the_pixel_centre_convention() -> None:
    """Pixel (u, v) is centred at (u + 0.5, v + 0.5): a linear map is reproduced exactly inside."""
    v, u = torch.meshgrid(torch.arange(6.0) + 0.5, torch.arange(8.0) + 0.5, indexing="ij")
    maps = torch.stack([u, 2 * v + 1])  # [2, 6, 8]
    uv = torch.tensor([[0.5, 0.5], [3.2, 4.7], [7.5, 5.5], [4.0, 1.0]])
    torch.testing.assert_close(sample_bilinear(maps, uv), torch.stack([uv[:, 0], 2 * uv[:, 1] + 1], dim=1))
    assert sample_bilinear(maps, torch.tensor([[-3.0, 2.0]])).abs().max() == 0  # outside: zero


def test_halved_intrinsics_project_to_halved_pixel_coordinates() -> None:
    gen = torch.Generator().manual_seed(4)
    points = _random_points(20, gen).float()
    intrinsics = torch.tensor([[300.0, 0.0, 160.0], [0.0, 280.0, 120.0], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(
        project_points(points, halve_intrinsics(intrinsics)), project_points(points, intrinsics) / 2
    )


def test_halving_depth_averages_valid_pixels_and_drops_depth_edges() -> None:
    depth = torch.tensor(
        [
            [2.00, 2.02, 1.00, 3.00, 0.00, 0.00],
            [2.04, 2.02, 1.00, 3.00, 0.00, 1.50],
        ]
    )
    halved = halve_depth(depth, focal=torch.tensor(100.0))
    # block 0: one surface (spread 4 cm < 6 footprints of 2 cm); block 1: 1 m against 3 m, an edge;
    # block 2: the single valid pixel
    torch.testing.assert_close(halved, torch.tensor([[2.02, 0.0, 1.5]]))


def test_pyramid_levels_and_their_limit() -> None:
    gray, depth = torch.rand(48, 64), torch.ones(48, 64)
    intrinsics = torch.tensor([[40.0, 0.0, 32.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]])
    levels = rgbd_pyramid(gray, depth, intrinsics, 3)
    assert [tuple(level.depth.shape) for level in levels] == [(48, 64), (24, 32), (12, 16)]
    torch.testing.assert_close(levels[1].intensity[0, 0], gray[:2, :2].mean())
    check_pyramid_fits(3, 48, 64)
    with pytest.raises(UserError, match="tracking.align_iters asks for 5 pyramid levels: a 64x48 frame"):
        check_pyramid_fits(5, 48, 64)


def test_damped_step_solves_the_normal_equations_and_never_returns_nan() -> None:
    gen = torch.Generator().manual_seed(5)
    rows = torch.randn(40, 6, generator=gen, dtype=F64)
    hessian, gradient = rows.T @ rows, torch.randn(6, generator=gen, dtype=F64)
    tiny = torch.tensor(1e-12, dtype=F64)
    step = damped_step(hessian, gradient, tiny)
    torch.testing.assert_close(hessian @ step, -gradient, rtol=0, atol=1e-2 * gradient.abs().max().item())
    no_data = torch.zeros(6, dtype=F64)
    assert damped_step(torch.zeros(6, 6, dtype=F64), no_data, tiny).abs().max() == 0
    assert damped_step(torch.full((6, 6), math.nan, dtype=F64), gradient, tiny).abs().max() == 0


def test_the_written_out_solve_equals_torch_linalg_and_flags_an_indefinite_system() -> None:
    gen = torch.Generator().manual_seed(6)
    rows = torch.randn(9, 40, 6, generator=gen, dtype=F64)
    systems, rhs = rows.mT @ rows, torch.randn(9, 6, generator=gen, dtype=F64)
    solved, factored = torch.vmap(solve_positive_definite)(systems, rhs)  # as under `batched`
    torch.testing.assert_close(solved, torch.linalg.solve(systems, rhs), rtol=1e-10, atol=1e-12)
    assert bool(factored.all())
    indefinite = torch.diag(torch.tensor([1.0, 2.0, -1.0, 3.0, 1.0, 1.0], dtype=F64))
    assert not bool(solve_positive_definite(indefinite, rhs[0])[1])
