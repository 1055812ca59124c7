"""One test per fault found by the adversarial test of 2026-12-05 (issue 42): each is refused with a named
error before any work, reported once with the value used, or stopped cleanly."""

from __future__ import annotations

import json
import os
import sys
import textwrap
import time
from pathlib import Path

import pytest

from torm.bench import BenchConfig, run_benchmark
from torm.bench.identity import code_version, package_files_hash
from torm.bench.results import read_results
from torm.bench.runner import check_workers_fit
from torm.cli import main as cli
from torm.errors import ConfigError, HardwareError
from torm.execution.pick_config import check_grip_force
from torm.pipeline import TrialConfig, run_trial
from torm.resources import check_trial_fits, trial_bytes

TESTS_DIR = str(Path(__file__).resolve().parent)
GIB = 1 << 30


@pytest.fixture
def fake_importable(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (TESTS_DIR, os.environ.get("PYTHONPATH")) if p))


# -- sizes bounded from a memory estimate before any work --------------------------------------------------------
def test_a_billion_views_is_refused_before_the_backend_opens(monkeypatch):
    import torm.pipeline as pipeline

    monkeypatch.setattr(pipeline, "make_backend", lambda c: pytest.fail("the backend must not be built"))
    t = time.monotonic()
    with pytest.raises(ConfigError, match=r"capture.n_views=1000000000 .* needs about .* GiB .* fewer views"):
        run_trial(TrialConfig(scenario="rw1", capture=pipeline.CaptureSettings(n_views=10**9)))
    assert time.monotonic() - t < 5.0


def test_trial_estimate_scales_with_views_and_resolution():
    assert trial_bytes(100, 0.5) - trial_bytes(50, 0.5) == 50 * 640 * 360 * 32
    check_trial_fits(50, 0.5, available=4 * GIB)  # the default fits a small machine
    with pytest.raises(ConfigError, match="capture.scale=50"):
        check_trial_fits(50, 50.0, available=24 * GIB)


def test_ten_thousand_workers_are_refused_with_the_count_that_fits():
    resolved = {"capture": {"n_views": 50, "scale": 0.5}}
    with pytest.raises(ConfigError, match=r"--workers 10000 .* use --workers 14 or fewer"):
        check_workers_fit(BenchConfig(workers=10000), resolved, available=20 * GIB)
    check_workers_fit(BenchConfig(workers=2), resolved, available=20 * GIB)
    with pytest.raises(ConfigError, match="at most 1024 Ray tasks"):
        check_workers_fit(BenchConfig(workers=10000, engine="ray"), resolved)


# -- clamps: errors before work, or one warning with the value used ---------------------------------------------
class _Gripper:
    force_range_n = (20.0, 235.0)


@pytest.mark.parametrize("force", [1e-7, 1e12])
def test_grip_force_outside_the_gripper_range_is_an_error(force):
    with pytest.raises(ConfigError, match=r"pick.grip_force=.* outside the gripper's pad force range 20-235 N"):
        check_grip_force(force, _Gripper())
    check_grip_force(130.0, _Gripper())
    check_grip_force(1e12, object())  # a gripper without a stated range is not checked


@pytest.mark.slow
def test_trial_with_an_impossible_grip_force_stops_before_the_capture():
    from torm.execution.pick_config import PickConfig

    t = time.monotonic()
    with pytest.raises(ConfigError, match="pick.grip_force=1e-07 N"):
        run_trial(TrialConfig(scenario="rw1", method="oracle", pick=PickConfig(grip_force=1e-7)))
    assert time.monotonic() - t < 60.0


def test_sim_gripper_warns_once_with_the_force_it_commands(caplog):
    from sim.backend import SimBackend
    from sim.world import build_world

    backend = SimBackend(build_world("rw1", 0))
    try:
        g = backend.gripper
        with caplog.at_level("WARNING", logger="sim.backend"):
            g.move(g.max_width, 0.1, 1e12)
            g.move(g.max_width, 0.1, 1e12)
        assert g.grip_report()["requested_n"] == 1e12 and g.grip_report()["commanded_n"] == 235.0
        warned = [r.getMessage() for r in caplog.records if "outside the 20-235 N range" in r.getMessage()]
        assert len(warned) == 1 and "235 N is commanded" in warned[0]
    finally:
        backend.close()


# -- tracebacks become named errors ------------------------------------------------------------------------------
def test_negative_seed_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        cli(["trial", "--seed", "-1"])
    assert exc.value.code == 2 and "-1 is negative" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="seed must be a non-negative integer"):
        TrialConfig(seed=-1)
    with pytest.raises(ConfigError, match="base_seed"):
        BenchConfig(base_seed=-1)


@pytest.mark.parametrize("argv", [["capture", "--scenario", "rw1", "--views", "2"], ["reconstruct", "CAP"]])
def test_output_under_a_file_is_refused_before_the_work(tmp_path, capsys, argv):
    afile = tmp_path / "afile"
    afile.write_text("x")
    argv = [a.replace("CAP", str(tmp_path)) for a in argv]
    t = time.monotonic()
    assert cli([*argv, "--out", str(afile / "sub")]) == 2
    err = capsys.readouterr().err
    assert f"{afile} is a file, not a folder" in err and "Traceback" not in err
    assert time.monotonic() - t < 10.0


