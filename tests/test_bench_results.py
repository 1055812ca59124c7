"""Crash-safe results files and manifests (torm.bench.results)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from torm.bench.results import (
    append_row,
    comparable,
    diff_dicts,
    move_aside,
    read_manifest,
    read_results,
    repair_tail,
    write_json_atomic,
)
from torm.errors import BenchmarkError


def _rows(n):
    return [{"key": f"rw/rw1/{i}/torm", "n_success": i % 2, "value": float(i) / 3} for i in range(n)]


def test_append_and_read_roundtrip_strict_json(tmp_path):
    p = tmp_path / "results.jsonl"
    for r in _rows(3):
        append_row(p, r)
    append_row(p, {"key": "x", "arr": np.arange(3), "nan": float("nan"), "np": np.float32(1.5), "t": (1, 2)})
    lines = p.read_bytes().split(b"\n")
    assert lines[-1] == b"" and len(lines) == 5  # one line per row, newline-terminated
    for raw in lines[:-1]:
        json.loads(raw, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    res = read_results(p)
    assert [r["key"] for r in res.rows] == [r["key"] for r in _rows(3)] + ["x"]
    assert res.rows[3] == {"key": "x", "arr": [0, 1, 2], "nan": None, "np": 1.5, "t": [1, 2]}
    assert not res.problems and not res.truncated


def test_truncated_last_line_is_dropped_and_repaired(tmp_path, caplog):
    p = tmp_path / "results.jsonl"
    for r in _rows(3):
        append_row(p, r)
    with open(p, "ab") as f:
        f.write(b'{"key": "rw/rw1/3/torm", "n_suc')  # an interrupted append
    with caplog.at_level(logging.WARNING):
        res = read_results(p)
    assert res.truncated and len(res.rows) == 3 and res.bad_lines == []
    assert "line 4 is incomplete" in res.problems[0] and "line 4" in caplog.text
    saved = repair_tail(p)
    assert saved is not None and saved.read_bytes() == b'{"key": "rw/rw1/3/torm", "n_suc'
    assert p.read_bytes().endswith(b"\n") and len(read_results(p).rows) == 3
    assert repair_tail(p) is None
    append_row(p, _rows(5)[4])  # appending after the repair gives a clean file
    res = read_results(p)
    assert [r["key"] for r in res.rows][-1] == "rw/rw1/4/torm" and not res.problems


def test_corrupted_middle_line_reported_with_line_number(tmp_path, caplog):
    p = tmp_path / "results.jsonl"
    rows = _rows(4)
    for r in rows[:2]:
        append_row(p, r)
    with open(p, "ab") as f:
        f.write(b'{"key": "rw/rw1/9/torm", "oops\x00 garbage\n')
    for r in rows[2:]:
        append_row(p, r)
    with caplog.at_level(logging.WARNING):
        res = read_results(p)
    assert res.bad_lines == [3]
    assert [r["key"] for r in res.rows] == [r["key"] for r in rows]  # the valid lines are kept
    assert "line 3 is corrupted" in res.problems[0] and "line 3" in caplog.text
    with pytest.raises(BenchmarkError, match="line 3"):
        read_results(p, strict=True)


def test_duplicate_keys_keep_the_first(tmp_path):
    p = tmp_path / "results.jsonl"
    append_row(p, {"key": "a", "v": 1})
    append_row(p, {"key": "a", "v": 2})
    res = read_results(p)
    assert res.rows == [{"key": "a", "v": 1}] and res.duplicates == ["a"]


def test_manifest_atomic_write_and_errors(tmp_path):
    write_json_atomic(tmp_path / "manifest.json", {"config": {"suite": "rw"}, "x": float("inf")})
    assert read_manifest(tmp_path) == {"config": {"suite": "rw"}, "x": None}
    assert not list(tmp_path.glob("*.tmp"))
    assert read_manifest(tmp_path / "missing") is None
    (tmp_path / "manifest.json").write_text("{broken")
    with pytest.raises(BenchmarkError, match="not valid JSON"):
        read_manifest(tmp_path)


def test_move_aside_keeps_everything(tmp_path):
    (tmp_path / "results.jsonl").write_text('{"key": "a"}\n')
    (tmp_path / "manifest.json").write_text("{}")
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "a.log").write_text("log")
    dest = move_aside(tmp_path)
    assert dest is not None and dest.parent == tmp_path and dest.name.startswith("old-")
    assert (dest / "results.jsonl").read_text() == '{"key": "a"}\n' and (dest / "logs" / "a.log").exists()
    assert not (tmp_path / "results.jsonl").exists()
    assert move_aside(tmp_path) is None


def test_diff_and_comparable():
    assert diff_dicts({"a": 1, "b": {"c": [1]}}, {"a": 1, "b": {"c": [2]}, "d": 0}) == [
        "b.c: [1] -> [2]", "d: '<unset>' -> 0"]
    row = {"key": "k", "run": {"wall_s": 3}, "timings": {"total": 1}, "versions": {},
           "perception": {"reconstruction_s": 2.0, "iou": 0.9}, "objects": [{"pick": {"duration_s": 1, "ok": 1}}]}
    assert comparable(row) == {"key": "k", "perception": {"iou": 0.9}, "objects": [{"pick": {"ok": 1}}]}


def test_a_later_attempt_replaces_a_row_and_the_old_one_becomes_history(tmp_path):
    p = tmp_path / "results.jsonl"
    append_row(p, {"key": "a", "status": "crashed"})
    append_row(p, {"key": "b", "status": "ok"})
    append_row(p, {"key": "a", "status": "timeout", "attempt": 2})
    append_row(p, {"key": "a", "status": "ok", "attempt": 3})
    append_row(p, {"key": "a", "status": "ok", "attempt": 3})  # the same attempt twice: a real duplicate
    res = read_results(p)
    assert [(r["key"], r["status"]) for r in res.rows] == [("a", "ok"), ("b", "ok")]  # file order of first sight
    assert [r["status"] for r in res.history] == ["crashed", "timeout"] and res.duplicates == ["a"]


def test_run_lock_refuses_a_second_holder_and_detects_a_stale_one(tmp_path):
    import json as _json
    import os
    import subprocess
    import sys

    from torm.bench.lock import RunLock

    with RunLock(tmp_path) as first:
        assert first.stale is None
        with pytest.raises(BenchmarkError, match=f"in use by another torm bench: pid {os.getpid()} on "):
            RunLock(tmp_path).acquire()
    assert (tmp_path / ".lock").read_text() == ""  # released: no holder left behind
    # a holder that died without releasing (its record is still there): taken over and reported
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (tmp_path / ".lock").write_text(_json.dumps({"pid": int(dead.stdout), "host": "h", "started": "t"}))
    with RunLock(tmp_path) as lock:
        assert lock.stale["pid"] == int(dead.stdout)
