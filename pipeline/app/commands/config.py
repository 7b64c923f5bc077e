"""`gsplatam config`: every setting, with its type, default (this machine's, as `run` would
use them, or under a preset) and meaning; one section or one key."""

from __future__ import annotations

import argparse

from pipeline.app.commands.options import SETTINGS_EPILOG, requested_config

HELP = "list every setting: key, type, default and meaning"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("key", nargs="?", help="only this section (e.g. tracking) or key (e.g. tracking.method)")
    parser.add_argument("--preset", help="defaults of this preset (default: the one `run` picks on this machine)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], help="the device `run` would use (default: auto)")
    parser.epilog = SETTINGS_EPILOG


def run(args: argparse.Namespace) -> int:
    from pipeline.config import Config
    from pipeline.config.docs import config_sections, format_sections

    config_sections(Config(), args.key)  # a section or key that is none: answered before torch loads
    asked = argparse.Namespace(preset=args.preset, device=args.device, config=None, overrides=[])
    config, device = requested_config(asked, live=False)
    sections = config_sections(config, args.key)
    chosen = "" if args.preset else " (the preset `gsplatam run` picks for this device)"
    print(f"Defaults of preset '{config.preset}' on device {device}{chosen}:")
    print(format_sections(sections), end="")
    print("Set a key with --set KEY=VALUE or in a TOML file given to --config ([section] then key = value).")
    return 0