# -- the backend opens inside the guarded block -------------------------------------------------------------------
class _FakeBackend:
    def __init__(self) -> None:
        self.closed = False
        self.gripper = _Gripper()

    def close(self) -> None:
        self.closed = True


def test_a_failure_right_after_the_backend_opened_closes_it(monkeypatch):
    import torm.pipeline as pipeline

    made: list[_FakeBackend] = []
    monkeypatch.setattr(pipeline, "make_backend", lambda c: made.append(_FakeBackend()) or made[-1])
    with pytest.raises(Exception):  # noqa: B017 - an unwritable recording: whatever the recorder raises
        run_trial(TrialConfig(scenario="rw1"), record="/proc/no/such/dir/x.rrd")
    assert made and made[0].closed
    # a backend that fails while opening is not masked by the clean-up
    monkeypatch.setattr(pipeline, "make_backend", lambda c: (_ for _ in ()).throw(HardwareError("no arm")))
    with pytest.raises(HardwareError, match="no arm"):
        run_trial(TrialConfig(scenario="rw1"))


# -- a run identity that covers the installed code without git ----------------------------------------------------
def test_package_hash_changes_when_an_installed_file_changes(tmp_path, monkeypatch):
    pkg = tmp_path / "fakepkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "success.py").write_text("LIFT_M = 0.25\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    h1 = package_files_hash(("fakepkg",))
    assert package_files_hash(("fakepkg",)) == h1
    (pkg / "success.py").write_text("LIFT_M = 0.20\n")
    assert package_files_hash(("fakepkg",)) != h1
    assert len(code_version()["files_sha256"]) == 64


def test_resume_after_a_code_change_without_git_is_refused(tmp_path, monkeypatch, fake_importable):
    import torm.bench.identity as identity

    monkeypatch.setattr(identity, "git_state", lambda cwd=None: {"commit": None, "dirty": None, "diff_sha256": None})
    cfg = BenchConfig(suite="rw", scenarios=("rw1",), trials=1, trial_fn="bench_fake_trials:run")
    run_benchmark(cfg, tmp_path / "r", progress=False)
    monkeypatch.setattr(identity, "package_files_hash", lambda packages=identity.CODE_PACKAGES: "0" * 64)
    from torm.errors import BenchmarkError

    with pytest.raises(BenchmarkError, match="files_sha256"):
        run_benchmark(cfg, tmp_path / "r", progress=False)


# -- runner details ------------------------------------------------------------------------------------------------
def test_complete_last_row_without_newline_is_kept_not_rerun(tmp_path, fake_importable):
    cfg = BenchConfig(suite="rw", scenarios=("rw1",), trials=2, trial_fn="bench_fake_trials:run")
    out = tmp_path / "r"
    run_benchmark(cfg, out, progress=False)
    res = out / "results.jsonl"
    res.write_bytes(res.read_bytes().rstrip(b"\n"))  # the write stopped between the row and its newline
    s = run_benchmark(cfg, out, progress=False)
    assert s["ran"] == 0 and s["already_done"] == 2
    assert res.read_bytes().endswith(b"\n") and len(read_results(res).rows) == 2
    assert not list(out.glob("results.jsonl.truncated-*"))


def test_corrupt_middle_line_is_reported_once(tmp_path, fake_importable):
    cfg = BenchConfig(suite="rw", scenarios=("rw1",), trials=3, trial_fn="bench_fake_trials:run")
    out = tmp_path / "r"
    run_benchmark(cfg, out, progress=False)
    res = out / "results.jsonl"
    lines = res.read_bytes().split(b"\n")
    lines[1] = b'{"key": "rw/rw1/1/torm", "broken'
    res.write_bytes(b"\n".join(lines))
    s1 = run_benchmark(cfg, out, progress=False)
    assert any("corrupted" in r for r in s1["repairs"]) and s1["ran"] == 1  # the damaged trial runs again
    saved = list(out.glob("results.jsonl.corrupt-*"))
    assert len(saved) == 1 and b"broken" in saved[0].read_bytes()
    s2 = run_benchmark(cfg, out, progress=False)
    assert not s2["repairs"] and s2["ran"] == 0
    assert len(read_results(res).rows) == 3


def test_worker_stopped_by_sigint_is_terminated_not_an_error(tmp_path, fake_importable):
    cfg = BenchConfig(suite="rw", scenarios=("rw1",), trials=1, trial_fn="bench_fake_trials:run",
                      overrides=("fake.sigint=rw1/0",))
    run_benchmark(cfg, tmp_path / "r", progress=False)
    row = read_results(tmp_path / "r" / "results.jsonl").rows[0]
    assert row["failure"] == "terminated" and row["message"].startswith("stopped by SIGINT")


def test_records_show_the_grip_force_actually_used():
    """Under ``measured`` the saved config holds the drawn pad force, and ``config_used`` says what replaced what."""
    code = textwrap.dedent("""
        import json
        from torm.pipeline import TrialConfig, WorldSettings, run_trial
        r = run_trial(TrialConfig(scenario="rw1", method="oracle", world=WorldSettings(realism="measured")))
        print(json.dumps({"cfg": r["config"]["pick"]["grip_force"], "used": r["config_used"]}))
    """)
    import subprocess

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600,
                         env={**os.environ, "MUJOCO_GL": "egl"})
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    used = got["used"]["pick.grip_force"]
    assert used["configured"] == 130.0 and got["cfg"] == used["used"] == used["drawn"] != 130.0
