"""The ``torm`` command line.

Each sub-command lives in its own module under :mod:`torm.commands` and exposes
``register(subparsers) -> None``, which adds an argparse parser whose ``func(args) -> int`` runs it.
Commands are discovered automatically, so adding one never touches this file. Machine-readable
output goes to stdout as JSON; progress and diagnostics go to the log on stderr (torm's own messages at
INFO, third-party libraries only from WARNING; ``-q`` for warnings only, ``-v`` / ``-vv`` for more).
``python -m torm`` is the same program.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from torm.errors import TormError

log = logging.getLogger("torm")


def build_parser() -> argparse.ArgumentParser:
    import torm.commands as commands
    from torm import __version__

    parser = argparse.ArgumentParser(
        prog="torm", description="TORM: see, reconstruct and grasp transparent objects; a simulation-in-the-loop "
        "grasp benchmark.", epilog="example: torm trial --scenario rw3 --seed 0  (torm COMMAND --help for more)")
    parser.add_argument("--version", action="version", version=f"torm {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more logging: -v torm debug messages, -vv also third-party libraries")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors on stderr (for scripts)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"torm.commands.{info.name}")
        module.register(sub)
    for child in sub.choices.values():
        _add_logging_flags(child)
    return parser


def _add_logging_flags(parser: argparse.ArgumentParser) -> None:
    """``-q`` / ``-v`` after the command name too (``torm trial -q``), on every nested sub-command."""
    group = parser.add_argument_group("logging")
    # SUPPRESS: a flag not given here must not overwrite the same flag given before the command name.
    group.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                       help="more logging (-vv: third-party libraries too)")
    group.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                       help="only warnings and errors on stderr")
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                _add_logging_flags(child)


#: Loggers of torm's own packages (everything else is a third-party library).
OWN_LOGGERS = ("torm", "sim", "bench")


def configure_logging(verbose: int = 0, quiet: bool = False) -> None:
    """stderr logging: torm's messages at INFO (DEBUG with ``verbose``), third-party ones from WARNING.

    ``quiet`` shows warnings and errors only; ``verbose >= 2`` also lets third-party INFO/DEBUG through.
    """
    own = logging.WARNING if quiet else (logging.INFO if verbose == 0 else logging.DEBUG)
    other = logging.WARNING if verbose < 2 or quiet else logging.DEBUG
    logging.basicConfig(level=other, format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S",
                        stream=sys.stderr, force=True)
    for name in OWN_LOGGERS:
        logging.getLogger(name).setLevel(own)


def main(argv: list[str] | None = None) -> int:
    from torm.runtime import ensure_headless_gl

    ensure_headless_gl()  # before anything imports mujoco: it picks its GL backend at import time
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    try:
        return int(args.func(args) or 0)
    except TormError as exc:  # printed once, here; library code raises without logging it
        print(f"torm: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # stdout closed early (e.g. piped into head): not an error of ours
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print("torm: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
