"""SLAM frame time with the web viewer open against without it, in one invocation.

The same config runs twice (viewer off, then on) on the embedded synthetic room. With the
viewer on, one client is connected for the whole run: a websocket client speaking viser's
protocol that receives every message a browser would (map, images, trajectory), so the server
side does all its work; drawing happens in a browser on another machine in real use.

    python bench/viewer_overhead.py --out bench/results [--preset tiny] [--frames 200]
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from pipeline.config import load_config, with_value
from pipeline.run import run_slam, versions


class ViserClient(threading.Thread):
    """Connects to the viewer once it listens and reads every message until the server closes."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.messages = 0
        self.bytes = 0
        self.connected = threading.Event()

    def run(self) -> None:
        import viser
        from websockets.sync.client import connect

        while True:
            try:
                socket = connect(
                    f"ws://127.0.0.1:{self.port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None
                )  # a map of 1M Gaussians is a 32 MB message
                break
            except OSError:
                time.sleep(0.05)
        self.connected.set()
        try:
            for message in socket:
                self.messages += 1
                self.bytes += len(message)
        except Exception:  # the server closing at the end of the run
            pass


def run_once(config: Any, name: str, port: int | None) -> dict[str, Any]:
    client = None
    if port is not None:
        config = replace(config, viewer=replace(config.viewer, enabled=True, port=port))
        client = ViserClient(port)
        client.start()
    result = run_slam(replace(config, run=replace(config.run, name=name)), progress=False)
    assert result.metrics is not None
    t = result.metrics["time"]
    row = {
        "viewer": port is not None,
        "frames": result.metrics["frames"],
        "total_ms": 1000 * t["total_s"],
        "tracking_ms": 1000 * t["tracking_s"],
        "mapping_ms": 1000 * t["mapping_s"],
        "fps_steady": t["fps_steady"],
        "ate_cm": result.metrics["ate"]["rmse_cm"] if result.metrics["ate"] else None,
        "gaussians": result.metrics["gaussians"],
    }
    if client is not None:
        row.update(client_connected=client.connected.is_set(), messages=client.messages, megabytes=client.bytes / 1e6)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--port", type=int, default=8095)
    parser.add_argument("--runs", default="/tmp/viewer_runs")
    args = parser.parse_args()
    config = load_config(args.preset, overrides=[f"synthetic.frames={args.frames}"])
    config = with_value(config, "run.output", args.runs)
    rows = [run_once(config, "without_viewer", None), run_once(config, "with_viewer", args.port)]
    for row in rows:
        print(row)
    ratio = rows[1]["total_ms"] / rows[0]["total_ms"]
    fps_ratio = rows[0]["fps_steady"] / rows[1]["fps_steady"]
    report = {"rows": rows, "slowdown_total_ms": ratio, "slowdown_wall": fps_ratio, "versions": versions()}
    out = Path(args.out)
    (out / "viewer.json").write_text(json.dumps(report, indent=2) + "\n")
    import torch

    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "CPU"
    lines = [
        "# Viewer overhead",
        "",
        f"{gpu}, torch {torch.__version__}, gsplat {report['versions'].get('gsplat')}, commit "
        f"{report['versions'].get('commit')}. Preset {args.preset}, synthetic room, {args.frames} frames, "
        "both runs in one invocation; with the viewer, one websocket client receives everything a browser would "
        f"(viewer.max_hz = {config.viewer.max_hz:g} snapshots per second). Means exclude the 2 warm-up frames.",
        "",
        "| viewer | ms/frame (SLAM step) | tracking | mapping | frames/s after warm-up | ATE RMSE | messages | MB sent |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {'on, 1 client' if r['viewer'] else 'off'} | {r['total_ms']:.1f} | {r['tracking_ms']:.1f} | "
            f"{r['mapping_ms']:.1f} | {r['fps_steady']:.2f} | {r['ate_cm']:.2f} cm | {r.get('messages', '')} | "
            f"{r.get('megabytes', 0):.1f} |"
        )
    lines += [
        "",
        f"Slowdown with the viewer: {100 * (ratio - 1):+.1f}% per SLAM step, {100 * (fps_ratio - 1):+.1f}% wall.",
    ]
    (out / "viewer.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
