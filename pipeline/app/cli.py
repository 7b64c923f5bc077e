"""The `gsplatam` command line (also `python -m pipeline`)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from pipeline.app.logs import configure_logging
from pipeline.errors import StageFailure, UserError

if TYPE_CHECKING:  # the commands import what they need when they run: --help stays fast
    from pipeline.config import Config
    from pipeline.io.datasets.base import Dataset

log = logging.getLogger("gsplatam")


class Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _add_config_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--preset", help="tiny, small, base or tum (default: base on a GPU, tiny on the CPU and for live input)"
    )
    parser.add_argument("--config", metavar="FILE", help="TOML file of settings (applied after the preset)")
    parser.add_argument(
        "--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[],
        help="override one setting, e.g. --set tracking.iters=20 (repeatable)",
    )  # fmt: skip
    parser.add_argument("--output", metavar="DIR", help="where run folders go (default: outputs)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], help="compute device (default: auto)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _add_viewer_options(parser: argparse.ArgumentParser, always: bool = False) -> None:
    if not always:
        parser.add_argument("--viewer", action="store_true", help="watch it in the browser (viser)")
    parser.add_argument("--viewer-port", type=int, help="viewer port (default: 8080)")
    parser.add_argument("--viewer-host", help="viewer address (default: 127.0.0.1; 0.0.0.0 exposes it)")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="gsplatam", description="Real-time RGB-D SLAM with Gaussian splatting (SplaTAM on gsplat).")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)

    run = sub.add_parser("run", help="SLAM on a dataset (default: a generated synthetic room)")
    run.add_argument(
        "dataset", nargs="?",
        help="dataset folder, Replica or TUM layout (default: synthetic room); or live, without recording: "
        "record3d:URL or nerfcapture:",
    )  # fmt: skip
    _add_config_options(run)
    run.add_argument("--name", help="run folder name under --output")
    run.add_argument("--resume", metavar="RUN_DIR", help="continue the run in RUN_DIR from its checkpoint")
    run.add_argument("--loader", choices=["pipelined", "sync"], help="asyncio pipeline (default) or a plain loop")
    run.add_argument("--profile", action="store_true", help="write a torch-profiler trace into the run folder")
    _add_viewer_options(run)

    synth = sub.add_parser("synth", help="write a synthetic RGB-D sequence with exact poses")
    synth.add_argument("out", help="output folder")
    synth.add_argument("--layout", choices=["replica", "tum"], default="replica")
    synth.add_argument("--frames", type=int, default=200)
    synth.add_argument("--width", type=int, default=1200)
    synth.add_argument("--height", type=int, default=680)
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument("--speed", type=float, default=0.3, help="camera speed, m/s")
    synth.add_argument("--jitter", type=float, default=0.01, help="hand-held shake, metres")
    synth.add_argument("--fps", type=float, default=30.0)
    synth.add_argument("--depth-noise", type=float, default=0.0, help="TUM only: depth noise std = k x depth^2")
    synth.add_argument("--holes", type=float, default=0.0, help="TUM only: fraction of depth pixels zeroed")
    synth.add_argument("--time-jitter", type=float, default=0.0, help="TUM only: depth/pose timestamp offsets, s")
    synth.add_argument("--quiet", action="store_true")

    bench = sub.add_parser("bench", help="benchmark matrix: presets x sequences (x ablations), JSON and a table")
    bench.add_argument("sequences", nargs="*", help="dataset folders (default: the synthetic room)")
    bench.add_argument("--presets", default="tiny", help="comma-separated presets (default: tiny)")
    bench.add_argument("--ablations", action="store_true", help="also run each side-by-side switch")
    bench.add_argument("--variants", help="comma-separated variants instead of --ablations' full set")
    bench.add_argument("--out", default="bench/results", help="where the JSON and table go")
    bench.add_argument("--stem", default="bench", help="file name stem of the JSON and table")
    bench.add_argument("--runs", default="outputs/bench", help="where the run folders go")
    bench.add_argument("--profile", action="store_true", help="profile every cell (trace and summary per run folder)")
    bench.add_argument(
        "--set", dest="overrides", metavar="KEY=VALUE", action="append", default=[], help="applied to every cell"
    )
    bench.add_argument(
        "--ray", nargs="?", const="", metavar="ADDRESS",
        help="each cell a Ray task, on the cluster at ADDRESS (host:port, or auto) or, without one, a local cluster",
    )  # fmt: skip
    bench.add_argument(
        "--gpus-per-cell", type=float, default=1.0, help="with --ray: GPUs each cell declares (fractions share one)"
    )
    bench.add_argument("--quiet", action="store_true")
    serve = sub.add_parser("serve", help="live daemon: reconstruct from a phone's stream until Ctrl-C")
    serve.add_argument(
        "--record3d", metavar="URL", action="append", default=[],
        help="Record3D app's Wi-Fi stream, e.g. http://192.168.1.20 (repeatable with --ray)",
    )  # fmt: skip
    serve.add_argument(
        "--nerfcapture", metavar="DOMAIN", nargs="?", const="", action="append", default=[],
        help="NeRFCapture app over DDS (topic Frames, domain live.dds_domain: 0, or DOMAIN; repeatable with --ray, "
        "a domain each); its pose per --set live.device_pose=...",
    )  # fmt: skip
    serve.add_argument(
        "--ray", nargs="?", const="", metavar="ADDRESS",
        help="every source a session on the Ray cluster at ADDRESS (host:port, or auto) or, without one, a local cluster",
    )  # fmt: skip
    serve.add_argument(
        "--gpus-per-session",
        type=float,
        default=1.0,
        help="with --ray: GPUs each session declares (fractions share one)",
    )
    _add_config_options(serve)
    serve.add_argument("--name", help="run folder name under --output (default: live_<source>_<preset>)")
    _add_viewer_options(serve)

    fake = sub.add_parser("fake-record3d", help="a fake Record3D phone streaming a dataset (for tests and demos)")
    fake.add_argument("--dataset", help="dataset folder (default: the generated synthetic room)")
    fake.add_argument("--host", default="127.0.0.1", help="address to serve on (default: 127.0.0.1)")
    fake.add_argument("--port", type=int, default=8000, help="HTTP port (the real app uses 80)")
    fake.add_argument("--fps", type=float, default=30.0, help="frame rate of the stream")
    fake.add_argument("--loop", action="store_true", help="start over at the end instead of ending the stream")
    fake.add_argument("--output", default="outputs", help="where the generated synthetic room is cached")
    fake.add_argument("--quiet", action="store_true")
    fake_nc = sub.add_parser("fake-nerfcapture", help="publish a dataset as the NeRFCapture app would (DDS)")
    fake_nc.add_argument("--dataset", help="dataset folder (default: the generated synthetic room)")
    fake_nc.add_argument("--fps", type=float, default=10.0, help="frame rate")
    fake_nc.add_argument("--wait", type=float, default=60.0, help="seconds to wait for a receiver")
    fake_nc.add_argument("--domain", type=int, default=0, help="DDS domain id (default: 0, the app's)")
    fake_nc.add_argument("--loop", action="store_true", help="start over at the end instead of ending the stream")
    fake_nc.add_argument("--output", default="outputs", help="where the generated synthetic room is cached")
    fake_nc.add_argument("--quiet", action="store_true")
    view = sub.add_parser("view", help="web viewer for a saved map: a run folder or a 3DGS PLY")
    view.add_argument("path", help="run folder (map.ply, trajectory.txt) or a .ply file")
    _add_viewer_options(view, always=True)
    return parser


def _config_from(args: argparse.Namespace) -> Config:
    from pipeline.config import load_config, with_value
    from pipeline.devices import default_preset, resolve_device

    config_file = args.config
    if getattr(args, "resume", None):
        config_file = config_file or str(Path(args.resume) / "config.toml")
        if not Path(config_file).exists():
            raise UserError(f"no config.toml in {args.resume}: is it a run folder?")
    live = args.command == "serve" or str(getattr(args, "dataset", "") or "").startswith(LIVE_SCHEMES)
    preset = args.preset or default_preset(resolve_device(args.device or "auto"), live)
    config = load_config(preset, config_file, args.overrides)
    if getattr(args, "dataset", None):
        config = with_value(config, "dataset.path", args.dataset)
    for key, value in (
        ("run.output", args.output),
        ("run.device", args.device),
        ("run.name", getattr(args, "name", None)),
        ("run.loader", getattr(args, "loader", None)),
        ("viewer.enabled", "true" if getattr(args, "viewer", False) else None),
        ("viewer.port", getattr(args, "viewer_port", None)),
        ("viewer.host", getattr(args, "viewer_host", None)),
    ):
        if value:
            config = with_value(config, key, value)
    return config


def cmd_run(args: argparse.Namespace) -> int:
    from pipeline.app.report import format_table
    from pipeline.app.run import run_slam

    config = _config_from(args)
    if args.dataset and args.dataset.startswith(LIVE_SCHEMES):
        if args.resume or args.profile or config.run.loader == "sync":
            raise UserError("a live input takes none of --resume, --profile, --loader sync")
        return _serve_live(args.dataset, config, progress=not args.quiet)
    if not config.dataset.path:
        log.info("no dataset given: running on the generated synthetic room (preset '%s')", config.preset)
    result = run_slam(
        config, resume=Path(args.resume) if args.resume else None, profile_trace=args.profile, progress=not args.quiet
    )
    if result.metrics is None:
        return 0
    print(format_table(result.metrics))
    print(f"outputs: {result.folder.path}/ (metrics.json, frames.csv, trajectory.txt, map.ply, checkpoint.safetensors)")
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from pipeline.config import SyntheticConfig
    from pipeline.devices import resolve_device
    from pipeline.io.datasets.synthetic_writer import write_synthetic

    config = SyntheticConfig(
        frames=args.frames,
        width=args.width,
        height=args.height,
        seed=args.seed,
        speed=args.speed,
        jitter=args.jitter,
        fps=args.fps,
        layout=args.layout,
        depth_noise=args.depth_noise,
        holes=args.holes,
        time_jitter=args.time_jitter,
    )
    count = write_synthetic(Path(args.out), config, not args.quiet, resolve_device("auto"))
    print(f"wrote {count} frames ({args.width}x{args.height}, {args.layout} layout) to {args.out}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from pipeline.app.bench import ABLATIONS, cells_of, default_variants, markdown, run_matrix, write_report
    from pipeline.config import load_config

    variants = args.variants.split(",") if args.variants else default_variants(args.ablations)
    unknown = [v for v in variants if v not in ABLATIONS]
    if unknown:
        raise UserError(f"unknown variant '{unknown[0]}' (choose from {', '.join(ABLATIONS)})")
    presets = args.presets.split(",")
    for preset in presets:
        load_config(preset, overrides=args.overrides)  # report bad presets and keys before any work
    cells = cells_of(args.sequences or ["synthetic"], presets, variants)
    if args.ray is None:
        _check_folders(args.sequences)  # on a cluster only the nodes need to see them: a cell reports it
        report = run_matrix(cells, args.overrides, Path(args.runs), not args.quiet, args.profile)
    else:
        _require_ray()
        from pipeline.app.ray_bench import run_matrix_on_ray

        report = run_matrix_on_ray(
            cells, args.overrides, Path(args.runs), args.ray or None, args.gpus_per_cell, args.profile
        )
    json_path, md_path = write_report(report, Path(args.out), args.stem)
    print(markdown(report))
    print(f"wrote {json_path} and {md_path}")
    failed = sum(bool(row["error"]) for row in report["rows"])
    if failed:
        print(f"{failed} of {len(cells)} cells failed (their error is in the table)", file=sys.stderr)
    return 1 if failed else 0


def _check_folders(sequences: list[str]) -> None:
    from pipeline.app.bench import SYNTHETIC_SEQUENCES

    missing = [s for s in sequences if s not in SYNTHETIC_SEQUENCES and not Path(s).is_dir()]
    if missing:
        raise UserError(f"dataset folder not found: {missing[0]}")


def _require_ray() -> None:
    import importlib.util

    if importlib.util.find_spec("ray") is None:
        raise UserError("--ray needs Ray: pip install 'gsplatam[cluster]'")


LIVE_SCHEMES = ("record3d:", "nerfcapture:")  # `run record3d:http://PHONE` / `run nerfcapture:`: no recording


def _serve_live(spec: str, config: Config, progress: bool) -> int:
    from pipeline.app.live_sources import live_source
    from pipeline.app.serve import serve

    source = live_source(spec, config)
    log.info("live from %s -> SLAM until Ctrl-C, which saves and stops", spec)
    result = serve(config, source, progress=progress)
    if result.metrics is not None:
        print(f"{result.metrics['frames']} frames, {result.metrics['gaussians']:,} Gaussians: {result.folder.path}/")
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    specs = [f"record3d:{url}" for url in args.record3d] + [f"nerfcapture:{domain}" for domain in args.nerfcapture]
    if not specs:
        raise UserError("serve needs a source: --record3d URL or --nerfcapture")
    config = _config_from(args)
    if args.ray is not None:
        _require_ray()
        from pipeline.app.ray_serve import serve_on_ray

        return serve_on_ray(specs, config, args.ray or None, args.gpus_per_session)
    if len(specs) > 1:
        raise UserError("several sources need --ray (each a session of its own)")
    return _serve_live(specs[0], config, progress=not args.quiet)


# The default scene of the fake phone: 256x192 is the iPhone LiDAR's depth resolution; 10 s at 30 fps.
FAKE_PHONE_SCENE_SIZE = (256, 192, 300)


def _fake_phone_dataset(args: argparse.Namespace) -> Dataset:
    from pipeline.config import DatasetConfig, SyntheticConfig
    from pipeline.io.datasets.loader import open_dataset
    from pipeline.io.datasets.synthetic_writer import cached_synthetic

    path = args.dataset
    if not path:
        width, height, frames = FAKE_PHONE_SCENE_SIZE
        scene = SyntheticConfig(frames=frames, width=width, height=height)
        path = str(cached_synthetic(Path(args.output) / "synthetic", scene, not args.quiet))
    return open_dataset(DatasetConfig(path=path))


def cmd_fake_record3d(args: argparse.Namespace) -> int:
    import asyncio

    from pipeline.io.live.fake_record3d import FakePhone

    dataset = _fake_phone_dataset(args)

    async def main() -> None:
        phone = FakePhone(dataset, args.fps, args.loop)
        port = await phone.start(args.host, args.port)
        log.info(
            "fake Record3D phone: http://%s:%d (%s, %d frames at %g fps)",
            args.host,
            port,
            dataset.name,
            len(dataset),
            args.fps,
        )
        try:
            await asyncio.Event().wait()
        finally:
            await phone.stop()

    asyncio.run(main())
    return 0


def cmd_fake_nerfcapture(args: argparse.Namespace) -> int:
    from pipeline.io.live.fake_nerfcapture import publish_dataset

    dataset = _fake_phone_dataset(args)
    log.info(
        "fake NeRFCapture: publishing %s (%d frames at %g fps) once a receiver matches",
        dataset.name,
        len(dataset),
        args.fps,
    )
    sent = publish_dataset(dataset, args.fps, args.wait, domain_id=args.domain, loop=args.loop)
    print(f"published {sent} frames")
    return 0 if sent else 1


def cmd_view(args: argparse.Namespace) -> int:
    import threading

    from pipeline.io.outputs.ply import read_ply
    from pipeline.io.trajectory import read_tum_trajectory
    from pipeline.io.ui.viewer import Viewer
    from pipeline.io.ui.viewer_feed import map_view

    path = Path(args.path)
    ply = path / "map.ply" if path.is_dir() else path
    if not ply.is_file():
        raise UserError(f"no map to show: {ply} does not exist")
    gaussians = read_ply(ply)
    viewer = Viewer(args.viewer_host or "127.0.0.1", args.viewer_port or 8080, f"gsplatam: {ply}", live=False)
    viewer.show_map(map_view(gaussians))
    trajectory = path / "trajectory.txt"
    if path.is_dir() and trajectory.is_file():
        poses = read_tum_trajectory(trajectory)[1]
        viewer.show_trajectory(poses)
        if len(poses):
            viewer.look_from(poses[0])
    viewer.stats.content = f"{len(gaussians):,} Gaussians from {ply}"
    print(f"showing {len(gaussians):,} Gaussians at {viewer.url} (Ctrl-C to quit)")
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        pass  # the way to quit
    finally:
        viewer.close()
    return 0


COMMANDS = {
    "run": cmd_run,
    "synth": cmd_synth,
    "bench": cmd_bench,
    "serve": cmd_serve,
    "fake-record3d": cmd_fake_record3d,
    "fake-nerfcapture": cmd_fake_nerfcapture,
    "view": cmd_view,
}


def _terminate_as_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    configure_logging()
    # Outside a run SIGTERM ends the command like Ctrl-C; during a run the runtime handles both.
    signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except UserError as exc:
        print(f"gsplatam: error: {exc}", file=sys.stderr)
        return 2
    except StageFailure as exc:
        if not isinstance(exc.cause, UserError):
            raise
        print(f"gsplatam: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("gsplatam: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
