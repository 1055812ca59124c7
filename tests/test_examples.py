"""The examples run: the Python-API trial picks its object, the bench YAML is a valid ``torm bench --config``."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_python_api_trial_example(capsys):
    spec = importlib.util.spec_from_file_location("python_api_trial", ROOT / "examples" / "python_api_trial.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    record = mod.main(["--scenario", "rw1", "--views", "6"])
    assert record["n_success"] == 1 and "rw1 (oracle): 1/1 objects picked" in capsys.readouterr().out


def test_bench_yaml_example_is_a_valid_bench_config(tmp_path):
    from torm.bench.spec import BenchConfig, parse_list
    from torm.cli import apply_options_config, build_parser

    parser = build_parser()
    argv = ["bench", "--config", str(ROOT / "examples" / "bench_night.yaml"), "--out", str(tmp_path / "r")]
    args = apply_options_config(parser, argv, parser.parse_args(argv))
    cfg = BenchConfig(suite=args.suite, trials=args.trials, methods=parse_list(args.method), workers=args.workers,
                      timeout_s=args.timeout, record=args.record, overrides=tuple(args.overrides))
    assert cfg.trials == 10 and cfg.methods == ("torm", "depth", "oracle") and cfg.record == "failures"
    assert "capture.depth_model=statistical" in cfg.overrides


@pytest.mark.parametrize("package", ["torm_plane_fill", "torm_scene_graspnet"])
def test_example_plugin_packages_pass_their_own_tests(package):
    """Each example plug-in is an installable package with its own tests; they run against this torm."""
    import os
    import subprocess
    import sys

    root = ROOT / "examples" / package
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root / "src"), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(root / "tests")],
                          cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert " passed" in proc.stdout
