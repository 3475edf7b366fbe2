"""`aefabmap` command line: one subcommand per module; only this layer prints and exits."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from aefabmap import __version__
from aefabmap_runtime.errors import AefabmapError

# Per-frame work runs on one BLAS thread: a multi-threaded BLAS on a small matrix product
# per frame costs more in thread wake-ups than it saves (quantise was several times slower
# with one thread per core: docs/streaming.md, "Results: two processes over loopback Zenoh
# (`bench stream`)"), and the other cores belong to the camera and the SLAM back-end.
SINGLE_BLAS_THREAD_COMMANDS = ("run", "replay", "eval", "demo", "bench")

# Each module exposes register(subparsers) and sets `func` (args -> exit code) on its parser.
SUBCOMMAND_MODULES = ("train", "eval", "bench", "run", "publish", "replay", "log", "demo", "status", "slam")

log = logging.getLogger("aefabmap")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="aefabmap", description="Appearance-based loop-closure detection (FAB-MAP 2.0).")
    parser.add_argument("--version", action="version", version=f"aefabmap {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(f"aefabmap.cli.{name}").register(sub)
    _end_help_with_exit_codes(parser)
    return parser


def _end_help_with_exit_codes(parser: argparse.ArgumentParser) -> None:
    """Append the shared exit codes to the epilog of `parser` and of every (nested) subcommand's parser."""
    from aefabmap.cli.options import EXIT_CODES

    parser.epilog = f"{parser.epilog}\n\n{EXIT_CODES}" if parser.epilog else EXIT_CODES
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command in action.choices.values():
                _end_help_with_exit_codes(command)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # Our own messages at INFO; third-party libraries (onnxscript, matplotlib...) only warn.
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    log.setLevel(logging.DEBUG if args.verbose else logging.INFO)
    try:
        if args.command in SINGLE_BLAS_THREAD_COMMANDS:
            from threadpoolctl import threadpool_limits

            with threadpool_limits(limits=1, user_api="blas"):
                return int(args.func(args) or 0)
        return int(args.func(args) or 0)
    except AefabmapError as exc:
        log.error("%s: %s", type(exc).__name__, exc)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
