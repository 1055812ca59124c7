"""The command line: plain-text help with examples on every command, examples and --set keys that are valid,
consistent flag names (old spellings kept as aliases), --version, python -m torm, torm config show."""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys

import pytest
import yaml

from torm import __version__
from torm import config as cfgmod
from torm.cli import build_parser, main
from torm.commands.config import config_class

#: the config each command's --set applies to (torm config show NAME)
SET_TARGET = {"trial": "trial", "bench": "trial", "capture": "capture", "reconstruct": "reconstruct",
              "train-segmenter": "train-segmenter"}


def _leaf_parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
    for action in subs:
        for name, child in action.choices.items():
            yield path + (name,), child
            yield from ((p, c) for p, c in _leaf_parsers(child, path + (name,)) if p != path + (name,))


def _examples(text: str) -> list[list[str]]:
    """Example command lines of a help text ("    torm ..." lines, backslash continuations joined)."""
    out, current = [], None
    for line in text.splitlines():
        if current is not None:
            current += " " + line.strip()
        elif line.startswith("    torm "):
            current = line.strip()
        if current is not None and not current.endswith("\\"):
            out.append(shlex.split(current, comments=True)[1:])
            current = None
        elif current is not None:
            current = current[:-1]
    return out


def test_every_command_has_plain_text_help_with_examples_that_parse():
    parser = build_parser()
    commands = {path[0]: child for path, child in _leaf_parsers(parser) if len(path) == 1}
    assert {"trial", "bench", "capture", "reconstruct", "segment", "scenes", "report", "calibrate",
            "config"} <= set(commands)
    n_examples = 0
    for name, child in commands.items():
        text = child.format_help()
        assert "``" not in text and ":class:`" not in text and "::\n" not in text, f"raw RST in torm {name} --help"
        examples = _examples(text)
        assert examples, f"torm {name} --help has no example"
        assert any(argv[0] == name for argv in examples), f"torm {name} --help has no example of itself"
        for argv in examples:
            args = parser.parse_args(argv)  # exits (SystemExit) on an invalid example
            assert args.command == argv[0]
            overrides = getattr(args, "overrides", [])
            if argv[0] == "reconstruct":  # segmentation[.KEY]: the --segmenter's own config (checked when it loads)
                overrides = [o for o in overrides if not o.startswith(("segmentation.", "segmentation="))]
            if overrides and argv[0] in SET_TARGET:  # the --set keys exist in that command's config
                cfgmod.from_dict(config_class(SET_TARGET[argv[0]]), {}, overrides)
            if overrides and argv[0] == "segment":
                cfgmod.from_dict(config_class(f"segment:{args.segmenter}"), {}, overrides)
            n_examples += 1
    assert n_examples >= 15


def test_every_help_text_renders():
    for path, child in _leaf_parsers(build_parser()):
        assert child.format_help().strip(), path


@pytest.mark.parametrize("argv, key, value", [
    (["capture", "--scenario", "rw1", "--out", "x", "--rrd", "a.rrd"], "record", "a.rrd"),
    (["capture", "--scenario", "rw1", "--out", "x", "--record", "a.rrd"], "record", "a.rrd"),
    (["scenes", "show", "--scenario", "rw1", "--out", "x", "--robot", "none"], "robot_config", "none"),
    (["scenes", "check", "--robot-config", "none"], "robot_config", "none"),
    (["trial", "--robot", "my.yaml"], "robot_config", "my.yaml"),
    (["bench", "--out", "r", "--robot", "my.yaml"], "robot_config", "my.yaml"),
    (["reconstruct", "cap", "--out", "o", "--rrd", "r.rrd"], "record", "r.rrd"),
])
def test_old_flag_names_are_aliases(argv, key, value):
    assert getattr(build_parser().parse_args(argv), key) == value


def test_logging_flags_before_or_after_the_command():
    p = build_parser()
    a = p.parse_args(["-q", "trial"])
    assert a.quiet and a.verbose == 0
    a = p.parse_args(["trial", "-vv"])
    assert not a.quiet and a.verbose == 2
    a = p.parse_args(["scenes", "list", "-q"])
    assert a.quiet


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.strip() == f"torm {__version__}"
    res = subprocess.run([sys.executable, "-m", "torm", "--version"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.strip() == f"torm {__version__}"


def test_config_show_yaml_round_trips_and_keys_are_settable(capsys):
    from torm.pipeline import TrialConfig

    assert main(["config", "show", "trial"]) == 0
    data = yaml.safe_load(capsys.readouterr().out)
    assert cfgmod.from_dict(TrialConfig, data) == TrialConfig()
    assert main(["config", "show", "trial", "--keys"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "reconstruction.grid_res: int = 48" in lines
    for line in lines:  # every key printed is a valid --set key with its printed default
        key, _, rest = line.partition(": ")
        default = rest.split(" = ", 1)[1]
        cfgmod.from_dict(TrialConfig, {}, [f"{key}={default}"])
    assert main(["config", "show", "segment:noisy", "--keys"]) == 0
    assert "preset: str = paper" in capsys.readouterr().out
    assert main(["config", "show", "nonsense"]) == 2
    assert "valid choices" in capsys.readouterr().err


def test_building_the_parser_imports_no_heavy_package():
    """``torm --help`` answers without torch, MuJoCo or the scene library (they took 7-12 s to import): every choice
    list comes from :mod:`torm.vocabulary`. Start-up time itself: ``benchmarks/results/cli_startup.md``."""
    import subprocess
    import sys

    probe = ("import sys; from torm.cli import build_parser; build_parser(); "
             "print(','.join(m for m in ('torch', 'mujoco', 'trimesh', 'mitsuba', 'onnxruntime', 'sim.scenes') "
             "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"building the parser imported {out}"
