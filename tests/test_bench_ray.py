"""The Ray engine writes the same rows as the local pool (local Ray, fake trial function)."""

from __future__ import annotations

from pathlib import Path

from torm.bench import BenchConfig, build_grid, run_benchmark
from torm.bench.isolate import TrialJob
from torm.bench.results import comparable, read_results


def _rows(out):
    return {r["key"]: r for r in read_results(Path(out) / "results.jsonl").rows}


def test_ray_rows_equal_pool_rows(local_ray, tmp_path):
    kw = {"suite": "rw", "scenarios": ("rw1", "rw3"), "trials": 2, "methods": ("torm", "oracle"), "workers": 2,
          # only the hang may time out: a real oracle trial takes 3-5 s alone, and went past 15 s with the
          # machine's 2 cores shared by 5 busy processes (a segmenter training beside the suite): 45 s holds that
          "trial_fn": "bench_fake_trials:run", "timeout_s": 45.0,
          "overrides": ("fake.hang=rw1/1", "fake.segv=rw3/1", "fake.raise=rw3/0")}
    s_pool = run_benchmark(BenchConfig(**kw), tmp_path / "pool", progress=False)
    s_ray = run_benchmark(BenchConfig(engine="ray", **kw), tmp_path / "ray", progress=False)
    assert s_pool["ran"] == s_ray["ran"] == 8
    pool, rayr = _rows(tmp_path / "pool"), _rows(tmp_path / "ray")
    assert set(pool) == set(rayr) == {s.key for s in build_grid(BenchConfig(**kw))}
    for key in pool:
        assert comparable(pool[key]) == comparable(rayr[key]), key
        assert rayr[key]["run"]["engine"] == "ray" and pool[key]["run"]["engine"] == "pool"
    assert rayr["rw/rw1/1/torm"]["failure"] == "timeout"
    assert rayr["rw/rw3/1/oracle"]["failure"] == "crashed"
    assert rayr["rw/rw1/0/oracle"]["status"] == "ok"


def test_driver_cancels_a_task_past_its_deadline(local_ray, tmp_path):
    from torm.bench.ray_engine import ray_rows

    spec = build_grid(BenchConfig(suite="rw", scenarios=("rw1",), trials=1))[0]
    # the task's own limit (30 s) is far away; the driver's backstop (30 s + grace -28.5 s) fires first
    job = TrialJob(trial_fn="bench_fake_trials:run", overrides=("fake.hang=rw1/0",), timeout_s=30.0, engine="ray")
    rows = list(ray_rows([spec], job, workers=1, grace_s=-28.5, poll_s=0.2))
    assert len(rows) == 1 and rows[0]["failure"] == "timeout" and rows[0]["key"] == spec.key
    assert rows[0]["run"]["wall_s"] < 15
