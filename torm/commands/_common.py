"""Argument helpers shared by sub-commands."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import OutputError


def plain(doc: str | None) -> str:
    """A module docstring as plain text for ``--help``: RST roles, double backquotes and ``::`` removed."""
    text = doc or ""
    text = re.sub(r":(?:class|func|mod|meth|data|attr):`~?([^`]+)`", r"\1", text)
    text = text.replace("``", "")
    text = re.sub(r"::\n", ":\n", text)
    return text.strip() + "\n"


def add_parser(subparsers: argparse._SubParsersAction, name: str, doc: str | None, help: str,
               **kwargs: Any) -> argparse.ArgumentParser:
    """A sub-command parser whose description is the plain-text ``doc`` (examples kept as written)."""
    return subparsers.add_parser(name, help=help, description=plain(doc),
                                 formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)


def add_overrides(parser: argparse.ArgumentParser, example: str, target: str) -> None:
    """Add ``--config FILE`` and repeatable ``--set a.b=c`` to a parser.

    Args:
        example: a valid override for this command (shown in ``--help``), e.g. ``reconstruction.grid_res=64``.
        target: the config the keys belong to (``torm config show NAME`` lists its keys), e.g. ``trial``.
    """
    parser.add_argument("--config", default=None, metavar="FILE.yaml",
                        help=f"YAML config file of the {target} config (defaults when omitted; "
                        f"`torm config show {target}` prints every key with its default)")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help=f"override a {target} config value, e.g. --set {example} (repeatable; later wins)",
    )


class _DeprecatedAlias(argparse.Action):
    """Store the value; when given through an old spelling (``deprecated``), say once on stderr which name
    replaces it (the old names are kept for one release)."""

    def __init__(self, *args: Any, deprecated: tuple[str, ...] = (), **kwargs: Any) -> None:
        self.deprecated = deprecated
        super().__init__(*args, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        if option_string in self.deprecated:
            new = next(o for o in self.option_strings if o not in self.deprecated)
            sys.stderr.write(f"torm: {option_string} is deprecated and will be removed in the next release; "
                             f"use {new}\n")
        setattr(namespace, self.dest, values)


def add_record(parser: argparse.ArgumentParser, what: str) -> None:
    """``--record FILE.rrd`` (rerun recording of ``what``), with the old spelling ``--rrd`` kept as an alias."""
    parser.add_argument("--record", "--rrd", dest="record", default=None, metavar="FILE.rrd",
                        action=_DeprecatedAlias, deprecated=("--rrd",),
                        help=f"write a rerun recording of {what} to this file (--rrd: old name, deprecated)")


def add_robot(parser: argparse.ArgumentParser, default: str | None, none_ok: bool = False) -> None:
    """``--robot-config NAME|FILE`` with the old spelling ``--robot`` kept as an alias."""
    extra = ", or 'none' for no robot" if none_ok else ""
    parser.add_argument("--robot-config", "--robot", dest="robot_config", default=default, metavar="NAME|FILE",
                        action=_DeprecatedAlias, deprecated=("--robot",),
                        help=f"robot folder name under sim/robots or a robot YAML (default {default or 'inovo_2f85'})"
                        f"{extra}; "
                        "--robot: old name, deprecated")


def _int_at_least(text: str, low: int, below: str, hint: str) -> int:
    """``text`` as an int >= ``low``; argparse.ArgumentTypeError saying ``below`` / ``hint`` otherwise."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer; {hint}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"{value} {below}; {hint}")
    return value


def seed_arg(text: str) -> int:
    """argparse ``type`` of a ``--seed``: a non-negative integer (numpy's generators refuse negative seeds)."""
    return _int_at_least(text, 0, "is negative", "give a seed 0, 1, 2, ...")


def count_arg(text: str) -> int:
    """argparse ``type`` of a count (``--views``, ``--workers``, ``--trials``): a positive integer."""
    return _int_at_least(text, 1, "is not a count", "give a number >= 1")


