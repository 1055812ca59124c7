"""Argument helpers shared by sub-commands."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np


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
