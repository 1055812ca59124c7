"""``torm config``: every config and its keys, with defaults, types and the ``--set`` spelling.

- ``torm config list``: the config names (what ``--config`` / ``--set`` configure for each command).
- ``torm config show NAME``: the defaults as YAML (a valid ``--config`` file to start from);
  ``--keys`` prints one dotted key per line with its type and default instead (the ``--set`` spelling).

Examples::

    torm config list
    torm config show trial
    torm config show trial --keys
    torm config show reconstruct --set grid_res=64
    torm config show segment:noisy
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import types
import typing
from typing import Any

import yaml

from torm.commands._common import add_parser
from torm.errors import UnknownNameError

#: name -> ("module:Class", which command reads it).
CONFIGS: dict[str, tuple[str, str]] = {
    "trial": ("torm.pipeline:TrialConfig", "torm trial, and every trial of torm bench (--set)"),
    "reconstruct": ("torm.reconstruction.api:ReconstructionConfig", "torm reconstruct; trial key 'reconstruction'"),
    "capture": ("sim.cameras.rig:CameraRigConfig", "torm capture (the simulated camera rig)"),
    "bench": ("torm.bench.spec:BenchConfig", "torm bench (its flags set these)"),
    "train-segmenter": ("torm.segmentation.training.run:SegTrainingSpec", "torm train-segmenter (data + train)"),
    "hardware": ("torm.hardware.config:HardwareConfig", "--hardware-config of torm trial/bench --backend real"),
    "env:pick": ("torm.env.pick_env:PickEnvConfig", "gymnasium.make('torm/TormPick-v0', **options)"),
    "env:grasp_select": ("torm.env.grasp_select_env:GraspSelectEnvConfig",
                         "gymnasium.make('torm/TormGraspSelect-v0', **options)"),
}


def config_class(name: str) -> type:
    """The frozen config dataclass called ``name`` (``segment:<segmenter>`` for a segmenter's)."""
    if name.startswith("segment:"):
        from torm.segmentation import segmenter_config_class

        return segmenter_config_class(name.split(":", 1)[1])
    if name not in CONFIGS:
        from torm.segmentation import SEGMENTERS

        raise UnknownNameError("config", name, [*CONFIGS, *(f"segment:{s}" for s in SEGMENTERS)])
    module, _, cls = CONFIGS[name][0].partition(":")
    return getattr(importlib.import_module(module), cls)


def _type_name(tp: Any) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return " | ".join(_type_name(a) for a in args)
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in args)
    if origin is not None:
        inner = ", ".join("..." if a is Ellipsis else _type_name(a) for a in args)
        return f"{getattr(origin, '__name__', str(origin))}[{inner}]"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def flat_keys(cls: type, instance: Any, prefix: str = "") -> list[tuple[str, str, Any]]:
    """(dotted key, type, default) of every leaf field of the dataclass ``cls`` (nested configs expanded)."""
    from torm.config import to_dict

    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        value = getattr(instance, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            out += flat_keys(type(value), value, key + ".")
        else:
            out.append((key, _type_name(hints[f.name]), to_dict(value)))
    return out


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "config", __doc__, help="list configs, show their keys and defaults")
    sub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    pl = sub.add_parser("list", help="config names and the commands that read them")
    pl.set_defaults(func=run_list)
    ps = sub.add_parser("show", help="defaults of a config as YAML (or --keys: one dotted key per line)")
    ps.add_argument("name", metavar="NAME", help="config name (torm config list)")
    ps.add_argument("--keys", action="store_true", help="one 'key: type = default' line per leaf key")
    ps.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="apply overrides first (checks them: unknown keys list the valid ones)")
    ps.set_defaults(func=run_show)


def run_list(args: argparse.Namespace) -> int:
    from torm.segmentation import SEGMENTERS

    for name, (_, used_by) in CONFIGS.items():
        print(f"{name:18s} {used_by}")
    print(f"{'segment:NAME':18s} torm segment --segmenter NAME, trial key 'segmentation.options' "
          f"(NAME: {', '.join(SEGMENTERS)})")
    return 0


def _unvalidated_defaults(cls: type) -> Any:
    """An instance of ``cls`` holding its field defaults, without running its validation (for display only)."""
    obj = object.__new__(cls)
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            value = f.default
        elif f.default_factory is not dataclasses.MISSING:
            value = f.default_factory()
        else:
            value = None
        object.__setattr__(obj, f.name, value)
    return obj


def run_show(args: argparse.Namespace) -> int:
    from torm import config as cfgmod
    from torm.errors import ConfigError

    cls = config_class(args.name)
    try:
        instance = cfgmod.from_dict(cls, {}, args.overrides, where=args.name)
    except ConfigError as exc:
        if args.overrides:
            raise
        # Some configs have keys without a usable default (e.g. the real robot's host): show them anyway.
        print(f"# the defaults alone are not a valid {args.name} config: {exc}")
        instance = _unvalidated_defaults(cls)
    if args.keys:
        for key, tp, default in flat_keys(cls, instance):
            text = yaml.safe_dump(default, default_flow_style=True).strip().removesuffix("...").strip()
            print(f"{key}: {tp} = {text}")
    else:
        print(f"# {args.name}: {CONFIGS.get(args.name, ('', 'torm segment'))[1]}")
        print(yaml.safe_dump(cfgmod.to_dict(instance), sort_keys=False).rstrip())
    return 0
