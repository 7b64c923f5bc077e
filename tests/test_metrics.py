"""Trajectory metrics on hand-made poses."""

from __future__ import annotations

import numpy as np

from pipeline.metrics import each_step_error, step_errors


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
