"""Visual odometry beside SLAM: image features in the decode threads, then, in frame order in the
upload thread, each frame's motion since the frame before it (`slam/tracking/odometry.py`).

Tracking takes the motion as a guess where constant velocity is unreliable (`tracking.odometry`);
none of this waits for the GPU. A frame that brings a device's own pose (ARKit through NeRFCapture,
a bag's poses as the guess) needs none and gets none.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from pipeline.frame import Frame, ImageFeatures
from pipeline.slam.tracking.odometry import detector, extract_features, relative_motion
from pipeline.stages.upload import UploadedFrame


class FeatureDecode:
    """The source's `decode`, then the frame's image features (at most `max_features`)."""

    def __init__(self, decode: Callable[[Any], Frame | None], max_features: int) -> None:
        self.decode = decode
        self.max_features = max_features
        self._local = threading.local()  # a detector per decode thread

    def __call__(self, ref: Any) -> Frame | None:
        frame = self.decode(ref)
        if frame is None or frame.c2w_prior is not None:
            return frame
        orb = getattr(self._local, "orb", None)
        if orb is None:
            orb = self._local.orb = detector(self.max_features)
        frame.features = extract_features(orb, frame.color, frame.depth, frame.intrinsics)
        return frame


class OdometryUpload:
    """Each frame's motion since the frame before it (frames arrive in order, one thread), then
    `upload`. A frame whose motion is not found (too few features agree) has none; the next one
    is matched to it all the same, since the last frame seen is the likeliest to overlap."""

    def __init__(self, upload: Callable[[Frame], UploadedFrame], min_inliers: int) -> None:
        self.upload = upload
        self.min_inliers = min_inliers
        self._earlier: tuple[int, ImageFeatures, tuple[int, int]] | None = None  # index, features, (H, W)

    def __call__(self, frame: Frame) -> UploadedFrame:
        features, size = frame.features, (frame.height, frame.width)
        earlier = self._earlier
        if features is not None and earlier is not None and earlier[2] == size:
            frame.motion = relative_motion(
                earlier[1], features, frame.intrinsics, frame.width, self.min_inliers, since=earlier[0]
            )
        self._earlier = None if features is None else (frame.index, features, size)
        frame.features = None  # matched: the next stages have no use for them
        return self.upload(frame)
