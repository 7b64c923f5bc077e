"""The map moves with corrected keyframe poses: exactly by each creating keyframe's correction."""

from __future__ import annotations

import torch

from pipeline.geometry import pose_matrix, quat_to_rotmat
from pipeline.render.types import Gaussians
from pipeline.slam.loops.map_correction import move_map, quat_multiply


def random_pose(gen: torch.Generator) -> torch.Tensor:
    return pose_matrix(
        torch.randn(4, generator=gen, dtype=torch.float64), torch.randn(3, generator=gen, dtype=torch.float64)
    )


def random_map(count: int, gen: torch.Generator) -> Gaussians:
    return Gaussians(
        means=torch.randn(count, 3, generator=gen),
        quats=2 * torch.randn(count, 4, generator=gen),  # unnormalised, as mapping leaves them
        log_scales=torch.randn(count, 3, generator=gen),
        opacity_logits=torch.randn(count, generator=gen),
        colors=torch.rand(count, 3, generator=gen),
    )


def test_gaussians_move_exactly_with_their_keyframe_and_the_others_not_at_all() -> None:
    gen = torch.Generator().manual_seed(0)
    gaussians = random_map(60, gen)
    creator = torch.randint(-1, 3, (60,), generator=gen)  # keyframes 0, 1, 2 and none (-1)
    old = torch.stack([random_pose(gen) for _ in range(3)])
    new = old.clone()
    new[0], new[1] = random_pose(gen), random_pose(gen)  # keyframes 0 and 1 are corrected, 2 is not
    moved = move_map(gaussians, creator, old, new)

    for keyframe in (0, 1):
        correction = new[keyframe] @ torch.linalg.inv(old[keyframe])
        mine = creator == keyframe
        assert 0 < int(mine.sum()) < 60
        expected = gaussians.means[mine].double() @ correction[:3, :3].T + correction[:3, 3]
        torch.testing.assert_close(moved.means[mine].double(), expected, atol=1e-5, rtol=0)
        rotations = quat_to_rotmat(moved.quats[mine].double())
        turned = correction[:3, :3] @ quat_to_rotmat(gaussians.quats[mine].double())
        torch.testing.assert_close(rotations, turned, atol=1e-5, rtol=0)
        torch.testing.assert_close(moved.quats[mine].norm(dim=-1), gaussians.quats[mine].norm(dim=-1))

    still = (creator == 2) | (creator == -1)  # keyframe 2's, and those of no keyframe
    assert int((creator == -1).sum()) > 0 and int((creator == 2).sum()) > 0
    assert torch.equal(moved.means[still], gaussians.means[still])
    assert torch.equal(moved.quats[still], gaussians.quats[still])
    for name in ("log_scales", "opacity_logits", "colors"):
        assert getattr(moved, name) is getattr(gaussians, name)


def test_a_gaussian_rigidly_attached_to_its_camera_stays_where_the_camera_sees_it() -> None:
    """The point and axes of a Gaussian in its keyframe's camera frame are the same before and after."""
    gen = torch.Generator().manual_seed(1)
    gaussians = random_map(10, gen)
    old, new = random_pose(gen)[None], random_pose(gen)[None]
    moved = move_map(gaussians, torch.zeros(10, dtype=torch.long), old, new)
    in_camera_before = (gaussians.means.double() - old[0, :3, 3]) @ old[0, :3, :3]
    in_camera_after = (moved.means.double() - new[0, :3, 3]) @ new[0, :3, :3]
    torch.testing.assert_close(in_camera_after, in_camera_before, atol=1e-5, rtol=0)
    axes_before = old[0, :3, :3].T @ quat_to_rotmat(gaussians.quats.double())
    axes_after = new[0, :3, :3].T @ quat_to_rotmat(moved.quats.double())
    torch.testing.assert_close(axes_after, axes_before, atol=1e-5, rtol=0)


def test_quat_multiply_composes_rotations() -> None:
    gen = torch.Generator().manual_seed(2)
    a, b = torch.randn(5, 4, generator=gen, dtype=torch.float64), torch.randn(5, 4, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b))
