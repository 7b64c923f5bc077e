"""SLAM's tracking side: the frontend that predicts, tracks and judges each frame's pose, and the
two tracking methods beneath it (`adam` by rendering loss, `align` by dense RGB-D alignment)."""
