"""The `dualnerf` command line. Subcommands live in `experiments/commands/<name>.py`, each exposing
`register(subparsers)` and importing nothing heavy at module level, so `dualnerf --help` is instant.

The global options (--cache, --runs, --quiet) are accepted before and after the command
(`dualnerf --cache X run W` and `dualnerf run W --cache X`).

Exit status: 0 success; 1 internal error (traceback printed) or failed steps; 2 user error (a message
naming what to fix, no traceback; see pipeline.errors for the rule); 130 interrupted (Ctrl-C); 143
terminated (SIGTERM: stops as cleanly as Ctrl-C, see pipeline.runner.terminate_as_interrupt).
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

COMMANDS = ["run", "status", "report", "params", "scene", "models", "cache"]


def add_global_options(parser: argparse.ArgumentParser, defaults: bool = True) -> None:
    """--cache, --runs, --quiet. On the commands' parsers (defaults=False) they leave a value given
    before the command alone unless given again after it."""
    def default(value):
        return value if defaults else argparse.SUPPRESS

    parser.add_argument("--cache", type=Path, default=default(None),
                        help="result store folder (default: $DUALNERF_CACHE, else ./cache)")
    parser.add_argument("--runs", type=Path, default=default(Path("runs")),
                        help="folder for run records and step logs (default: ./runs)")
    parser.add_argument("--quiet", action="store_true", default=default(False),
                        help="no progress bars; a log line every ~10%% of a step instead")


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as package_version

    try:
        return package_version("dualnerf-pipeline")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _command_parsers(parser: argparse.ArgumentParser):
    """Every parser below `parser` (commands, and actions such as `cache ls`)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):
                yield sub
                yield from _command_parsers(sub)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dualnerf", description="Resumable batch pipeline for DualNeRF text-driven 3D scene editing.")
    add_global_options(parser)
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        module_name = f"experiments.commands.{name}"
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:
                continue      # that command is not written yet; any other missing module is a real error
            raise
        module.register(subparsers)
    for sub in _command_parsers(parser):
        add_global_options(sub, defaults=False)
    return parser


def cache_dir(args: argparse.Namespace) -> Path:
    """--cache, else $DUALNERF_CACHE, else ./cache."""
    if args.cache is not None:
        return Path(args.cache)
    return Path(os.environ.get("DUALNERF_CACHE") or "cache")


def open_store(args: argparse.Namespace):
    from pipeline.store import Store

    return Store(cache_dir(args))


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handler = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 2
    from pipeline.errors import is_user_error
    from pipeline.runner import Terminated, terminate_as_interrupt

    try:
        with terminate_as_interrupt():
            return int(handler(args) or 0)
    except Terminated:
        print("dualnerf: terminated (SIGTERM); checkpoints are kept, rerun the same command to resume.",
              file=sys.stderr)
        return Terminated.exit_status
    except KeyboardInterrupt:
        print("dualnerf: interrupted; checkpoints are kept, rerun the same command to resume.", file=sys.stderr)
        return 130
    except Exception as exc:
        if is_user_error(exc):
            print(f"dualnerf: error: {exc}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    sys.exit(main())
