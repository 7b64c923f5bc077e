"""Sessions and a benchmark matrix on Ray: what sharing GPUs gives, on however many GPUs there are.

live: fake phones at --fps (one process each, the 256x192 room, looping) feed
`serve --ray`; first one session per GPU at 1 GPU each ("alone"), then two per GPU at 0.5
("shared"). For each session, over --seconds after --warmup: frames/s processed, frame age
(arrival to result, from the status endpoint every 0.5 s) and frames dropped.

matrix: the same bench matrix one cell after the other (`bench`), then through Ray at each
`--gpus-per-cell` share (`bench --ray`); the wall time of each whole matrix.

    python bench/ray_scale.py --out DIR [--parts live,matrix] [--seconds 60] [--fps 30]

Writes DIR/<stem>.json and DIR/<stem>.md (and each matrix's own JSON and table). `--phone
nerfcapture` (DDS, one domain per phone) needs no video codec: on the device machine its wheels
and Ray's fit one call (docs/cluster.md).
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

import ray
import torch

from pipeline.app.report import versions
from pipeline.io.files.atomic import atomic_write_text

PHONE_SIZE = ("--width", "256", "--height", "192")  # the iPhone LiDAR's depth resolution
POLL_S = 0.5
FIRST_DDS_DOMAIN = 100  # NeRFCapture phone i publishes on domain 100 + i


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def status(port: int) -> dict[str, Any] | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=2) as response:
            return json.loads(response.read())
    except OSError:
        return None


def pipeline_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "pipeline", *args]


def start_phones(
    kind: str, scene: Path, count: int, args: argparse.Namespace, logs: Path
) -> tuple[list[subprocess.Popen], list[str]]:
    """`count` fake phones streaming `scene` in a loop at --fps, one process each -> them, and the
    `serve` arguments naming them (Record3D: one port each; NeRFCapture: one DDS domain each)."""
    phones, sources = [], []
    for i in range(count):
        if kind == "record3d":
            port = free_port()
            command = pipeline_command("fake-record3d", "--port", str(port))
            sources += ["--record3d", f"http://127.0.0.1:{port}"]
        else:
            domain = str(FIRST_DDS_DOMAIN + i)
            command = pipeline_command("fake-nerfcapture", "--domain", domain, "--wait", str(args.start_timeout))
            sources += ["--nerfcapture", domain]
        command += ["--dataset", str(scene), "--fps", str(args.fps), "--loop", "--quiet"]
        with open(logs / f"phone_{i}.log", "w") as log:
            phones.append(subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT))
    time.sleep(3)  # the phones listen
    return phones, sources


def live_scenario(
    address: str, scene: Path, sessions: int, gpus_each: float, args: argparse.Namespace, work: Path
) -> dict[str, Any]:
    """`sessions` sessions at `gpus_each` GPUs, one phone each -> per-session frames/s, frame age, drops."""
    name = f"{sessions}x{gpus_each:g}gpu"
    logs = work / name
    logs.mkdir(parents=True, exist_ok=True)
    phones, sources = start_phones(args.phone, scene, sessions, args, logs)
    port = free_port()
    command = pipeline_command("serve", "--ray", address, "--gpus-per-session", f"{gpus_each:g}", "--quiet")
    command += sources
    command += ["--preset", args.preset, "--output", str(logs / "runs"), "--set", f"live.status_port={port}"]
    command += ["--set", "live.save_every_s=3600"]  # no periodic save inside the measured window
    with open(logs / "driver.log", "w") as log:
        driver = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    samples: list[dict[str, Any]] = []
    try:
        deadline = time.monotonic() + args.start_timeout
        while time.monotonic() < deadline:  # every session has mapped a frame: they are all warm from here
            board = status(port)
            if board and all((s.get("live") or {}).get("processed", 0) > 0 for s in board["sessions"]):
                break
            time.sleep(POLL_S)
        else:
            raise RuntimeError(f"{name}: sessions not all mapping after {args.start_timeout} s; see {logs}")
        time.sleep(args.warmup)
        end = time.monotonic() + args.seconds
        while time.monotonic() < end:
            board = status(port)
            if board:
                samples.append(
                    {"t": time.monotonic(), "sessions": {s["name"]: s.get("live") or {} for s in board["sessions"]}}
                )
            time.sleep(POLL_S)
    finally:
        driver.send_signal(signal.SIGINT)  # every session finishes its frame and saves
        try:
            driver.wait(timeout=300)
        except subprocess.TimeoutExpired:
            driver.kill()
        for phone in phones:
            phone.send_signal(signal.SIGINT)
            phone.wait(timeout=30)
    return {"scenario": name, "sessions": sessions, "gpus_per_session": gpus_each, "per_session": per_session(samples)}


def per_session(samples: list[dict[str, Any]]) -> list[dict[str, Any]]:
    first, last = samples[0], samples[-1]
    seconds = last["t"] - first["t"]
    out = []
    for name, end in last["sessions"].items():
        start = first["sessions"].get(name, {})
        ages = [s["sessions"].get(name, {}).get("frame_age_ms") or {} for s in samples]  # over its last frames
        out.append(
            {
                "session": name,
                "seconds": seconds,
                "fps_processed": (end.get("processed", 0) - start.get("processed", 0)) / seconds,
                "fps_received": (end.get("received", 0) - start.get("received", 0)) / seconds,
                "dropped": end.get("dropped", 0) - start.get("dropped", 0),
                "frame_age_ms_p50": _mean([a.get("result_p50") for a in ages]),
                "frame_age_ms_p95": _mean([a.get("result_p95") for a in ages]),
                "last_frame_ms": end.get("last_frame_ms"),
                "gaussians": end.get("gaussians"),
            }
        )
    return out


def _mean(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return statistics.fmean(known) if known else None


def matrix_run(extra: list[str], stem: str, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    command = pipeline_command("bench", *args.sequences, "--presets", args.presets, "--quiet")
    command += [arg for setting in args.matrix_set for arg in ("--set", setting)]
    command += ["--out", str(args.out), "--stem", stem, "--runs", str(work / stem), *extra]
    start = time.perf_counter()
    with open(work / f"{stem}.log", "w") as log:
        code = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - start
    report = json.loads((args.out / f"{stem}.json").read_text()) if code in (0, 1) else {}
    rows = report.get("rows", [])
    return {
        "run": stem,
        "command_wall_s": wall,
        "matrix_wall_s": report.get("wall_s"),
        "cells": len(rows),
        "failed": sum(bool(r.get("error")) for r in rows),
        "exit_code": code,
        "placements": sorted({f"{r.get('node')} / {r.get('gpu')}" for r in rows}),
    }


def markdown(result: dict[str, Any]) -> str:
    lines = [f"Device: {result['device']}; {result['gpus']} GPUs; versions {result['versions']}", ""]
    if result.get("live"):
        lines += [
            f"Live: fake {result['phone']} phones at {result['fps']:g} frames/s (256x192), preset {result['preset']}, "
            f"{result['seconds']:g} s measured after {result['warmup']:g} s warm-up.",
            "",
            "Frame age: arrival to result, the status endpoint's median and 95th percentile over each session's"
            " last frames, averaged over the samples taken every 0.5 s.",
            "",
            "| scenario | session | frames/s processed | frames/s received | dropped | frame age p50 ms | p95 ms | last frame ms |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for scenario in result["live"]:
            for s in scenario["per_session"]:
                lines.append(
                    f"| {scenario['scenario']} | {s['session']} | {s['fps_processed']:.1f} | {s['fps_received']:.1f} | "
                    f"{s['dropped']} | {_ms(s['frame_age_ms_p50'])} | {_ms(s['frame_age_ms_p95'])} | {_ms(s['last_frame_ms'])} |"
                )
        lines.append("")
    if result.get("matrix"):
        lines += [
            f"Matrix: {' '.join(result['sequences'])} x presets {result['presets']}.",
            "",
            "| run | cells | failed | matrix wall s | command wall s | ran on |",
            "|---|---|---|---|---|---|",
        ]
        for run in result["matrix"]:
            lines.append(
                f"| {run['run']} | {run['cells']} | {run['failed']} | {_ms(run['matrix_wall_s'])} | "
                f"{run['command_wall_s']:.1f} | {'; '.join(run['placements'])} |"
            )
    return "\n".join(lines) + "\n"


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--parts", default="live,matrix")
    parser.add_argument("--stem", default="ray_scale", help="file name stem of the JSON and table")
    parser.add_argument("--phone", choices=["record3d", "nerfcapture"], default="record3d", help="the fake phones")
    parser.add_argument("--preset", default="tiny", help="live sessions' preset")
    parser.add_argument("--fps", type=float, default=30.0, help="each phone's frame rate")
    parser.add_argument("--phone-frames", type=int, default=300, help="frames of the phones' looping scene")
    parser.add_argument("--seconds", type=float, default=60.0, help="measured window per live scenario")
    parser.add_argument("--warmup", type=float, default=10.0, help="after every session mapped its first frame")
    parser.add_argument("--start-timeout", type=float, default=180.0)
    parser.add_argument("--sequences", nargs="+", default=["synthetic", "synthetic-tum"])
    parser.add_argument("--presets", default="tiny", help="the matrix's presets")
    parser.add_argument("--gpus-per-cell", default="1,0.5", help="the Ray runs of the matrix, one per share")
    parser.add_argument("--matrix-set", action="append", default=[], metavar="KEY=VALUE", help="--set for every cell")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    parts = args.parts.split(",")
    work = Path(tempfile.mkdtemp(prefix="ray_scale_"))
    ray.init(include_dashboard=False)  # this machine's GPUs; the commands below join it by its address
    address = ray.get_runtime_context().gcs_address
    gpus = int(ray.cluster_resources().get("GPU", 0))
    result: dict[str, Any] = {
        "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "CPU",
        "gpus": gpus,
        "versions": versions(),
        "work": str(work),
    }
    try:
        if "live" in parts:
            scene = work / "phone_scene"
            synth = pipeline_command("synth", str(scene), *PHONE_SIZE, "--frames", str(args.phone_frames), "--quiet")
            subprocess.run(synth, check=True)
            per_gpu = max(gpus, 1)
            result.update(phone=args.phone, fps=args.fps, preset=args.preset, seconds=args.seconds, warmup=args.warmup)
            result["live"] = [
                live_scenario(address, scene, per_gpu, 1.0, args, work),  # one session per GPU, alone on it
                live_scenario(address, scene, 2 * per_gpu, 0.5, args, work),  # two per GPU
            ]
        if "matrix" in parts:
            result.update(sequences=args.sequences, presets=args.presets)
            runs = [matrix_run([], "matrix_sequential", args, work)]
            for share in args.gpus_per_cell.split(","):
                extra = ["--ray", address, "--gpus-per-cell", share]
                runs.append(matrix_run(extra, f"matrix_ray_{share}gpu", args, work))
            result["matrix"] = runs
    finally:
        ray.shutdown()
        atomic_write_text(args.out / f"{args.stem}.json", json.dumps(result, indent=2) + "\n")
        atomic_write_text(args.out / f"{args.stem}.md", markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
