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

from pipeline.app.report import versions
from pipeline.app.run import run_slam
from pipeline.config import load_config, with_value
from pipeline.devices import resolve_device
from pipeline.io.files.atomic import atomic_write_text


class ViserClient(threading.Thread):
    """Connects to the viewer once it listens and reads every message until the server closes."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.messages = 0
        self.bytes = 0
        self.connected = threading.Event()

    def run(self) -> None:
        import msgspec
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
        # A browser reports its camera first; viser counts it as a client from then on.
        camera = {
            "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.0, 0.0], "fov": 1.0,
            "near": 0.01, "far": 100.0, "image_height": 720, "image_width": 1280, "look_at": [0.0, 0.0, 1.0],
            "up_direction": [0.0, -1.0, 0.0],
        }  # fmt: skip
        socket.send(msgspec.msgpack.encode(camera))
        self.connected.set()
        try:
            for message in socket:
                self.messages += 1
                self.bytes += len(message)
        except Exception:  # the server closing at the end of the run
            pass


def run_once(config: Any, name: str, port: int | None, map_every_s: float = 0.0) -> dict[str, Any]:
    client = None
    if port is not None:
        config = replace(config, viewer=replace(config.viewer, enabled=True, port=port, map_every_s=map_every_s))
        client = ViserClient(port)
        client.start()
    named = replace(config, run=replace(config.run, name=name))
    result = run_slam(named, resolve_device(config.run.device), progress=False, overwrite=True)
    assert result.metrics is not None and result.metrics.time is not None
    t = result.metrics.time
    row = {
        "viewer": port is not None,
        "map_every_s": map_every_s,
        "frames": result.metrics.frames,
        "total_ms": 1000 * t.total_s,
        "tracking_ms": 1000 * t.tracking_s,
        "mapping_ms": 1000 * t.mapping_s,
        "fps_steady": t.fps_steady,
        "ate_cm": result.metrics.ate.rmse_cm if result.metrics.ate else None,
        "gaussians": result.metrics.gaussians,
    }
    if client is not None:
        row.update(client_connected=client.connected.is_set(), messages=client.messages, megabytes=client.bytes / 1e6)
    return row


def _label(row: dict[str, Any]) -> str:
    return f"on, 1 client, map every {row['map_every_s']:g} s" if row["viewer"] else "off"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--port", type=int, default=8095)
    parser.add_argument("--runs", default="/tmp/viewer_runs")
    parser.add_argument("--map-every", default="5,1", help="viewer.map_every_s values to measure, comma-separated")
    args = parser.parse_args()
    config = load_config(args.preset, overrides=[f"synthetic.frames={args.frames}"])
    config = with_value(config, "run.output", args.runs)
    rows = [run_once(config, "without_viewer", None)]
    for k, every in enumerate(float(v) for v in args.map_every.split(",")):
        rows.append(run_once(config, f"with_viewer_map_{every:g}s", args.port + k, every))
    for row in rows:
        row["slowdown_step"] = row["total_ms"] / rows[0]["total_ms"] - 1
        row["slowdown_wall"] = rows[0]["fps_steady"] / row["fps_steady"] - 1
        print(row)
    report = {"rows": rows, "versions": versions()}
    out = Path(args.out)
    atomic_write_text(out / "viewer.json", json.dumps(report, indent=2) + "\n")
    import torch

    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "CPU"
    lines = [
        "# Viewer overhead",
        "",
        f"{gpu}, torch {torch.__version__}, gsplat {report['versions'].get('gsplat')}, commit "
        f"{report['versions'].get('commit')}. Preset {args.preset}, synthetic room, {args.frames} frames, "
        "all runs in one invocation; with the viewer, one websocket client (it reports a camera, as a browser does, "
        "and receives every message a browser would); stats, images and camera once a second (viewer.max_hz), "
        "the whole map at most every viewer.map_every_s (default 5 s). "
        "Means exclude the 2 warm-up frames.",
        "",
        "| viewer | ms/frame (SLAM step) | vs off | tracking | mapping | frames/s after warm-up | vs off "
        "| ATE RMSE | messages | MB received |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {_label(r)} | {r['total_ms']:.1f} | {100 * r['slowdown_step']:+.1f}% | {r['tracking_ms']:.1f} "
            f"| {r['mapping_ms']:.1f} | {r['fps_steady']:.2f} | {100 * r['slowdown_wall']:+.1f}% | {r['ate_cm']:.2f} cm "
            f"| {r.get('messages', '')} | {r.get('megabytes', 0):.1f} |"
        )
    atomic_write_text(out / "viewer.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
