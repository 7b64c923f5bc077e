"""The `gsplatam` command line (also `python -m pipeline`)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from tqdm.contrib.logging import logging_redirect_tqdm

from pipeline import __version__
from pipeline.app.logs import configure_logging
from pipeline.config.schema import SYNTHETIC_CPU, SYNTHETIC_GPU
from pipeline.errors import StageFailure, UserError
from pipeline.extras import missing_extra
from pipeline.io.outputs.exports import FORMATS as EXPORT_FORMATS

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
        help="override one setting, e.g. --set tracking.iters=20 (repeatable; every key: gsplatam config)",
    )  # fmt: skip
    parser.add_argument("--output", metavar="DIR", help="where run folders go (default: outputs)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], help="compute device (default: auto)")


def _common_options() -> Parser:
    """Options every command takes: progress bars and how much it logs."""
    common = Parser(add_help=False)
    common.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    common.add_argument("-v", "--verbose", action="store_true", help="log debug messages (as --log-level debug)")
    common.add_argument(
        "--log-level",
        choices=["debug", "info", "warning", "error"],
        default="info",
        help="messages shown (default: info)",
    )
    return common


def _add_viewer_options(parser: argparse.ArgumentParser, always: bool = False) -> None:
    if not always:
        parser.add_argument(
            "--viewer", nargs="?", const="viser", choices=["viser", "open3d"],
            help="watch it: viser, a web page (the default), or open3d, a desktop window",
        )  # fmt: skip
    parser.add_argument("--viewer-port", type=int, help="viewer port (default: 8080)")
    parser.add_argument("--viewer-host", help="viewer address (default: 127.0.0.1; 0.0.0.0 exposes it)")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="gsplatam",
        description="Real-time RGB-D SLAM with Gaussian splatting (SplaTAM on gsplat).",
        epilog="Every setting (for --set KEY=VALUE and --config FILE): gsplatam config [SECTION]",
    )
    parser.add_argument("--version", action="version", version=f"gsplatam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    command = partial(sub.add_parser, parents=[_common_options()])

    run = command("run", help="SLAM on a dataset (default: a generated synthetic room)")
    run.add_argument(
        "dataset", nargs="?",
        help="dataset folder, Replica or TUM layout (default: synthetic room); or live, without recording: "
        "record3d:URL or nerfcapture:",
    )  # fmt: skip
    _add_config_options(run)
    run.add_argument("--name", help="run folder name under --output (default: <dataset>_<preset>-<date>-<time>)")
    run.add_argument("--overwrite", action="store_true", help="replace the earlier run in the --name folder")
    run.add_argument("--resume", metavar="RUN_DIR", help="continue the run in RUN_DIR from its checkpoint")
    run.add_argument("--loader", choices=["pipelined", "sync"], help="asyncio pipeline (default) or a plain loop")
    run.add_argument("--profile", action="store_true", help="write a torch-profiler trace into the run folder")
    _add_viewer_options(run)

    synth = command("synth", help="write a synthetic RGB-D sequence with exact poses")
    synth.add_argument("out", help="output folder")
    synth.add_argument("--layout", choices=["replica", "tum"], default="replica")
    gpu, cpu = SYNTHETIC_GPU, SYNTHETIC_CPU
    for i, name in enumerate(("width", "height", "frames")):
        synth.add_argument(f"--{name}", type=int, default=0, help=f"default: {gpu[i]} with CUDA, {cpu[i]} on the CPU")
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument("--speed", type=float, default=0.3, help="camera speed, m/s")
    synth.add_argument("--jitter", type=float, default=0.01, help="hand-held shake, metres")
    synth.add_argument("--fps", type=float, default=30.0)
    synth.add_argument("--depth-noise", type=float, default=0.0, help="TUM only: depth noise std = k x depth^2")
    synth.add_argument("--holes", type=float, default=0.0, help="TUM only: fraction of depth pixels zeroed")
    synth.add_argument("--time-jitter", type=float, default=0.0, help="TUM only: depth/pose timestamp offsets, s")
    synth.add_argument("--loops", type=int, default=0, help="a closed path, back at its start N times (frames: all)")
    synth.add_argument("--trap", action="store_true", help="the room's halves twins: look-alike places, no loop")

    bench = command("bench", help="benchmark matrix: presets x sequences (x ablations), JSON and a table")
    bench.add_argument("sequences", nargs="*", help="dataset folders (default: the synthetic room)")
    bench.add_argument("--presets", default="tiny", help="comma-separated presets (default: tiny)")
    bench.add_argument("--ablations", action="store_true", help="also run each side-by-side switch")
    bench.add_argument("--variants", help="comma-separated variants instead of --ablations' full set")
    bench.add_argument("--out", default="bench/results", help="where the JSON and table go")
    bench.add_argument("--stem", default="bench", help="file name stem of the JSON and table")
    bench.add_argument("--runs", default="outputs/bench", help="where the run folders go")
    bench.add_argument("--profile", action="store_true", help="profile every cell (trace and summary per run folder)")
    bench.add_argument("--repeats", type=int, default=1, help="run every cell this many times (run-to-run spread)")
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
    serve = command("serve", help="live daemon: reconstruct from a phone's stream until Ctrl-C")
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
    serve.add_argument("--name", help="run folder name under --output (default: live_<source>_<preset>-<date>-<time>)")
    serve.add_argument("--overwrite", action="store_true", help="replace the earlier run in the --name folder")
    _add_viewer_options(serve)

    fake = command("fake-record3d", help="a fake Record3D phone streaming a dataset (for tests and demos)")
    fake.add_argument("--dataset", help="dataset folder (default: the generated synthetic room)")
    fake.add_argument("--host", default="127.0.0.1", help="address to serve on (default: 127.0.0.1)")
    fake.add_argument("--port", type=int, default=8000, help="HTTP port (the real app uses 80)")
    fake.add_argument("--fps", type=float, default=30.0, help="frame rate of the stream")
    fake.add_argument("--loop", action="store_true", help="start over at the end instead of ending the stream")
    fake.add_argument("--output", default="outputs", help="where the generated synthetic room is cached")
    fake_nc = command("fake-nerfcapture", help="publish a dataset as the NeRFCapture app would (DDS)")
    fake_nc.add_argument("--dataset", help="dataset folder (default: the generated synthetic room)")
    fake_nc.add_argument("--fps", type=float, default=10.0, help="frame rate")
    fake_nc.add_argument("--wait", type=float, default=60.0, help="seconds to wait for a receiver")
    fake_nc.add_argument("--domain", type=int, default=0, help="DDS domain id (default: 0, the app's)")
    fake_nc.add_argument("--loop", action="store_true", help="start over at the end instead of ending the stream")
    fake_nc.add_argument("--output", default="outputs", help="where the generated synthetic room is cached")
    view = command("view", help="viewer for a saved map: a run folder or a 3DGS PLY")
    view.add_argument("path", help="run folder (map.ply, trajectory.txt) or a .ply file")
    view.add_argument("--open3d", action="store_true", help="in a desktop window (Open3D) instead of the browser")
    _add_viewer_options(view, always=True)

    export = command("export", help="a run folder to nerfstudio, .splat, a full PLY, a mesh or a point cloud")
    export.add_argument("run_dir", help="run folder")
    export.add_argument("--to", required=True, choices=list(EXPORT_FORMATS), help="the format")
    export.add_argument("--output", metavar="PATH", help="file (folder for nerfstudio); default: in the run folder")
    export.add_argument("--voxel", type=float, default=0.02, help="mesh: TSDF voxel size, metres (default: 0.02)")
    export.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="mesh: where to render")

    config = command("config", help="list every setting: key, type, default and meaning")
    config.add_argument("section", nargs="?", help="only this section (e.g. tracking)")
    config.add_argument("--preset", default="base", help="defaults of this preset (default: base)")
    return parser


def _config_from(args: argparse.Namespace) -> Config:
    from pipeline.config import load_config, validate, with_value
    from pipeline.devices import default_preset, resolve_device

    config_file = args.config
    if getattr(args, "resume", None):
        config_file = config_file or str(Path(args.resume) / "config.toml")
        if not Path(config_file).exists():
            raise UserError(f"no config.toml in {args.resume}: is it a run folder?")
    live = args.command == "serve" or str(getattr(args, "dataset", "") or "").startswith(LIVE_SCHEMES)
    preset = args.preset or default_preset(resolve_device(args.device or "auto"), live)
    config = load_config(preset, config_file, args.overrides)
    if args.preset and config.preset != args.preset:
        log.warning("--preset %s is overridden by %s, which names preset '%s'", args.preset, config_file, config.preset)
    if getattr(args, "dataset", None):
        config = with_value(config, "dataset.path", args.dataset)
    for key, value in (
        ("run.output", args.output),
        ("run.device", args.device),
        ("run.name", getattr(args, "name", None)),
        ("run.loader", getattr(args, "loader", None)),
        ("viewer.enabled", "true" if getattr(args, "viewer", None) else None),
        ("viewer.kind", getattr(args, "viewer", None)),
        ("viewer.port", getattr(args, "viewer_port", None)),
        ("viewer.host", getattr(args, "viewer_host", None)),
    ):
        if value is not None:
            config = with_value(config, key, value)
    validate(config)
    return config


def cmd_run(args: argparse.Namespace) -> int:
    from pipeline.app.report import files_and_next_steps, format_table
    from pipeline.app.run import run_slam

    config = _config_from(args)
    if args.dataset and args.dataset.startswith(LIVE_SCHEMES):
        if args.resume or args.profile or config.run.loader == "sync":
            raise UserError("a live input takes none of --resume, --profile, --loader sync")
        return _serve_live(args.dataset, config, not args.quiet, args.overwrite)
    if not config.dataset.path:
        log.info("no dataset given: running on the generated synthetic room (preset '%s')", config.preset)
    if args.resume and args.overwrite:
        raise UserError("--resume continues a run, --overwrite replaces one: give one of them")
    resume = Path(args.resume) if args.resume else None
    result = run_slam(config, resume, profile_trace=args.profile, progress=not args.quiet, overwrite=args.overwrite)
    if result.metrics is None:
        return 0
    print(format_table(result.metrics))
    print(files_and_next_steps(result.folder.path))
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from pipeline.config import SyntheticConfig
    from pipeline.devices import resolve_device, synthetic_for
    from pipeline.io.datasets.synthetic_writer import write_synthetic

    device = resolve_device("auto")
    requested = SyntheticConfig(
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
        loops=args.loops,
        trap=args.trap,
    )
    config = synthetic_for(requested, device)  # sizes left at 0 by device (a closed path's frames: all of it)
    count = write_synthetic(Path(args.out), config, not args.quiet, device)
    print(f"wrote {count} frames ({config.width}x{config.height}, {args.layout} layout) to {args.out}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from pipeline.app.bench import ABLATIONS, cells_of, default_variants, markdown, run_matrix, write_report
    from pipeline.config import load_config

    variants = args.variants.split(",") if args.variants else default_variants(args.ablations)
    unknown = [v for v in variants if v not in ABLATIONS]
    if unknown:
        raise UserError(f"unknown variant '{unknown[0]}' (choose from {', '.join(ABLATIONS)})")
    presets = args.presets.split(",")
    if args.repeats < 1:
        raise UserError("--repeats must be at least 1")
    for preset in presets:
        load_config(preset, overrides=args.overrides)  # report bad presets and keys before any work
    cells = cells_of(args.sequences or ["synthetic"], presets, variants, args.repeats)
    if args.ray is None:
        _check_folders(args.sequences)  # on a cluster only the nodes need to see them: a cell reports it
        report = run_matrix(cells, args.overrides, Path(args.runs), not args.quiet, args.profile)
    else:
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


LIVE_SCHEMES = ("record3d:", "nerfcapture:")  # `run record3d:http://PHONE` / `run nerfcapture:`: no recording


def _serve_live(spec: str, config: Config, progress: bool, overwrite: bool) -> int:
    from pipeline.app.live_sources import live_source
    from pipeline.app.report import files_and_next_steps
    from pipeline.app.serve import serve

    source = live_source(spec, config)
    log.info("live from %s -> SLAM until Ctrl-C, which saves and stops", spec)
    result = serve(config, source, progress, overwrite)
    if result.metrics is not None:
        print(f"{result.metrics['frames']} frames, {result.metrics['gaussians']:,} Gaussians")
        print(files_and_next_steps(result.folder.path))
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    specs = [f"record3d:{url}" for url in args.record3d] + [f"nerfcapture:{domain}" for domain in args.nerfcapture]
    if not specs:
        raise UserError("serve needs a source: --record3d URL or --nerfcapture")
    config = _config_from(args)
    if args.ray is not None:
        from pipeline.app.ray_serve import serve_on_ray

        return serve_on_ray(specs, config, args.ray or None, args.gpus_per_session)
    if len(specs) > 1:
        raise UserError("several sources need --ray (each a session of its own)")
    return _serve_live(specs[0], config, not args.quiet, args.overwrite)


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

    if not 0 <= args.port <= 65535:
        raise UserError(f"--port {args.port} is not a port (0 to 65535; 0: any free one)")
    dataset = _fake_phone_dataset(args)

    async def main() -> None:
        phone = FakePhone(dataset, args.fps, args.loop)
        try:
            port = await phone.start(args.host, args.port)
        except OSError as exc:
            await phone.stop()
            raise UserError(f"cannot serve on {args.host}:{args.port}: {exc.strerror or exc}") from None
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
    from pipeline.app.view import view_saved_map

    if args.viewer_port is not None and not 1 <= args.viewer_port <= 65535:
        raise UserError(f"--viewer-port {args.viewer_port} is not a port (1 to 65535)")
    view_saved_map(Path(args.path), args.open3d, args.viewer_host or "127.0.0.1", args.viewer_port or 8080)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from pipeline.app.export import export_run

    exported = export_run(
        Path(args.run_dir), args.to, Path(args.output) if args.output else None, args.voxel, args.device
    )
    print(f"wrote {exported.path}: {exported.summary}")
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    from pipeline.config import preset_config
    from pipeline.config.docs import config_sections, format_sections

    print(format_sections(config_sections(preset_config(args.preset), args.section)), end="")
    print("Set a key with --set KEY=VALUE or in a TOML file given to --config ([section] then key = value).")
    return 0


COMMANDS = {
    "run": cmd_run,
    "synth": cmd_synth,
    "bench": cmd_bench,
    "serve": cmd_serve,
    "fake-record3d": cmd_fake_record3d,
    "fake-nerfcapture": cmd_fake_nerfcapture,
    "view": cmd_view,
    "export": cmd_export,
    "config": cmd_config,
}


def _terminate_as_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _configure_logging(args: argparse.Namespace) -> None:
    configure_logging()
    log.setLevel(logging.DEBUG if args.verbose else getattr(logging, args.log_level.upper()))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _configure_logging(args)
    # Outside a run SIGTERM ends the command like Ctrl-C; during a run the runtime handles both.
    # SIGINT too, even where the process started with it ignored (a job a shell put in the
    # background): a command given SIGINT stops as the README says, whoever started it.
    signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with logging_redirect_tqdm():  # log lines go above the progress bars, never through them
            return COMMANDS[args.command](args)
    except UserError as exc:
        return _fail(str(exc))
    except ImportError as exc:
        message = missing_extra(exc)
        if message is None:
            raise
        return _fail(message)
    except StageFailure as exc:
        if isinstance(exc.cause, UserError):
            return _fail(str(exc))
        if isinstance(exc.cause, ImportError) and (message := missing_extra(exc.cause)):
            return _fail(f"stage '{exc.stage}': {message}")
        raise
    except KeyboardInterrupt:
        print("gsplatam: interrupted", file=sys.stderr)
        return 130


def _fail(message: str) -> int:
    print(f"gsplatam: error: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
