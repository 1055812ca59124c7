"""benchmarks/bench_throughput.py runs a grid through the runner and writes throughput.json/.md (fake trials)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTS_DIR = str(Path(__file__).resolve().parent)


def test_throughput_script_writes_results(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (TESTS_DIR, os.environ.get("PYTHONPATH")) if p)}
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_throughput.py"), "--scenario", "rw1,rw3,rw4",
           "--method", "torm,depth", "--workers", "2", "--trial-fn", "bench_fake_trials:run", "--set",
           "fake.sleep_s=0.2", "--run-dir", str(tmp_path / "run"), "--results-dir", str(tmp_path / "res"),
           "--no-progress"]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    res = json.loads((tmp_path / "res" / "throughput.json").read_text())
    assert res["trials"] == 6 and res["config"]["workers"] == 2
    # 6 trials of >= 0.2 s each on 2 workers: at most 6 / 0.6 s = 36000 trials/hour
    assert 0 < res["trials_per_hour"] < 36000
    torm = res["per_method"]["torm"]
    assert torm["trials"] == 3 and torm["stage_mean_s"]["reconstruction"] == 1.0 and torm["trial_total_mean_s"] == 4.0
    assert torm["worker_wall_mean_s"] >= 0.2 and torm["objects"] == 1 + 2 + 3
    md = (tmp_path / "res" / "throughput.md").read_text()
    assert f"**{res['trials_per_hour']} trials/hour**" in md and "| torm | 3 |" in md
    # run again: the run folder starts fresh (old rows moved aside, not deleted)
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((tmp_path / "res" / "throughput.json").read_text())["trials"] == 6
    assert len(list((tmp_path / "run").glob("old-*"))) == 1
