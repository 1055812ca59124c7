"""One vocabulary on the command line: every command that takes a segmenter, renderer, depth model or realism
profile offers the same choices, read from :mod:`torm.vocabulary`; ``torm trial --method`` takes a plug-in."""

from __future__ import annotations

import argparse

import pytest

from torm import vocabulary as vocab
from torm.cli import build_parser

#: flag -> (the shared choices, the commands that take it)
SHARED = {
    "--segmenter": (vocab.SEGMENTERS, ("trial", "bench", "segment", "reconstruct")),
    "--renderer": (vocab.RENDERERS, ("trial", "bench", "capture")),
    "--depth-model": (vocab.DEPTH_MODELS, ("trial", "bench", "capture")),
    "--realism": (vocab.REALISM_PROFILES, ("trial", "bench")),
}


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


@pytest.mark.parametrize(("flag", "command"), [(f, c) for f, (_, cmds) in SHARED.items() for c in cmds])
def test_every_command_offers_the_shared_choices(flag, command):
    sub = _subparsers()[command]
    action = next((a for a in sub._actions if flag in a.option_strings), None)
    assert action is not None, f"torm {command} has no {flag}"
    assert tuple(action.choices) == SHARED[flag][0], (command, flag, action.choices)


def test_no_other_command_takes_a_shared_flag_with_other_choices():
    for name, sub in _subparsers().items():
        for a in sub._actions:
            for flag, (choices, _) in SHARED.items():
                if flag in a.option_strings and a.choices is not None:
                    assert tuple(a.choices) == choices, (name, flag)


def test_trial_flags_reach_the_config_and_method_takes_a_plugin_name():
    from torm.commands.trial import trial_config_from_args

    sub = _subparsers()["trial"]
    args = sub.parse_args(["--renderer", "pbr", "--depth-model", "statistical", "--realism", "measured",
                           "--segmenter", "difference", "--set", "capture.reference=true"])
    cfg = trial_config_from_args(args)
    assert (cfg.capture.renderer, cfg.capture.depth_model, cfg.world.realism) == ("pbr", "statistical", "measured")
    assert cfg.segmentation.segmenter == "difference"
    args = sub.parse_args(["--method", "my_lab.methods:make_method"])
    assert args.method == "my_lab.methods:make_method"  # no fixed choice list refuses a plug-in
