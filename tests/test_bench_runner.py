"""The benchmark runner on the local pool with a fake trial function (torm.bench.runner).

Covers: one row per trial, determinism, isolation (timeout, crash, segfault, exceptions), resume
after SIGKILL of the runner, refusal of a changed config, --fresh, grid extension and recordings.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from torm.bench import BenchConfig, build_grid, run_benchmark
from torm.bench.results import comparable, read_manifest, read_results
from torm.errors import BenchmarkError

TESTS_DIR = str(Path(__file__).resolve().parent)
FAKE = "bench_fake_trials:run"


@pytest.fixture(autouse=True)
def _fake_importable(monkeypatch):
    """Worker processes import the fake trial module from tests/."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (TESTS_DIR, os.environ.get("PYTHONPATH")) if p))


def _cfg(**kw):
    base = {"suite": "rw", "scenarios": ("rw1", "rw3"), "trials": 2, "methods": ("torm", "depth"), "workers": 2,
            "trial_fn": FAKE, "timeout_s": 20.0}
    base.update(kw)
    return BenchConfig(**base)


def _rows(out):
    return {r["key"]: r for r in read_results(Path(out) / "results.jsonl").rows}


def test_runs_every_trial_once_and_is_deterministic(tmp_path):
    cfg = _cfg()
    s1 = run_benchmark(cfg, tmp_path / "a", progress=False)
    s2 = run_benchmark(_cfg(workers=1), tmp_path / "b", progress=False)  # other order, same results
    assert s1["ran"] == s2["ran"] == 8
    a, b = _rows(tmp_path / "a"), _rows(tmp_path / "b")
    assert set(a) == {s.key for s in build_grid(cfg)}
    assert len((tmp_path / "a" / "results.jsonl").read_text().splitlines()) == 8
    for key in a:
        assert comparable(a[key]) == comparable(b[key])
        assert a[key]["status"] == "ok" and a[key]["run"]["engine"] == "pool"
    r = a["rw/rw3/1/depth"]
    assert r["seed"] == build_grid(cfg)[-1].seed
    assert [o["name"] for o in r["objects"]] == ["cylinder", "hexagonal_prism"]
    assert s1["objects"] == sum(x["n_objects"] for x in a.values())
    # running the same command again does nothing and duplicates nothing
    s3 = run_benchmark(cfg, tmp_path / "a", progress=False)
    assert s3["ran"] == 0 and s3["already_done"] == 8
    assert len((tmp_path / "a" / "results.jsonl").read_text().splitlines()) == 8
    man = read_manifest(tmp_path / "a")
    assert [s["trials_run"] for s in man["sessions"]] == [8, 0]
    assert all(s["status"] == "finished" for s in man["sessions"]) and man["grid"]["n_trials"] == 8


def test_failures_become_rows_and_the_run_continues(tmp_path):
    cfg = _cfg(methods=("torm",), scenarios=("rw1", "rw3", "rw4"), trials=2, timeout_s=3.0, overrides=(
        "fake.hang=rw1/0", "fake.crash=rw1/1", "fake.segv=rw3/0", "fake.raise=rw3/1", "fake.physics=rw4/0",
        "fake.blowup=rw4/1"))
    t0 = time.monotonic()
    s = run_benchmark(cfg, tmp_path / "r", progress=False)
    assert time.monotonic() - t0 < 30
    rows = _rows(tmp_path / "r")
    assert s["ran"] == 6 and len(rows) == 6
    hang = rows["rw/rw1/0/torm"]
    assert (hang["status"], hang["failure"]) == ("timeout", "timeout")
    assert 2.5 < hang["run"]["wall_s"] < 15
    assert [o["outcome"] for o in hang["objects"]] == ["timeout"] and hang["n_success"] == 0
    crash = rows["rw/rw1/1/torm"]
    assert (crash["status"], crash["failure"]) == ("crashed", "crashed") and "exited with code 3" in crash["message"]
    segv = rows["rw/rw3/0/torm"]
    assert segv["failure"] == "crashed" and "SIGSEGV" in segv["message"]
    assert [o["outcome"] for o in segv["objects"]] == ["crashed", "crashed"]  # both objects count as failed
    err = rows["rw/rw3/1/torm"]
    assert (err["status"], err["failure"]) == ("error", "error") and "RuntimeError: fake failure" in err["message"]
    assert "bench_fake_trials.py" in err["traceback"]
    assert rows["rw/rw4/0/torm"]["failure"] == "physics_error" and rows["rw/rw4/0/torm"]["status"] == "error"
    blow = rows["rw/rw4/1/torm"]
    assert (blow["status"], blow["failure"]) == ("ok", "physics_error")
    # logs of failed trials are kept
    assert Path(segv["run"]["log"]).exists() and Path(hang["run"]["log"]).exists()
    assert s["failure_categories_this_session"] == {"timeout": 1, "crashed": 2, "error": 1, "physics_error": 2}


