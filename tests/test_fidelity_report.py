"""benchmarks/fidelity.py end to end on the fake trial function: run folders through the runner, the tables
beside the paper's Table III with Wilson intervals, the failure modes, the sensitivity rows and the plot."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("fidelity")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(TESTS), os.environ.get("PYTHONPATH")) if p))
    cmd = [sys.executable, str(ROOT / "benchmarks" / "fidelity.py"), "--trials", "2", "--sensitivity-trials", "1",
           "--scenario", "rw1", "--scenario", "rw4", "--workers", "2", "--trial-fn", "bench_fake_trials:run",
           "--runs-dir", str(tmp / "runs"), "--results-dir", str(tmp / "res"), "--segmenter", "noisy"]
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    return tmp


def test_fidelity_writes_tables_beside_the_paper(report: Path) -> None:
    res = report / "res"
    doc = json.loads((res / "fidelity_seg-noisy.json").read_text())
    assert (res / "fidelity_seg-noisy.png").stat().st_size > 1000
    assert "segmentation.segmenter=noisy" in doc["config"]["overrides"]
    assert "world.realism=measured" in doc["config"]["overrides"]
    s = doc["summary"]
    rows = {e["scenario"]: e for e in s["scenarios"]}
    assert set(rows) == {"rw1", "rw4"}
    e = rows["rw4"]
    assert e["paper_torm"]["k"] == 9 and e["paper_torm"]["n"] == 10
    for m in ("torm", "oracle", "depth"):
        t = e[m]["trials"]
        assert t["n"] == 2 and 0.0 <= t["wilson95"][0] <= (t["rate"] or 0.0) <= t["wilson95"][1] <= 1.0
        assert e[m]["objects"]["n"] == 6  # 3 objects x 2 trials
    gap = e["gap_torm"]
    assert gap["newcombe95"][0] <= gap["sim_minus_paper"] <= gap["newcombe95"][1]
    assert s["objects"]["cylinder"]["paper_graspnet"] == {"k": 3, "n": 10, "rate": 0.3,
                                                          "wilson95": s["objects"]["cylinder"]["paper_graspnet"][
                                                              "wilson95"]}
    modes = [f["mode"] for f in s["failures"]]
    assert modes == ["slip", "displaced", "pruned", "not seen", "phantom", "other"]
    assert [f["paper_failed_trials"] for f in s["failures"]] == [2, 4, 3, 0, 0, 0]  # the paper's 9 failed trials
    settings = [x["setting"] for x in s["sensitivity"]]
    assert settings == ["ideal", "contact alone", "grip_force alone", "objects alone", "calibration alone",
                        "execution alone", "all (measured)"]
    md = (res / "fidelity_seg-noisy.md").read_text()
    for heading in ("Per scenario, in the paper's unit", "Per object", "Failure kinds beside the paper's",
                    "Sensitivity"):
        assert heading in md
    # every sensitivity run folder went through the resumable runner
    runs = report / "runs"
    assert (runs / "fidelity_seg-noisy" / "manifest.json").is_file()
    man = json.loads((runs / "fidelity_seg-noisy_sens_contact" / "manifest.json").read_text())
    assert "world.factors=[contact]" in man["config"]["overrides"]


def test_report_only_rewrites_without_running(report: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(TESTS))
    cmd = [sys.executable, str(ROOT / "benchmarks" / "fidelity.py"), "--trials", "2", "--sensitivity-trials", "1",
           "--scenario", "rw1", "--scenario", "rw4", "--trial-fn", "bench_fake_trials:run", "--report-only",
           "--runs-dir", str(report / "runs"), "--results-dir", str(report / "res2"), "--segmenter", "noisy"]
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    a = json.loads((report / "res" / "fidelity_seg-noisy.json").read_text())["summary"]["totals"]
    b = json.loads((report / "res2" / "fidelity_seg-noisy.json").read_text())["summary"]["totals"]
    assert a == b
