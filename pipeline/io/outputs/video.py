"""An MP4 of rendered frames, encoded by PyAV (the 'live' extra): H.264 where the FFmpeg it
brings has an H.264 encoder, else MPEG-4 part 2."""

from __future__ import annotations

from collections.abc import Iterable
from fractions import Fraction
from pathlib import Path

import numpy as np

from pipeline.io.files.atomic import atomic_export

CODECS = ("libx264", "mpeg4")  # the first this FFmpeg encodes with


def write_mp4(path: Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Encode `frames` ([H, W, 3] uint8 RGB, one size; an odd width or height loses its last
    column or row: yuv420p halves both) at `fps` frames per second into `path`, which appears
    whole or not at all. -> frames written."""
    import av

    codec = next(name for name in CODECS if _encodes(name))
    written = 0

    def encode(staged: Path) -> None:
        nonlocal written
        with av.open(str(staged), mode="w", format="mp4") as container:
            stream: av.VideoStream | None = None
            for frame in frames:
                even = frame[: frame.shape[0] // 2 * 2, : frame.shape[1] // 2 * 2]
                if stream is None:
                    added = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001))
                    assert isinstance(added, av.VideoStream)
                    stream = added
                    stream.width, stream.height, stream.pix_fmt = even.shape[1], even.shape[0], "yuv420p"
                for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(even), format="rgb24")):
                    container.mux(packet)
                written += 1
            if stream is not None:
                for packet in stream.encode():  # flush the encoder
                    container.mux(packet)

    atomic_export(path, encode)
    return written


def _encodes(name: str) -> bool:
    import av

    try:
        av.codec.Codec(name, "w")
    except Exception:  # av's own error type for an encoder its FFmpeg lacks
        return False
    return True
