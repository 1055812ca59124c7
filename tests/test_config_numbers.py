"""Config numbers (YAML 1.2 / JSON spellings), NaN/inf refused in every float field, and the CLI's error and
output-path handling (torm.config, torm.cli, torm trial --out, torm bench --out)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from dataclasses import dataclass, field

import pytest

from torm.config import InfFloat, check_finite, from_dict, load, parse_yaml
from torm.errors import ConfigError
from torm.pipeline import TrialConfig


@pytest.mark.parametrize("text, value", [
    ("1e-7", 1e-7), ("1E5", 1e5), ("-2.5e+3", -2500.0), ("+1e3", 1000.0), (".5", 0.5), ("-.5", -0.5),
    ("1.", 1.0), ("1.0e-7", 1e-7), ("1_000.5", 1000.5), ("12", 12), ("0x1F", 31), ("0o17", 15)])
def test_yaml_and_json_number_spellings_are_numbers(text, value):
    got = parse_yaml(text)
    assert got == value and type(got) is type(value)
    assert parse_yaml(json.dumps({"v": value})) == {"v": value}  # JSON's own spelling reads back the same


def test_non_numbers_stay_strings():
    for text in ("1e", "e5", "1.2.3", "rw3", "0o8"):
        assert isinstance(parse_yaml(text), str), text


def test_1e_minus_7_is_accepted_in_a_file_and_an_override(tmp_path):
    p = tmp_path / "trial.yaml"
    p.write_text("success:\n  slip_tolerance: 1e-7\n")
    assert load(TrialConfig, p).success.slip_tolerance == 1e-7
    cfg = from_dict(TrialConfig, {}, ["success.slip_tolerance=1e-7", "capture.scale=5e-1"])
    assert cfg.success.slip_tolerance == 1e-7 and cfg.capture.scale == 0.5


@pytest.mark.parametrize("spelling", [".nan", ".NaN", ".inf", "-.inf"])
def test_slip_tolerance_nan_and_inf_are_refused(spelling, tmp_path):
    with pytest.raises(ConfigError, match=r"success\.slip_tolerance: (NaN|-?inf)"):
        from_dict(TrialConfig, {}, [f"success.slip_tolerance={spelling}"])
    p = tmp_path / "t.yaml"
    p.write_text(f"success: {{slip_tolerance: {spelling}}}\n")
    with pytest.raises(ConfigError, match="slip_tolerance"):
        load(TrialConfig, p)


def test_every_float_field_is_covered_without_asking():
    """Every float of every section, inside tuples too, also for an instance built in Python."""
    from torm.execution.success import SuccessCriteria

    with pytest.raises(ConfigError, match=r"place_area\[1\]\[0\]: NaN"):
        from_dict(TrialConfig, {}, ["place_area=[[0.2, -0.3], [.nan, 0.3]]"])
    with pytest.raises(ConfigError, match=r"TrialConfig\.success\.slip_tolerance: NaN"):
        TrialConfig(success=SuccessCriteria(slip_tolerance=math.nan))  # the min() check alone lets NaN through
    with pytest.raises(ConfigError, match="timeout_s: inf"):
        from torm.bench.spec import BenchConfig

        BenchConfig(timeout_s=math.inf)


@dataclass(frozen=True)
class _Inner:
    gain: float = 1.0
    limit: InfFloat = math.inf  # explicitly allowed to be infinite ("no limit")
    bounds: tuple[InfFloat, ...] = (0.0, math.inf)


@dataclass(frozen=True)
class _Outer:
    inner: _Inner = field(default_factory=_Inner)
    maybe: float | None = None

    def __post_init__(self) -> None:
        check_finite(self)


def test_inf_only_where_a_field_opts_in_and_nan_never():
    cfg = from_dict(_Outer, {"inner": {"limit": float("-inf"), "bounds": [1e-3, ".inf"]}}, ["inner.bounds=[0, .inf]"])
    assert cfg.inner.limit == -math.inf and cfg.inner.bounds == (0.0, math.inf)
    with pytest.raises(ConfigError, match=r"inner\.limit: NaN"):
        from_dict(_Outer, {}, ["inner.limit=.nan"])
    with pytest.raises(ConfigError, match=r"inner\.gain: inf"):
        from_dict(_Outer, {}, ["inner.gain=.inf"])
    with pytest.raises(ConfigError, match=r"maybe: NaN"):
        from_dict(_Outer, {}, ["maybe=.nan"])
    assert from_dict(_Outer, {}, ["maybe=2e-3"]).maybe == 0.002
    with pytest.raises(ConfigError, match=r"_Outer\.inner\.gain: NaN"):
        _Outer(inner=_Inner(gain=math.nan))  # check_finite in __post_init__: direct construction too
    _Outer(inner=_Inner(limit=math.inf))


def _torm(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "torm.cli", *args], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "MUJOCO_GL": "egl"}, **kw)


def test_cli_prints_a_config_error_once(capsys):
    from torm.cli import main

    done = _torm("bench", "--timeout", "nan", "--out", "unused", "--no-progress")  # a real process: logging too
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.count("argument --timeout: 'nan' is not a finite number") == 1, done.stderr
    assert main(["trial", "--set", "success.slip_tolerance=.nan"]) == 2
    assert capsys.readouterr().err.count("slip_tolerance: NaN") == 1


def test_trial_out_is_checked_before_the_trial_runs(tmp_path, monkeypatch, capsys):
    import torm.pipeline
    from torm.cli import main

    def must_not_run(*a, **k):
        raise AssertionError("the trial ran although --out cannot be written")

    monkeypatch.setattr(torm.pipeline, "run_trial", must_not_run)
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main(["trial", "--out", str(blocker / "result.json")]) == 2  # a file where a folder must be
    err = capsys.readouterr().err
    assert err.count("--out") == 1 and "cannot write" in err
    assert main(["trial", "--record", str(tmp_path)]) == 2 and "is a folder" in capsys.readouterr().err


def test_trial_result_is_printed_when_writing_it_fails(tmp_path, monkeypatch, capsys):
    import torm.pipeline
    from torm.cli import main

    out = tmp_path / "res" / "result.json"

    def fake_trial(config, record=None):
        (tmp_path / "res").rmdir()  # the folder vanishes while the trial runs ...
        (tmp_path / "res").write_text("")  # ... and a file takes its place
        return {"scenario": config.scenario, "n_success": 1}

    monkeypatch.setattr(torm.pipeline, "run_trial", fake_trial)
    assert main(["trial", "--out", str(out)]) == 2
    cap = capsys.readouterr()
    assert json.loads(cap.out) == {"scenario": "rw3", "n_success": 1}
    assert "writing failed" in cap.err and "printed on stdout" in cap.err and cap.err.count("--out") == 1
    ok = tmp_path / "ok" / "r.json"
    monkeypatch.setattr(torm.pipeline, "run_trial", lambda config, record=None: {"n_success": 2})
    assert main(["trial", "--out", str(ok)]) == 0 and json.loads(ok.read_text()) == {"n_success": 2}


def test_bench_out_that_cannot_be_created_is_a_clear_error(tmp_path, capsys):
    from torm.cli import main

    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main(["bench", "--out", str(blocker / "run"), "--scenario", "rw1", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "cannot create the run folder" in err and err.count("run folder") == 1
