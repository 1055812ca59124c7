"""benchmarks/stress.py end to end on the fake trial function: one run folder per (group, level) plus the ideal
world, through the resumable runner, with the stress overrides; the curves' JSON, Markdown and plot."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent


def test_stress_sweep_writes_curves_per_factor_group(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(TESTS), os.environ.get("PYTHONPATH")) if p))
    cmd = [sys.executable, str(ROOT / "benchmarks" / "stress.py"), "--trials", "1", "--scenario", "rw1",
           "--levels", "1,2", "--groups", "contact,calibration,grip_force", "--workers", "1", "--trial-fn",
           "bench_fake_trials:run", "--runs-dir", str(tmp_path / "runs"), "--results-dir", str(tmp_path / "res"),
           "--set", "capture.n_views=12"]
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    doc = json.loads((tmp_path / "res" / "stress.json").read_text())
    assert set(doc["summary"]) == {"contact", "calibration", "grip_force"}
    assert list(doc["summary"]["contact"]) == ["ideal", "x1", "x2"]
    assert doc["summary"]["contact"]["x2"]["objects"]["n"] == 1
    assert "pad_friction 0.15" in doc["values"]["contact"]["2"]  # 0.30 (worst sourced) / 2
    assert "table_height_error 0.002 m" in doc["values"]["calibration"]["2"]  # every parameter of the group
    # 20 N (worst sourced) / 2 lies below the 2F-85's 20 N floor: clipped, it would test nothing, so it is not run
    assert doc["summary"]["grip_force"]["x1"]["objects"]["n"] == 1
    assert "floor" in doc["summary"]["grip_force"]["x2"]["skipped"]
    assert not (tmp_path / "runs" / "grip_force_x2").exists()
    man = json.loads((tmp_path / "runs" / "calibration_x2" / "manifest.json").read_text())
    assert {"capture.n_views=12", "world.realism=stress", "world.stress=2", "world.factors=[calibration]"} <= set(
        man["config"]["overrides"])
    md = (tmp_path / "res" / "stress.md").read_text()
    assert "stress, not realism" in md and "| contact |" in md and "`capture.n_views=12`" in md
    assert "not run (below the gripper's 20 N floor)" in md
    assert (tmp_path / "res" / "stress.png").stat().st_size > 1000
