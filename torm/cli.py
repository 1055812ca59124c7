"""The ``torm`` command line.

Each sub-command lives in its own module under :mod:`torm.commands` and exposes
``register(subparsers) -> None``, which adds an argparse parser whose ``func(args) -> int`` runs it.
Commands are discovered automatically, so adding one never touches this file. Machine-readable
output goes to stdout as JSON; diagnostics go to the log on stderr.
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

    parser = argparse.ArgumentParser(prog="torm", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"torm.commands.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from torm.runtime import ensure_headless_gl

    ensure_headless_gl()  # before anything imports mujoco: it picks its GL backend at import time
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose + 1, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        return int(args.func(args) or 0)
    except TormError as exc:  # printed once, here; library code raises without logging it
        print(f"torm: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("torm: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
