"""One CLI vocabulary (issue 41): every command takes ``--config`` and ``--set``; ``torm trial`` prints a short
summary on a terminal and the JSON record with ``--json`` or into a pipe."""

from __future__ import annotations

import json
import sys

import pytest

import torm.pipeline
from torm.cli import _leaves, apply_options_config, build_parser
from torm.cli import main as cli
from torm.commands.trial import format_summary
from torm.errors import ConfigError


def test_every_command_takes_config_and_set():
    parser = build_parser()
    leaves = _leaves(parser)
    assert len(leaves) >= 12
    for leaf in leaves:
        opts = {o for a in leaf._actions for o in a.option_strings}
        assert {"--config", "--set"} <= opts, leaf.prog


def test_options_yaml_sets_a_commands_options_and_the_command_line_wins(tmp_path):
    cfg = tmp_path / "bench.yaml"
    cfg.write_text("trials: 3\nmethod: [oracle]\nworkers: 2\nset: ['capture.n_views=3']\n")
    parser = build_parser()
    argv = ["bench", "--out", str(tmp_path / "run"), "--config", str(cfg), "--workers", "1"]
    args = apply_options_config(parser, argv, parser.parse_args(argv))
    assert (args.trials, args.method, args.workers, args.overrides) == (3, ["oracle"], 1, ["capture.n_views=3"])
    parser = build_parser()  # a list given on the command line replaces the file's list (not appended to it)
    argv = ["bench", "--out", str(tmp_path / "run"), "--config", str(cfg), "--method", "depth"]
    assert apply_options_config(parser, argv, parser.parse_args(argv)).method == ["depth"]
    parser = build_parser()
    argv = ["report", str(tmp_path), "--set", "out=somewhere"]
    assert apply_options_config(parser, argv, parser.parse_args(argv)).out == "somewhere"
    parser = build_parser()
    argv = ["report", str(tmp_path), "--set", "outt=x"]
    with pytest.raises(ConfigError, match=r"unknown option\(s\) \['outt'\]; valid: out"):
        apply_options_config(parser, argv, parser.parse_args(argv))


RECORD = {"summary": {"scenario": "rw3", "seed": 0, "method": "torm", "success": "2/3",
                      "outcomes": {"1:cylinder": "success", "2:heart": "slipped_during_lift", "3:cube": "success"},
                      "phantom_attempts": 1, "failure": None, "total_s": 42.0},
          "context": {"realism": "measured", "segmenter": "learned", "renderer": "pbr", "depth_model": "ideal"},
          "timings": {"capture": 20.5, "reconstruction": 12.0, "execution": 8.0, "setup": 1.5, "total": 42.0}}


def test_terminal_summary_names_what_ran_and_each_outcome():
    text = format_summary(RECORD)
    assert text.splitlines()[0] == "trial rw3 seed 0 method torm: 2/3 objects picked, 1 phantom attempt(s)"
    assert "ran: realism measured, segmenter learned, renderer pbr, depth_model ideal" in text
    assert "2:heart" in text and "slipped_during_lift" in text
    assert "total 42.0 s (capture 20.5 s, reconstruction 12.0 s, execution 8.0 s)" in text
    assert len(text.splitlines()) <= 10


def test_trial_prints_json_into_a_pipe_and_a_summary_on_a_terminal(monkeypatch, capsys):
    monkeypatch.setattr(torm.pipeline, "run_trial", lambda cfg, record=None: RECORD)
    assert cli(["trial", "--scenario", "rw3"]) == 0
    assert json.loads(capsys.readouterr().out)["summary"]["success"] == "2/3"  # pytest's stdout is not a tty
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True)
    assert cli(["trial", "--scenario", "rw3"]) == 0
    assert capsys.readouterr().out.startswith("trial rw3 seed 0 method torm: 2/3 objects picked")
    assert cli(["trial", "--scenario", "rw3", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["summary"]["method"] == "torm"


def test_bench_shorthands_become_trial_overrides():
    from torm.commands.bench import trial_overrides

    parser = build_parser()
    args = parser.parse_args(["bench", "--out", "x", "--segmenter", "learned", "--renderer", "pbr", "--depth-model",
                              "statistical", "--realism", "ideal", "--views", "20", "--set", "capture.scale=0.25"])
    assert trial_overrides(args) == ("segmentation.segmenter=learned", "capture.renderer=pbr",
                                     "capture.depth_model=statistical", "world.realism=ideal", "capture.n_views=20",
                                     "capture.scale=0.25")
    assert "lab" in parser._subparsers._group_actions[0].choices["bench"].format_help()  # every suite is listed
    assert build_parser().parse_args(["capture", "--scenario", "rw1", "--out", "x"]).progress  # on by default


def test_old_option_names_still_work_and_say_they_are_deprecated(capsys):
    args = build_parser().parse_args(["trial", "--robot", "mini6_lg90", "--rrd", "x.rrd"])
    assert (args.robot_config, args.record) == ("mini6_lg90", "x.rrd")
    err = capsys.readouterr().err
    assert "--robot is deprecated" in err and "use --robot-config" in err and "--rrd is deprecated" in err
    build_parser().parse_args(["trial", "--robot-config", "mini6_lg90"])
    assert "deprecated" not in capsys.readouterr().err
