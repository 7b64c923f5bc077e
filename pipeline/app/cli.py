"""The `gsplatam` command line (also `python -m pipeline`): the commands' table, and what every
command shares (logging, signals, one line and exit code 2 for a mistake a user can fix)."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from typing import Any, NoReturn, Protocol

from tqdm.contrib.logging import logging_redirect_tqdm

from pipeline import __version__
from pipeline.app.commands import (
    bench,
    config,
    download,
    export,
    fake_nerfcapture,
    fake_record3d,
    render,
    run,
    serve,
    synth,
    view,
)
from pipeline.app.commands.options import SETTINGS_EPILOG, settings_epilog
from pipeline.app.logs import configure_logging
from pipeline.config.choices import did_you_mean, nearest
from pipeline.errors import MappingProcessFailed, StageFailure, UserError
from pipeline.extras import missing_extra
from pipeline.processes import terminate_as_interrupt


class Command(Protocol):
    """What a command's module (app/commands/) holds."""

    HELP: str  # one line for `gsplatam --help`

    def add_arguments(self, parser: argparse.ArgumentParser) -> None: ...

    def run(self, args: argparse.Namespace) -> int:
        """The command, once its arguments are parsed -> the exit code."""
        ...


COMMANDS: dict[str, Command] = {
    "run": run,
    "synth": synth,
    "bench": bench,
    "serve": serve,
    "fake-record3d": fake_record3d,
    "fake-nerfcapture": fake_nerfcapture,
    "view": view,
    "export": export,
    "render": render,
    "download": download,
    "config": config,
}

log = logging.getLogger("gsplatam")
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE  # 141: what a shell reports for a writer whose reader went away


class Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")

    def format_help(self) -> str:
        if self.epilog == SETTINGS_EPILOG:
            self.epilog = settings_epilog()
        return super().format_help()

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        """A value outside an option's choices, answered with the nearest ones (did you mean)."""
        choices = action.choices
        if choices is not None and value not in choices:
            names = [str(c) for c in choices]
            hint = did_you_mean(nearest(str(value), names))
            listed = ", ".join(map(repr, names))
            raise argparse.ArgumentError(
                action, f"invalid choice: {value!r}" + (f": {hint}" if hint else "") + f" (choose from {listed})"
            )


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


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser: every command's arguments, or (`only`, the command given) that
    command's alone, the others by name and help line (a command's arguments may import what
    takes seconds to load: the export registry's writers)."""
    parser = Parser(
        prog="gsplatam",
        description="Real-time RGB-D SLAM with Gaussian splatting (SplaTAM on gsplat).",
        epilog="Every setting (for --set KEY=VALUE and --config FILE): gsplatam config [SECTION]",
    )
    parser.add_argument("--version", action="version", version=f"gsplatam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    common = _common_options()
    for name, command in COMMANDS.items():
        # the description and epilog as written (a command's list of settings keeps its lines)
        formatter = argparse.RawDescriptionHelpFormatter
        command_parser = sub.add_parser(name, help=command.HELP, parents=[common], formatter_class=formatter)
        if only is None or only == name:
            command.add_arguments(command_parser)
    return parser


def _configure_logging(args: argparse.Namespace) -> None:
    configure_logging()
    log.setLevel(logging.DEBUG if args.verbose else getattr(logging, args.log_level.upper()))


def main(argv: list[str] | None = None) -> int:
    """The command of `argv` -> its exit code. Output piped into a reader that stops early
    (`gsplatam config | head -1`) ends the command quietly with EXIT_BROKEN_PIPE."""
    try:
        code = _main(argv)
        sys.stdout.flush()  # here, not at interpreter exit, where it would print a traceback
        return code
    except BrokenPipeError:
        # Python's advice (signal module docs): point stdout at devnull so the exit's flush is quiet.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE


def _main(argv: list[str] | None) -> int:
    given = sys.argv[1:] if argv is None else argv
    command = next((word for word in given if not word.startswith("-")), None)  # a command's name, or a typo
    args = build_parser(command if command in COMMANDS else None).parse_args(argv)
    _configure_logging(args)
    # Outside a run SIGTERM ends the command like Ctrl-C; during a run the runtime handles both.
    # SIGINT too, even where the process started with it ignored (a job a shell put in the
    # background): a command given SIGINT stops as the README says, whoever started it.
    signal.signal(signal.SIGTERM, terminate_as_interrupt)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with logging_redirect_tqdm():  # log lines go above the progress bars, never through them
            return COMMANDS[args.command].run(args)
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
        if isinstance(exc.cause, MappingProcessFailed):  # what was processed is written (said above): exit 1
            print(f"gsplatam: error: {exc.cause}", file=sys.stderr)
            return 1
        if isinstance(exc.cause, ImportError) and (message := missing_extra(exc.cause)):
            return _fail(f"stage '{exc.stage}': {message}")
        raise
    except MappingProcessFailed as exc:  # after SLAM: what the mapping process completed is written (said above)
        print(f"gsplatam: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("gsplatam: interrupted", file=sys.stderr)
        return 130


def _fail(message: str) -> int:
    print(f"gsplatam: error: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
