"""Loop closure in the mapping side: candidates, their verification by dense alignment, the
keyframe pose graph (GTSAM) and moving the map with corrected keyframe poses."""
