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

from torm.errors import ConfigError, TormError

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
        _add_options_config(child)
    return parser


def _leaves(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """The parsers that run something (they set ``func``), nested sub-commands included."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [parser]
    return [leaf for a in subs for child in a.choices.values() for leaf in _leaves(child)]


def _add_options_config(parser: argparse.ArgumentParser) -> None:
    """Give every command ``--config`` and ``--set``: where a command has no config of its own, ``--config
    FILE.yaml`` holds its options (keys: the long option names) and ``--set OPTION=VALUE`` sets one; the options
    given on the command line win (:func:`apply_options_config`)."""
    for leaf in _leaves(parser):
        opts = {o for a in leaf._actions for o in a.option_strings}
        if "--config" not in opts:
            leaf.add_argument("--config", dest="options_config", default=None, metavar="FILE.yaml",
                              help="YAML of this command's options (keys: the long option names, e.g. out: "
                                   "report/); options given on the command line win")
        if "--set" not in opts:
            leaf.add_argument("--set", dest="options_set", action="append", default=[], metavar="OPTION=VALUE",
                              help="set one of this command's options, e.g. --set out=report/ (repeatable)")
        leaf.set_defaults(_options_parser=leaf)


def apply_options_config(parser: argparse.ArgumentParser, argv: list[str] | None,
                         args: argparse.Namespace) -> argparse.Namespace:
    """Re-parse ``argv`` with the command's options from ``--config FILE.yaml`` / ``--set OPTION=VALUE`` as
    defaults (commands without a config of their own). ConfigError names an unknown key and the valid ones."""
    from torm.config import load_yaml, parse_override

    leaf = getattr(args, "_options_parser", None)
    path, sets = getattr(args, "options_config", None), list(getattr(args, "options_set", None) or [])
    if leaf is None or (not path and not sets):
        return args
    keys: dict[str, str] = {}
    for a in leaf._actions:
        if a.dest in ("help", "options_config", "options_set", "verbose", "quiet") or not a.option_strings:
            continue
        keys[a.dest] = a.dest
        for o in a.option_strings:
            if o.startswith("--"):
                keys[o[2:]] = keys[o[2:].replace("-", "_")] = a.dest
    data = dict(load_yaml(path)) if path else {}
    for text in sets:
        key_path, value = parse_override(text)
        data[".".join(key_path)] = value
    unknown = sorted(k for k in data if k not in keys)
    if unknown:
        valid = sorted({k for k in keys if "_" not in k or k == keys[k]})
        raise ConfigError(f"{path or '--set'}: unknown option(s) {unknown}; valid: {', '.join(valid)}")
    # a list option (--method a --method b) given on the command line replaces the file's list, not extends it
    words = list(sys.argv[1:] if argv is None else argv)
    given = {a.dest for a in leaf._actions if isinstance(a, argparse._AppendAction)
             and any(w == o or w.startswith(o + "=") for o in a.option_strings for w in words)}
    leaf.set_defaults(**{keys[k]: v for k, v in data.items() if keys[k] not in given})
    return parser.parse_args(argv)


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
        args = apply_options_config(parser, argv, args)
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
