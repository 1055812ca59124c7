"""The real closed-loop trial through the benchmark runner: same seed, same result (smallest setting)."""

from __future__ import annotations

from pathlib import Path

import pytest

from torm.bench import BenchConfig, build_grid, run_benchmark
from torm.bench.results import comparable, read_manifest, read_results


@pytest.mark.slow
def test_real_trial_same_seed_same_row(tmp_path):
    # rw1 (one glass cylinder), oracle geometry, 2 views at quarter resolution: a few seconds per trial
    kw = {"suite": "rw", "scenarios": ("rw1",), "methods": ("oracle",), "trials": 1, "timeout_s": 300.0,
          "overrides": ("capture.n_views=2", "capture.scale=0.25")}
    run_benchmark(BenchConfig(**kw), tmp_path / "a", progress=False)
    # the second run also records: the recording wrapper must not change the trial
    run_benchmark(BenchConfig(record="all", **kw), tmp_path / "b", progress=False)
    a = read_results(tmp_path / "a" / "results.jsonl").rows
    b = read_results(tmp_path / "b" / "results.jsonl").rows
    assert len(a) == len(b) == 1
    ra, rb = a[0], b[0]
    assert ra["status"] == "ok", ra.get("message")
    spec = build_grid(BenchConfig(**kw))[0]
    assert ra["key"] == spec.key and ra["config"]["seed"] == spec.seed and ra["config"]["capture"]["n_views"] == 2
    assert ra["n_objects"] == 1 and ra["objects"][0]["name"] == "cylinder"
    assert set(ra["timings"]) >= {"setup", "capture", "reconstruction", "grasp_planning", "total"}
    assert comparable(ra) == comparable(rb)
    trial_config = read_manifest(tmp_path / "a")["trial_config"]  # the resolved base config
    assert {k: trial_config["capture"][k] for k in ("n_views", "scale")} == {"n_views": 2, "scale": 0.25}
    assert read_manifest(tmp_path / "a")["identity"]["trial_config"] == trial_config  # the run identity holds it
    rec = Path(rb["run"]["recording"])
    assert rec.exists() and rec.stat().st_size > 1000


def test_bad_override_is_refused_before_any_trial(tmp_path):
    from torm.errors import ConfigError

    with pytest.raises(ConfigError, match="n_veiws"):
        run_benchmark(BenchConfig(suite="rw", scenarios=("rw1",), overrides=("capture.n_veiws=3",)), tmp_path / "r",
                      progress=False)
    assert not (tmp_path / "r" / "results.jsonl").exists()
    with pytest.raises(ConfigError, match="no function"):
        run_benchmark(BenchConfig(suite="rw", trial_fn="torm.bench.trial:nope"), tmp_path / "r", progress=False)
