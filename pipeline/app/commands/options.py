"""Options several commands share, and the config they ask for."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.errors import UserError
from pipeline.io.sources.cameras import CAMERAS

if TYPE_CHECKING:
    import torch

    from pipeline.config import Config

log = logging.getLogger("gsplatam")

# command-line options that set a key of the config (after --config and --set: they win)
OPTION_KEYS = (
    ("dataset", "dataset.path"), ("output", "run.output"), ("device", "run.device"), ("name", "run.name"),
    ("loader", "run.loader"), ("viewer", "viewer.kind"), ("viewer_port", "viewer.port"), ("viewer_host", "viewer.host"),
)  # fmt: skip
# The settings most runs touch, named by `run --help` and `config --help` (every one: gsplatam config).
MOST_USED = (
    "dataset.depth_scale", "dataset.intrinsics", "dataset.start", "dataset.end", "dataset.stride", "dataset.width",
    "tracking.method", "slam.schedule", "mapping.final_iters", "loops.enabled", "run.eval_every", "run.save_every_s",
    "viewer.rerun_save",
)  # fmt: skip
LIVE_SPECS = " or ".join(
    f"{scheme}:[{camera.metavar}]" if camera.address_optional else f"{scheme}:{camera.metavar}"
    for scheme, camera in CAMERAS.items()
)


# A command's epilog that `--help` replaces by settings_epilog() (built only then: it reads the schema's comments).
SETTINGS_EPILOG = "<the most used settings>"


def settings_epilog() -> str:
    """The most used settings, a line each (key=default, then its meaning), for --help."""
    from pipeline.config import Config
    from pipeline.config.docs import config_sections, wrapped

    docs = {k.key: k for section in config_sections(Config()) for k in section.keys}
    pairs = [(f"{key}={docs[key].default}", docs[key].meaning) for key in MOST_USED]
    width = max(len(pair) for pair, _ in pairs)
    lines = [wrapped(f"  {pair:<{width}}  {meaning}", width + 4) for pair, meaning in pairs]
    return "\n".join(["most used settings (--set KEY=VALUE; the default shown; every one: gsplatam config):", *lines])


def add_config_options(parser: argparse.ArgumentParser) -> None:
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


def add_run_folder_options(parser: argparse.ArgumentParser, default_name: str) -> None:
    parser.add_argument("--name", help=f"run folder name under --output (default: {default_name})")
    parser.add_argument("--overwrite", action="store_true", help="replace the earlier run in the --name folder")


def add_viewer_options(parser: argparse.ArgumentParser, always: bool = False) -> None:
    if not always:
        parser.add_argument(
            "--viewer", nargs="?", const="viser", choices=["viser", "open3d", "rerun"],
            help="watch it: viser, a web page (the default), open3d, a desktop window, or rerun, rerun's viewer "
            "(or a .rrd file: --set viewer.rerun_save=FILE)",
        )  # fmt: skip
    parser.add_argument("--viewer-port", type=int, help="viewer port (default: 8080)")
    parser.add_argument("--viewer-host", help="viewer address (default: 127.0.0.1; 0.0.0.0 exposes it)")


def requested_config(
    args: argparse.Namespace, live: bool, config_file: Path | None = None
) -> tuple[Config, torch.device]:
    """The config the command line asks for (preset, `--config` or else `config_file`, `--set`,
    then the options) and the device it names, resolved once. Without a preset named (here or
    by the file) the device chooses it: base on a GPU for datasets, tiny on the CPU and for
    `live` input. The config is read and checked before torch is imported: a mistake in it is
    answered at once."""
    from pipeline.config import DEFAULT_PRESET_CPU, load_config

    source = args.config or config_file
    overrides = [*args.overrides, *_option_settings(args)]
    named = args.preset is not None
    config = load_config(args.preset if named else DEFAULT_PRESET_CPU, source, overrides)
    check_paths(config)
    from pipeline.devices import default_preset, resolve_device  # torch

    device = resolve_device(config.run.device)
    if not named and (preset := default_preset(device, live)) != config.preset:
        config = load_config(preset, source, overrides)  # a file that names its preset keeps it
    if named and config.preset != args.preset:
        log.warning("--preset %s is overridden by %s, which names preset '%s'", args.preset, source, config.preset)
    return config, device


def check_paths(config: Config) -> None:
    """The files a run writes outside its run folder, checked before it starts: UserError naming
    the setting where one cannot be written there."""
    if config.viewer.rerun_save:
        save = Path(config.viewer.rerun_save)
        if save.is_dir():
            raise UserError(f"viewer.rerun_save: {save} is a folder; name the .rrd file to write")
        if not save.parent.is_dir():
            raise UserError(f"viewer.rerun_save: the folder {save.parent} does not exist")


def _option_settings(args: argparse.Namespace) -> list[str]:
    """The options given, as `--set` settings."""
    given = [(key, getattr(args, option, None)) for option, key in OPTION_KEYS]
    if getattr(args, "dataset", None):  # the folder as given, beside the absolute path a run records
        given.append(("dataset.path_as_given", args.dataset))
    if getattr(args, "viewer", None):
        given.append(("viewer.enabled", "true"))
    return [f"{key}={value}" for key, value in given if value is not None and value != ""]