def _worker_pids(marker: str) -> list[int]:
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if "torm.bench.worker" in cmd and marker in cmd:
                pids.append(int(d.name))
    return pids


def test_sigkilled_run_resumes_with_exactly_one_row_per_trial(tmp_path):
    out = tmp_path / "run"
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    cmd = [sys.executable, "-m", "torm.cli", "bench", "--suite", "rw", "--scenario", "rw1,rw2,rw3", "--trials", "3",
           "--method", "torm", "--workers", "2", "--out", str(out), "--trial-fn", FAKE, "--set", "fake.sleep_s=0.4",
           "--no-progress"]
    env = {**os.environ, "TMPDIR": str(scratch)}  # worker job files live here: lets us find the workers
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    results = out / "results.jsonl"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if results.exists() and len(results.read_bytes().splitlines()) >= 2:
            break
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    n_before = len(read_results(results).rows)
    assert 2 <= n_before < 9
    # orphaned workers notice their parent died and exit (no CPU burnt for nobody)
    deadline = time.monotonic() + 10
    while _worker_pids(str(scratch)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _worker_pids(str(scratch)) == []
    with open(results, "ab") as f:  # as if the kill had hit in the middle of an append
        f.write(b'{"key": "rw/rw2/2/torm", "sta')
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["already_done"] == n_before and summary["ran"] == 9 - n_before
    lines = results.read_text().splitlines()
    keys = [json.loads(x)["key"] for x in lines]
    assert len(keys) == 9 and sorted(keys) == sorted(f"rw/rw{i}/{t}/torm" for i in (1, 2, 3) for t in range(3))
    assert len(list(out.glob("results.jsonl.truncated-*"))) == 1
    sessions = read_manifest(out)["sessions"]
    assert [s["status"] for s in sessions] == ["killed", "finished"]  # marked when the next bench resumed
    repairs = "\n".join(summary["repairs"])
    assert "session 1" in repairs and "killed mid-run" in repairs  # the summary lists every repair it made
    assert "incomplete last line" in repairs and "stale lock" in repairs and f"pid {proc.pid}" in repairs


def test_changed_config_is_refused_with_the_difference(tmp_path):
    out = tmp_path / "r"
    run_benchmark(_cfg(trials=1), out, progress=False)
    with pytest.raises(BenchmarkError) as exc:
        run_benchmark(_cfg(trials=1, overrides=("fake.sleep_s=0.01",), timeout_s=7.0), out, progress=False)
    msg = str(exc.value)
    assert "bench.overrides: [] -> ['fake.sleep_s=0.01']" in msg and "bench.timeout_s: 20.0 -> 7.0" in msg
    assert "--fresh" in msg
    assert len(_rows(out)) == 4  # nothing touched
    # extending the grid is not a config change: only the new trials run
    s = run_benchmark(_cfg(trials=2), out, progress=False)
    assert s["ran"] == 4 and len(_rows(out)) == 8
    # --fresh moves the old results aside and starts over
    s = run_benchmark(_cfg(trials=1, overrides=("fake.sleep_s=0.01",)), out, fresh=True, progress=False)
    assert s["ran"] == 4 and len(_rows(out)) == 4
    old = list(out.glob("old-*"))
    assert len(old) == 1 and len(read_results(old[0] / "results.jsonl").rows) == 8
    assert (old[0] / "manifest.json").exists()


def test_results_without_manifest_are_refused(tmp_path):
    (tmp_path / "results.jsonl").write_text('{"key": "x"}\n')
    with pytest.raises(BenchmarkError, match="--fresh"):
        run_benchmark(_cfg(), tmp_path, progress=False)


def test_recordings_kept_for_failures_only(tmp_path):
    cfg = _cfg(methods=("torm",), scenarios=("rw1",), trials=4, record="failures")
    run_benchmark(cfg, tmp_path / "f", progress=False)
    rows = _rows(tmp_path / "f")
    kept = {p.name for p in (tmp_path / "f" / "recordings").glob("*.rrd")}
    failed = {k for k, r in rows.items() if r["n_success"] < r["n_objects"]}
    assert failed and failed != set(rows)  # the fake method fails some of these trials, not all
    assert kept == {k.replace("/", "__") + ".rrd" for k in failed}
    for k, r in rows.items():
        assert (r["run"]["recording"] is not None) == (k in failed)
    run_benchmark(_cfg(methods=("torm",), scenarios=("rw1",), trials=4, record="all"), tmp_path / "a", progress=False)
    assert len(list((tmp_path / "a" / "recordings").glob("*.rrd"))) == 4


def test_changed_default_refuses_resume_with_a_diff(tmp_path, monkeypatch):
    """The identity is the fully resolved trial config: a default that changed between two invocations (no
    override changed) is refused, and so is a different code version."""
    import bench_fake_resolved

    from torm.bench import identity as ident_mod

    out = tmp_path / "r"
    cfg = _cfg(trials=1, scenarios=("rw1",), methods=("torm",), trial_fn="bench_fake_resolved:run")
    run_benchmark(cfg, out, progress=False)
    man = read_manifest(out)
    assert man["identity"]["trial_config"]["pick"]["grip_force"] == 130.0
    code = man["identity"]["code"]
    assert set(code) == {"git", "files_sha256", "packages"} and "numpy" in code["packages"]
    monkeypatch.setitem(bench_fake_resolved.DEFAULTS, "pick", {"grip_force": 40.0})
    with pytest.raises(BenchmarkError, match=r"trial_config\.pick\.grip_force: 130\.0 -> 40\.0"):
        run_benchmark(cfg, out, progress=False)
    monkeypatch.setitem(bench_fake_resolved.DEFAULTS, "pick", {"grip_force": 130.0})
    real = ident_mod.code_version()
    monkeypatch.setattr(ident_mod, "code_version", lambda: {**real, "git": {**real["git"], "commit": "0" * 40}})
    with pytest.raises(BenchmarkError, match=r"code\.git\.commit: .* -> '0000"):
        run_benchmark(cfg, out, progress=False)
    monkeypatch.setattr(ident_mod, "code_version", lambda: real)
    assert run_benchmark(cfg, out, progress=False)["already_done"] == 1  # the original config and code resume


def test_default_trial_identity_holds_every_resolved_field():
    from torm.bench.identity import run_identity
    from torm.bench.runner import bench_identity
    from torm.bench.trial import check_overrides

    cfg = BenchConfig(suite="rw", overrides=("capture.n_views=4",))
    ident = run_identity(bench_identity(cfg, check_overrides(cfg.overrides)), check_overrides(cfg.overrides))
    tc = ident["trial_config"]
    assert tc["pick"]["grip_force"] == 130.0 and tc["success"]["slip_tolerance"] == 0.02  # defaults, not overrides
    assert tc["capture"]["n_views"] == 4 and "overrides" not in ident["bench"]
    assert ident["bench"] == {"suite": "rw", "trial_fn": "torm.bench.trial:run_spec", "base_seed": 0,
                              "timeout_s": 1800.0}


def test_second_bench_on_the_same_folder_is_refused(tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "torm.cli", "bench", "--suite", "rw", "--scenario", "rw1", "--trials", "6",
           "--method", "torm", "--workers", "1", "--out", str(out), "--trial-fn", FAKE, "--set", "fake.sleep_s=1.0",
           "--no-progress", "--stop-grace", "5"]  # >= 6 s of trials: still running while the others try
    first = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (out / "manifest.json").exists():
            time.sleep(0.05)
        with pytest.raises(BenchmarkError, match=f"in use by another torm bench: pid {first.pid} on "):
            run_benchmark(_cfg(scenarios=("rw1",), trials=6, methods=("torm",), workers=1,
                               overrides=("fake.sleep_s=1.0",)), out, progress=False)
        second = subprocess.run(cmd, capture_output=True, text=True, timeout=60)  # the CLI says so once
        assert second.returncode == 2 and second.stderr.count(f"pid {first.pid}") == 1
    finally:
        first.send_signal(signal.SIGTERM)
        _, err = first.communicate(timeout=60)
    assert first.returncode == 130, err  # stopped cleanly by SIGTERM
    sessions = read_manifest(out)["sessions"]
    assert [s["status"] for s in sessions] == ["interrupted"] and (out / ".lock").read_text() == ""
    # the folder is free again (a clean stop leaves no stale lock); a smaller grid resumes without a config change
    s = run_benchmark(_cfg(scenarios=("rw1",), trials=1, methods=("torm",), workers=1, timeout_s=1800.0,
                           overrides=("fake.sleep_s=1.0",)), out, progress=False)
    assert s["ran"] + s["already_done"] == 1 and not any("stale" in r for r in s["repairs"])


def test_retry_failed_replaces_a_crashed_row_and_keeps_it_as_history(tmp_path):
    marker = tmp_path / "crashed-once"
    cfg = _cfg(scenarios=("rw1",), trials=2, methods=("torm",), workers=1, overrides=(f"fake.crash_once={marker}",))
    out = tmp_path / "r"
    run_benchmark(cfg, out, progress=False)
    rows = _rows(out)
    crashed = [k for k, r in rows.items() if r["status"] == "crashed"]
    assert len(crashed) == 1 and "exited with code 3" in rows[crashed[0]]["message"]
    assert run_benchmark(cfg, out, progress=False)["ran"] == 0  # a plain resume keeps the crashed row
    s = run_benchmark(cfg, out, progress=False, retry="failed")
    assert s["retried"] == crashed and s["ran"] == 1
    assert s["history_rows"] == 1  # the crashed row is history now, counted in the summary of the retry
    res = read_results(out / "results.jsonl")
    new = {r["key"]: r for r in res.rows}[crashed[0]]
    assert new["status"] == "ok" and new["attempt"] == 2 and new["retry_of"]["status"] == "crashed"
    assert [r["key"] for r in res.history] == crashed and res.history[0]["status"] == "crashed"
    assert len((out / "results.jsonl").read_text().splitlines()) == 3 and not res.duplicates
    assert run_benchmark(cfg, out, progress=False, retry="failed")["ran"] == 0  # nothing failed any more
    with pytest.raises(Exception, match="retry"):
        run_benchmark(cfg, out, progress=False, retry="everything")


def test_ray_that_cannot_start_is_a_named_error_with_the_fix():
    from torm.bench.ray_engine import _init_ray
    from torm.errors import BenchmarkError

    class NoStore:
        def init(self, **kw):
            raise OSError("[Errno 12] Cannot allocate memory: mmap of the object store failed")

    with pytest.raises(BenchmarkError, match=r"Ray could not start a local Ray with 2 worker\(s\).*"
                                             r"RAY_DEFAULT_OBJECT_STORE_MAX_MEMORY_BYTES.*--engine pool"):
        _init_ray(NoStore(), None, 2)
