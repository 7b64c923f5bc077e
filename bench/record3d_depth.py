"""Depth error of the Record3D path through the real aiortc H.264 loopback.

The fake phone streams a synthetic room (exact depth) on 127.0.0.1; the receiver decodes and
masks the hue depth exactly as `serve` does; errors are taken over pixels valid on both sides.

    python bench/record3d_depth.py --out bench/results
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import tempfile
from pathlib import Path

import aiortc
import av
import numpy as np

from pipeline.app.report import versions
from pipeline.config import DatasetConfig, LiveConfig, SyntheticConfig
from pipeline.frame import Frame
from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.sources.datasets.base import Dataset
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.io.sources.live.fake_record3d import FakePhone
from pipeline.io.sources.live.record3d import Record3DPacket, Record3DSession, Record3DSource, StreamEnded
from pipeline.io.sources.live.record3d_format import DEPTH_VALID_M


def _nearest_sent(dataset: Dataset, color: np.ndarray, guess: int) -> Frame:
    """The sent frame whose colour is closest to the received one, near `guess` (a lost packet
    shifts the count)."""
    candidates = [dataset.decode(dataset.refs[i]) for i in range(max(0, guess - 3), min(len(dataset), guess + 4))]
    return min(candidates, key=lambda f: np.abs(f.color.astype(np.int16) - color).mean())


async def measure(dataset: Dataset, fps: float) -> dict[str, float]:
    phone = FakePhone(dataset, fps=fps)
    port = await phone.start("127.0.0.1", 0)
    url = f"http://127.0.0.1:{port}"
    session = Record3DSession(url, LiveConfig())
    decoder = Record3DSource(url, LiveConfig())
    errors, kept = [], []
    try:
        await session.open()
        async for image in session.frames():
            frame = decoder.decode(Record3DPacket(len(kept), 0.0, image, session.metadata))
            if frame is None:
                continue
            sent = _nearest_sent(dataset, frame.color, len(kept))
            sendable = (sent.depth >= DEPTH_VALID_M[0]) & (sent.depth < DEPTH_VALID_M[1])
            valid = (frame.depth > 0) & sendable
            errors.append(np.abs(frame.depth[valid] - sent.depth[valid]))
            kept.append(valid.sum() / max(sendable.sum(), 1))
    except StreamEnded:
        pass  # the fake phone reached the end of the dataset
    finally:
        await session.close()
        await phone.stop()
    error = np.concatenate(errors)
    return {
        "frames_received": len(errors),
        "frames_sent": phone.state.sent,
        "median_mm": float(1000 * np.median(error)),
        "p95_mm": float(1000 * np.percentile(error, 95)),
        "mean_mm": float(1000 * error.mean()),
        "kept_fraction": float(np.mean(kept)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--sizes", default="256x192,640x480", help="colour (= depth) sizes, WxH")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes.split(","):
            width, height = (int(v) for v in size.split("x"))
            path = Path(tmp) / size
            write_synthetic(path, SyntheticConfig(frames=args.frames, width=width, height=height), progress=False)
            result = asyncio.run(measure(open_dataset(DatasetConfig(path=str(path))), 30.0))
            rows.append({"size": size, **result})
            print(rows[-1])
    report = {"rows": rows, "versions": {**versions(), "aiortc": aiortc.__version__, "av": av.__version__}}
    report["machine"] = f"{platform.machine()} CPU (codec runs on the CPU)"
    out = Path(args.out)
    atomic_write_text(out / "record3d_depth.json", json.dumps(report, indent=2) + "\n")
    lines = [
        "# Record3D depth through the aiortc H.264 loopback",
        "",
        f"Synthetic room, {args.frames} frames at 30 fps per size, fake phone -> receiver on 127.0.0.1, "
        f"aiortc {aiortc.__version__}, PyAV {av.__version__}, commit {report['versions']['commit']}. "
        "Errors over pixels valid in both the sent depth (0.1-2.8 m) and the received, masked depth; "
        "'kept' is the fraction of sendable pixels that survive decoding and masks (seam, edges, holes' borders).",
        "",
        "| size (per half) | frames received / sent | median | p95 | mean | kept |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['size']} | {r['frames_received']} / {r['frames_sent']} | {r['median_mm']:.1f} mm | {r['p95_mm']:.1f} mm | "
            f"{r['mean_mm']:.1f} mm | {r['kept_fraction']:.1%} |"
        )
    atomic_write_text(out / "record3d_depth.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
