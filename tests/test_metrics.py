"""Trajectory metrics on hand-made poses."""

from __future__ import annotations

import numpy as np

from pipeline.metrics import absolute_trajectory_error, aligned_centre_errors, each_step_error, step_errors


def _walk(steps_m: list[float]) -> np.ndarray:
    """Camera-to-world poses [N, 4, 4] along x, `steps_m` apart."""
    poses = np.repeat(np.eye(4)[None], len(steps_m) + 1, axis=0)
    poses[:, 0, 3] = np.concatenate([[0.0], np.cumsum(steps_m)])
    return poses


def test_a_step_error_is_each_step_s_own_and_ignores_the_world_frame() -> None:
    reference = _walk([0.05, 0.05, 0.01, 0.05])
    world = np.array([[0.0, -1, 0, 2], [1, 0, 0, -1], [0, 0, 1, 0.5], [0, 0, 0, 1]])  # turned 90 degrees, moved
    estimated = world @ _walk([0.05, 0.03, 0.01, 0.05])  # in another world frame
    lengths, errors = each_step_error(estimated, reference)
    np.testing.assert_allclose(lengths, [0.05, 0.05, 0.01, 0.05], atol=1e-12)
    np.testing.assert_allclose(errors, [0.0, 0.02, 0.0, 0.0], atol=1e-12)  # the second step 2 cm short, once
    large = step_errors(estimated, reference, min_step_m=0.03)
    assert large.steps == 3 and np.isclose(large.max_m, 0.02) and np.isclose(large.mean_m, 0.02 / 3)
    assert step_errors(estimated, reference, min_step_m=0.1).steps == 0


def test_aligned_centre_errors_are_each_frame_s_own_in_the_reference_frame() -> None:
    """One frame 4 cm off along y among many right ones, the estimate in another world frame: the
    alignment puts it back, and that frame alone carries (nearly all of) the error."""
    reference = _walk([0.05] * 20)
    off = reference.copy()
    off[10, 1, 3] += 0.04
    world = np.array([[0.0, -1, 0, 2], [1, 0, 0, -1], [0, 0, 1, 0.5], [0, 0, 0, 1]])
    errors = aligned_centre_errors(world @ off, reference)
    norms = np.linalg.norm(errors, axis=1)
    assert errors.shape == (21, 3) and int(np.argmax(norms)) == 10 and 0.035 < norms[10] < 0.04
    assert np.all(np.delete(norms, 10) < 0.005)
    ate = absolute_trajectory_error(world @ off, reference)
    assert np.isclose(ate.rmse_m, np.sqrt(np.mean(norms**2)))
