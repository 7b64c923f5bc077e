"""The trajectory apart from tracking: what a checkpoint keeps of it, and what a resume restores."""

from __future__ import annotations

import torch

from pipeline.slam.keyframes import KeyframePose
from pipeline.slam.tracking.trajectory import TrackingState, Trajectory

CPU = torch.device("cpu")


def shifted(x: float) -> torch.Tensor:
    pose = torch.eye(4)
    pose[0, 3] = x
    return pose


def test_a_saved_trajectory_restores_its_poses_states_and_last_good_frame() -> None:
    """Frames 0-3 tracked, 2 lost, 3 relocalised (each with a device pose prior); saved as of
    frame 3 with keyframe 0 moved: the saved poses follow it, the poses as tracked stay; restored,
    the states, the last good frame and its prior come back, and `follow` anchors the frames."""
    trajectory = Trajectory(CPU)
    states = [TrackingState.TRACKED, TrackingState.TRACKED, TrackingState.LOST, TrackingState.RELOCALISED]
    anchor = KeyframePose(0, shifted(0.0), 0)
    for i, state in enumerate(states):
        trajectory.append(shifted(0.1 * i), None if i == 0 else anchor, i / 30, state, shifted(1.0 + i))
    assert trajectory.last_good == 3 and trajectory.lost_in_row == 0
    assert trajectory.last_prior is not None and torch.equal(trajectory.last_prior, shifted(4.0))

    moved = KeyframePose(0, shifted(0.5), 0)
    saved = trajectory.state(3, shifted(2.0), [moved], [0.1, 0.2])
    assert saved.lost_frames == [2] and saved.relocalised_frames == [] and saved.frames_done == 3
    torch.testing.assert_close(saved.poses, torch.stack([shifted(0.5), shifted(0.6), shifted(0.7)]))
    assert saved.tracked_poses is not None
    torch.testing.assert_close(saved.tracked_poses, torch.stack([shifted(0.0), shifted(0.1), shifted(0.2)]))

    restored = Trajectory.restored(trajectory.state(4, shifted(4.0), [], []), CPU)
    assert restored.states == states and restored.last_good == 3 and len(restored) == 4
    assert restored.last_prior is not None and torch.equal(restored.last_prior, shifted(4.0))
    assert restored.anchors == [None] * 4 and restored.timestamps == [None] * 4
    restored.follow([KeyframePose(2, shifted(0.2), 2)])
    assert restored.anchors[:2] == [None, None] and all(a is not None and a.position == 2 for a in restored.anchors[2:])
