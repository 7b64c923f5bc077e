"""`gsplatam config`: every setting, with its type, default (under a preset) and meaning."""

from __future__ import annotations

import argparse

HELP = "list every setting: key, type, default and meaning"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("section", nargs="?", help="only this section (e.g. tracking)")
    parser.add_argument("--preset", default="base", help="defaults of this preset (default: base)")


def run(args: argparse.Namespace) -> int:
    from pipeline.config import preset_config
    from pipeline.config.docs import config_sections, format_sections

    print(format_sections(config_sections(preset_config(args.preset), args.section)), end="")
    print("Set a key with --set KEY=VALUE or in a TOML file given to --config ([section] then key = value).")
    return 0
