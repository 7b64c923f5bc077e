"""A fake NeRFCapture phone: publishes a dataset on the `Frames` topic as the app would."""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace

import cv2
import numpy as np
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic

from pipeline.io.sources.datasets.base import Dataset
from pipeline.io.sources.live.nerfcapture import (
    DOMAIN_ID,
    TOPIC,
    SplatCaptureFrame,
    participant,
    reliable_qos,
    sample_from_frame,
)

log = logging.getLogger("gsplatam")

# ARKit's world origin is wherever the session started: a fixed, arbitrary offset of the
# dataset's first camera, which the receiver must remove by making poses relative.
ARKIT_WORLD = np.eye(4)
ARKIT_WORLD[:3, :3] = cv2.Rodrigues(np.array([0.1, -0.4, 0.2]))[0]
ARKIT_WORLD[:3, 3] = [0.5, 1.2, -0.3]


def publish_dataset(
    dataset: Dataset,
    fps: float,
    wait_for_reader_s: float = 30.0,
    stop: threading.Event | None = None,
    domain_id: int = DOMAIN_ID,
    loop: bool = False,
    pace: Callable[[int], None] | None = None,
) -> int:
    """Publish every frame of `dataset` at `fps` once a reader has matched (reliable QoS, no
    history: a late reader would miss frames), over and over with `loop` (ids and timestamps go
    on increasing, as the app's would); -> frames published. `pace`, when given, is called with
    the count published so far before each frame and returns when the next may go (a publisher
    held to its receiver's speed, as a test needs on a slow machine; `fps` stays the top rate)."""
    dp = participant(domain_id)
    writer = DataWriter(dp, Topic(dp, TOPIC, SplatCaptureFrame), qos=reliable_qos())
    stop = stop or threading.Event()
    deadline = time.monotonic() + wait_for_reader_s
    while not writer.get_matched_subscriptions():
        if time.monotonic() > deadline or stop.is_set():
            log.warning("fake-nerfcapture: no reader matched in %g s", wait_for_reader_s)
            return 0
        time.sleep(0.05)
    start = time.monotonic()
    count = 0
    for lap in itertools.count() if loop and len(dataset) else range(1):
        for ref in dataset.refs:
            if stop.wait(max(0.0, start + count / fps - time.monotonic())):
                return count
            if pace is not None:
                pace(count)
            frame = dataset.decode(ref)
            frame = replace(frame, timestamp=frame.timestamp + lap * len(dataset) / fps)  # the clock goes on
            c2w = frame.c2w_gt if frame.c2w_gt is not None else np.eye(4)
            writer.write(sample_from_frame(frame, count + 1, ARKIT_WORLD @ c2w))
            count += 1
    return count
