"""Argument helpers shared by sub-commands."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import OutputError


def add_overrides(parser: argparse.ArgumentParser) -> None:
    """Add ``--config FILE`` and repeatable ``--set a.b=c`` to a parser."""
    parser.add_argument("--config", default=None, help="YAML config file (defaults when omitted)")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a config value, e.g. --set reconstruction.grid_res=64 (repeatable)",
    )


def _default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


def print_json(obj: Any) -> None:
    """Write ``obj`` as indented JSON to stdout (numpy values converted)."""
    json.dump(obj, sys.stdout, indent=2, default=_default)
    sys.stdout.write("\n")


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
        tmp.write_text(json.dumps(obj, indent=2, default=_default) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise OutputError(f"{flag} {path}: writing failed ({exc.strerror or exc})") from exc