#: Largest image side accepted by a pixel flag (px): twice the widest sensor torm models (a D455's 1280 px).
MAX_IMAGE_SIDE_PX = 8192


def pixels_arg(text: str) -> int:
    """argparse ``type`` of an image side (``--width``, ``--height``): an integer in [1, MAX_IMAGE_SIDE_PX] px."""
    value = _int_at_least(text, 1, "is not an image size", "give a number of pixels >= 1")
    if value > MAX_IMAGE_SIDE_PX:
        raise argparse.ArgumentTypeError(f"{value} px is larger than {MAX_IMAGE_SIDE_PX} px; give a camera's image "
                                         "size (1280 x 720 for the simulated D455)")
    return value


def finite_float(text: str) -> float:
    """argparse ``type`` of a float flag: a finite number (NaN and +-inf are refused, not passed on)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number; give a number such as 0.5")
    return value


def positive_float(text: str) -> float:
    """argparse ``type`` of a float flag that must be > 0 (a duration, a length, a scale)."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return value


def check_output_dir(path: str | os.PathLike, flag: str = "--out") -> Path:
    """Make sure the folder ``path`` can be created and written before any work starts; returns it.

    Creates the folder (and its parents) and writes, then removes, a probe file in it. OutputError naming
    ``flag`` when ``path`` or a parent is a file, or the location is not writable.
    """
    p = Path(path).expanduser()
    for parent in [p, *p.parents]:
        if parent.exists() and not parent.is_dir():
            raise OutputError(f"{flag} {p}: {parent} is a file, not a folder; choose another output folder")
    try:
        p.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=p, prefix=".probe.", suffix=".tmp"):
            pass
    except OSError as exc:
        raise OutputError(f"{flag} {p}: cannot write there ({exc.strerror or exc}); choose a writable "
                          "location") from exc
    return p


def _default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


#: Significant digits of floats in CLI JSON output (1 um on metres, 1 us on seconds up to ~1 s).
SIGNIFICANT_DIGITS = 6


def rounded(obj: Any, digits: int = SIGNIFICANT_DIGITS) -> Any:
    """``obj`` with every float (numpy ones too) rounded to ``digits`` significant digits, NaN/inf kept."""
    if isinstance(obj, dict):
        return {k: rounded(v, digits) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [rounded(v, digits) for v in obj]
    if isinstance(obj, np.ndarray):
        return rounded(obj.tolist(), digits)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return float(f"{x:.{digits}g}") if np.isfinite(x) else x
    return obj


def dumps_json(obj: Any) -> str:
    """``obj`` as indented JSON text with floats rounded (:func:`rounded`) and numpy values converted."""
    return json.dumps(rounded(obj), indent=2, default=_default)


def print_json(obj: Any) -> None:
    """Write ``obj`` as indented JSON to stdout (floats rounded to 6 significant digits, numpy values converted)."""
    sys.stdout.write(dumps_json(obj) + "\n")


def check_output_file(path: str | os.PathLike, flag: str = "--out") -> Path:
    """Make sure ``path`` can be written before any work starts; returns it. OutputError naming ``flag`` when not.

    Creates the parent folder when missing and writes (then removes) a probe file in it; an existing
    file must be a writable regular file.
    """
    p = Path(path).expanduser()
    if p.is_dir():
        raise OutputError(f"{flag} {p} is a folder; give a file name")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=p.parent, prefix=f".{p.name}.", suffix=".probe"):
            pass
    except OSError as exc:
        raise OutputError(f"{flag} {p}: cannot write in {p.parent} ({exc.strerror or exc}); choose a writable "
                          "location") from exc
    if p.exists() and not os.access(p, os.W_OK):
        raise OutputError(f"{flag} {p} exists and is not writable; choose another file")
    return p


def write_json_file(path: Path, obj: Any, flag: str = "--out") -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically (temp file + rename); OutputError when it fails."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text(dumps_json(obj) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise OutputError(f"{flag} {path}: writing failed ({exc.strerror or exc})") from exc
