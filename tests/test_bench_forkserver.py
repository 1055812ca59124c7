"""Trial workers forked from a preloaded server (torm.bench.forkserver) behave like spawned ones.

The runner tests (test_bench_runner.py, test_bench_stop.py) run with the default ``forkserver`` start method
and cover timeouts, crashes, segfaults, a SIGKILLed runner and the real arm's stop; here: the rows are the same
as with ``spawn``, the row says how its worker started, a server that is not safe to fork from is refused and
the trials fall back to ``spawn``, and the server leaves when its runner does.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from torm.bench import BenchConfig, build_grid, run_benchmark
from torm.bench.forkserver import Forkserver, ForkServerError
from torm.bench.isolate import THREAD_ENV
from torm.bench.results import read_results
from torm.errors import UnknownNameError

TESTS_DIR = str(Path(__file__).resolve().parent)
FAKE = "bench_fake_trials:run"


@pytest.fixture(autouse=True)
def _fake_importable(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (TESTS_DIR, os.environ.get("PYTHONPATH")) if p))


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.update({name: "1" for name in THREAD_ENV})
    return env


def _rows(out: Path) -> dict[str, dict]:
    return {r["key"]: r for r in read_results(out / "results.jsonl").rows}


def test_forked_workers_give_the_rows_spawned_ones_give(tmp_path):
    rows = {}
    for method in ("forkserver", "spawn"):
        cfg = BenchConfig(suite="rw", scenarios=("rw1", "rw3"), trials=2, methods=("torm",), workers=2,
                          trial_fn=FAKE, timeout_s=20.0, start_method=method, threads=1,
                          overrides=("fake.crash=rw3/1", "fake.raise=rw1/0"))
        run_benchmark(cfg, tmp_path / method, progress=False)
        rows[method] = _rows(tmp_path / method)
    assert {r["run"]["start_method"] for r in rows["forkserver"].values()} == {"forkserver"}
    assert {r["run"]["start_method"] for r in rows["spawn"].values()} == {"spawn"}
    strip = ("run", "traceback")
    for key, row in rows["spawn"].items():
        forked = rows["forkserver"][key]
        assert {k: v for k, v in forked.items() if k not in strip} == {k: v for k, v in row.items() if k not in strip}
    assert rows["forkserver"]["rw/rw3/1/torm"]["failure"] == "crashed"
    assert "exited with code 3" in rows["forkserver"]["rw/rw3/1/torm"]["message"]


def test_a_module_that_starts_a_thread_at_import_is_refused():
    with pytest.raises(ForkServerError, match="threads after its imports"):
        Forkserver(_env(), ("bench_fake_threaded",))


def test_trials_fall_back_to_spawn_when_the_server_is_refused(tmp_path, monkeypatch):
    starts = []
    real_init = Forkserver.__init__

    def counting_init(self, *args, **kwargs):
        starts.append(1)
        real_init(self, *args, **kwargs)

    monkeypatch.setattr(Forkserver, "__init__", counting_init)
    cfg = BenchConfig(suite="rw", scenarios=("rw1",), trials=3, methods=("torm",), workers=1, threads=1,
                      trial_fn="bench_fake_threaded:run", timeout_s=20.0)
    run_benchmark(cfg, tmp_path / "run", progress=False, validate=False)
    rows = list(_rows(tmp_path / "run").values())
    assert len(rows) == 3 and {r["run"]["start_method"] for r in rows} == {"spawn"}
    assert all("should have been refused" in r["message"] for r in rows)  # the trials ran (and raised), spawned
    assert len(starts) == 1  # a refused server is not started again for every trial


def test_unknown_start_method_is_a_named_error():
    with pytest.raises(UnknownNameError, match="forkserver, spawn"):
        BenchConfig(start_method="fork")


def test_the_server_leaves_when_its_runner_goes_away():
    server = Forkserver(_env(), ())
    assert server.failed_imports == {}  # every preload imports in this environment
    assert server.proc.stdin is not None
    server.proc.stdin.close()  # what a dead runner's pipe looks like
    assert server.proc.wait(timeout=10) == 0


def test_a_forked_worker_reports_its_signal(tmp_path):
    job = tmp_path / "job.json"
    result = tmp_path / "result.json"
    server = Forkserver(_env(), ())
    try:
        spec = build_grid(BenchConfig(scenarios=("rw1",), trial_fn=FAKE))[0]
        job.write_text(json.dumps({"spec": spec.as_dict(), "overrides": ["fake.hang=rw1/0"], "trial_fn": FAKE,
                                   "record_path": None, "result_path": str(result), "parent_pid": server.pid}))
        worker = server.start_worker(str(job), str(tmp_path / "log"), _env())
        with pytest.raises(subprocess.TimeoutExpired):
            worker.wait(timeout=0.5)
        worker.kill()
        assert worker.wait(timeout=10) == -9
        assert os.getpgid(server.pid) != os.getpgid(os.getpid())
    finally:
        server.close()
    assert not result.exists()


def test_more_than_one_thread_per_trial_spawns(tmp_path):
    cfg = BenchConfig(suite="rw", scenarios=("rw1",), trials=1, methods=("torm",), workers=1, threads=2,
                      trial_fn=FAKE, timeout_s=20.0)
    run_benchmark(cfg, tmp_path / "run", progress=False)
    (row,) = _rows(tmp_path / "run").values()
    assert row["run"]["start_method"] == "spawn" and row["status"] == "ok"


def test_a_dead_server_is_a_named_error(tmp_path):
    server = Forkserver(_env(), ())
    server.proc.kill()
    server.proc.wait()
    with pytest.raises(ForkServerError):
        server.start_worker(str(tmp_path / "job.json"), str(tmp_path / "log"), _env())


def test_a_forked_worker_has_devnull_as_stdin_and_its_log_as_stdout(tmp_path):
    """The child's fds 0-2 are /dev/null and the trial's log, not the server's pipes."""
    probe = tmp_path / "probe.py"
    probe.write_text("import os, sys\n"
                     "def run(spec, overrides=(), record_path=None):\n"
                     "    print('fd0', os.readlink('/proc/self/fd/0'), flush=True)\n"
                     "    print('stdin', repr(sys.stdin.read()), flush=True)\n"
                     "    return {'n_objects': 0, 'n_success': 0, 'objects': []}\n")
    server = Forkserver({**_env(), "PYTHONPATH": str(tmp_path)}, ())
    try:
        spec = build_grid(BenchConfig(scenarios=("rw1",), trial_fn=FAKE))[0]
        job, log = tmp_path / "job.json", tmp_path / "log"
        job.write_text(json.dumps({"spec": spec.as_dict(), "overrides": [], "trial_fn": "probe:run",
                                   "record_path": None, "result_path": str(tmp_path / "result.json"),
                                   "parent_pid": server.pid}))
        assert server.start_worker(str(job), str(log), {**_env(), "PYTHONPATH": str(tmp_path)}).wait(30) == 0
    finally:
        server.close()
    text = log.read_text()
    assert "fd0 /dev/null" in text and "stdin ''" in text
    assert json.loads((tmp_path / "result.json").read_text())["status"] == "ok"


def test_threads_are_counted_natively_and_unknown_counts_as_unsafe(monkeypatch):
    from torm.bench import forkserver

    assert forkserver.thread_count() >= 1  # pytest's own threads, native ones included

    def no_proc(path):
        raise FileNotFoundError(path)

    monkeypatch.setattr(forkserver.os, "listdir", no_proc)
    assert forkserver.thread_count() == 0  # never 1: the server would fork without knowing
