"""The daemon against the fake Record3D phone at camera rate: frame age, frames/s, drops, and
memory sampled through a long session (run on the device machine; needs the live extra).

The fake phone streams a generated room (looping) over real WebRTC on 127.0.0.1; `serve` runs
in a subprocess as a user would start it; its status endpoint is read every `--sample-s`;
`--disconnect-at` drops the phone's connection at those seconds (the daemon reconnects).
Writes live_latency_<W>x<H>_<seconds>s.json, the daemon's log and its frames.csv under --out.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

from pipeline.app.report import versions
from pipeline.config import DatasetConfig, SyntheticConfig
from pipeline.io.files.atomic import atomic_write_bytes, atomic_write_text
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic_writer import cached_synthetic
from pipeline.io.sources.live.fake_record3d import FakePhone


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def status(port: int) -> dict[str, Any] | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=2) as response:
            return json.loads(response.read())
    except OSError:
        return None


async def session(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    width, height = (int(v) for v in args.size.split("x"))
    scene = cached_synthetic(Path("/tmp/live_scene"), SyntheticConfig(frames=300, width=width, height=height), False)
    phone = FakePhone(open_dataset(DatasetConfig(path=str(scene))), fps=args.fps, loop=True)
    phone_port = await phone.start("127.0.0.1", 0)
    status_port = free_port()
    run_name = f"live_{args.size}_{args.seconds}s_{os.getpid()}"  # several runs of one size in one call
    command = [
        sys.executable, "-m", "pipeline", "serve", "--record3d", f"http://127.0.0.1:{phone_port}",
        "--preset", args.preset, "--output", "/tmp/live_runs", "--name", run_name,
        "--quiet", "--set", f"live.status_port={status_port}", *sum((["--set", s] for s in args.set), []),
    ]  # fmt: skip
    log = open(out / f"daemon_{args.size}_{args.seconds}s.log", "w")
    daemon = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    samples: list[dict[str, Any]] = []
    disconnects = sorted(args.disconnect_at)
    start = time.monotonic()
    try:
        while time.monotonic() - start < args.seconds and daemon.poll() is None:
            await asyncio.sleep(args.sample_s)
            if disconnects and time.monotonic() - start >= disconnects[0]:
                disconnects.pop(0)
                await phone.disconnect()  # the phone keeps moving until the daemon reconnects
            read = await asyncio.to_thread(status, status_port)
            samples.append({"t_s": time.monotonic() - start, "status": read})
    finally:
        daemon.send_signal(signal.SIGINT)
        code = await asyncio.to_thread(daemon.wait, 120)
        sent = phone.state.sent
        await phone.stop()
    folder = Path("/tmp/live_runs") / run_name
    metrics_path = next(folder.glob("**/metrics.json"), None) if folder.exists() else None
    metrics = json.loads(metrics_path.read_text()) if metrics_path else None
    if metrics_path is not None and (metrics_path.parent / "frames.csv").exists():
        frames = (metrics_path.parent / "frames.csv").read_bytes()
        atomic_write_bytes(out / f"frames_{args.size}_{args.seconds}s.csv", frames)
    answered = [s for s in samples if s["status"] is not None]
    memory = [s["status"].get("gpu_memory_gb") for s in answered if s["status"].get("gpu_memory_gb") is not None]
    return {
        "size": args.size, "fps_sent": args.fps, "seconds": args.seconds, "preset": args.preset, "set": args.set,
        "disconnect_at_s": args.disconnect_at,
        "exit_code": code, "frames_sent": sent, "status_samples": len(samples), "status_answered": len(answered),
        "gpu_memory_gb": memory, "metrics": metrics, "samples": samples,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", default="256x192")
    parser.add_argument("--seconds", type=int, default=60)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--sample-s", type=float, default=10.0)
    parser.add_argument("--set", action="append", default=[])
    parser.add_argument(
        "--disconnect-at", type=float, action="append", default=[], help="seconds: drop the phone's connection"
    )
    parser.add_argument("--out", default="bench/results")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = asyncio.run(session(args, out))
    result["versions"] = versions()
    metrics = result["metrics"] or {}
    print(json.dumps({k: result[k] for k in ("size", "exit_code", "frames_sent", "status_answered")}, indent=1))
    print("frame_age_ms", metrics.get("frame_age_ms"), "fps", (metrics.get("time") or {}).get("fps_steady"))
    print("gpu_memory_gb", result["gpu_memory_gb"])
    atomic_write_text(out / f"live_latency_{args.size}_{args.seconds}s.json", json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
