"""``torm report``: the tables hold the numbers of the rows; plots are written; problems are reported."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from torm.bench import BenchConfig, run_benchmark
from torm.bench.report import load_run, success_counts, throughput, trial_counts, write_report
from torm.bench.results import read_results
from torm.bench.stats import difference_interval, wilson_interval
from torm.errors import BenchmarkError

TESTS_DIR = str(Path(__file__).resolve().parent)


@pytest.fixture(scope="module")
def run_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    old = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (TESTS_DIR, old) if p)
    try:
        kw = {"suite": "rw", "scenarios": ("rw1", "rw3", "rw4"), "trials": 3, "methods": ("torm", "depth"),
              "workers": 2, "trial_fn": "bench_fake_trials:run", "timeout_s": 20.0}
        run_benchmark(BenchConfig(overrides=("fake.crash=rw3/2",), **kw), root / "a", progress=False)
        run_benchmark(BenchConfig(base_seed=7, **kw), root / "b", progress=False)
    finally:
        if old is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = old
    return root


def _table(md: str, first_header: str) -> list[list[str]]:
    """Rows of the first Markdown table whose header starts with ``first_header``."""
    lines = md.splitlines()
    start = next(i for i, x in enumerate(lines) if x.startswith(f"| {first_header} |"))
    out = []
    for x in lines[start + 2:]:
        if not x.startswith("|"):
            break
        out.append([c.strip() for c in x.strip("|").split("|")])
    return out


def _kn(k: int, n: int) -> str:
    lo, hi = wilson_interval(k, n)
    return f"{k}/{n} ({100 * k / n:.0f}% [{100 * lo:.0f}-{100 * hi:.0f}])"


def test_report_numbers_match_rows(run_dirs):
    summary = write_report([run_dirs / "a"])
    md = (run_dirs / "a" / "report.md").read_text()
    rows = read_results(run_dirs / "a" / "results.jsonl").rows
    table = _table(md, "Scenario")
    by_sc = {r[0]: r for r in table}
    assert set(by_sc) == {"rw1", "rw3", "rw4", "**all**"}
    header = next(x for x in md.splitlines() if x.startswith("| Scenario |"))
    cols = [c.strip() for c in header.strip("|").split("|")]
    assert cols == ["Scenario", "OCC", "Objects", "torm trials", "torm objects", "torm phantom / spurious",
                    "depth trials", "depth objects", "depth phantom / spurious"]
    for sc in ("rw1", "rw3", "rw4"):
        for m in ("torm", "depth"):
            sel = [r for r in rows if r["scenario"] == sc and r["method"] == m]
            k = sum(o["outcome"] == "success" for r in sel for o in r["objects"])
            n = sum(len(r["objects"]) for r in sel)
            assert by_sc[sc][cols.index(f"{m} objects")] == _kn(k, n)
            # the paper's unit: a trial counts when every object of the scene was picked
            kt = sum(r["status"] == "ok" and all(o["outcome"] == "success" for o in r["objects"]) for r in sel)
            assert by_sc[sc][cols.index(f"{m} trials")] == _kn(kt, len(sel))
    # rw3 torm: one crashed trial counts its two objects as failed
    assert sum(len(r["objects"]) for r in rows if r["scenario"] == "rw3" and r["method"] == "torm") == 6
    assert by_sc["rw1"][1] == "10%"  # OCC from perception.occlusion_ratio of the rows
    assert by_sc["rw4"][2].startswith("3 (ball, cube, toothpick_box)")
    k, n = success_counts(rows, None, "torm")
    assert by_sc["**all**"][cols.index("torm objects")] == f"**{_kn(k, n)}**"
    assert summary["runs"][0]["success"]["torm"] == {"k": k, "n": n}
    ph = sum(int(r.get("n_phantom_attempts") or 0) for r in rows if r["method"] == "torm")
    sp = sum(len(r.get("spurious_objects") or []) for r in rows if r["method"] == "torm")
    assert by_sc["**all**"][cols.index("torm phantom / spurious")] == f"**{ph} / {sp}**"
    kt, nt = trial_counts(rows, None, "torm")
    assert summary["runs"][0]["trial_success"]["torm"] == {"k": kt, "n": nt} and nt == 9
    # per-object table and the CSV export hold the same numbers
    per_obj = {(r[0], r[1]): r[2:] for r in _table(md.split("### Per object")[1], "Scenario")}
    sel = [r for r in rows if r["scenario"] == "rw3" and r["method"] == "depth"]
    k_cyl = sum(o["outcome"] == "success" for r in sel for o in r["objects"] if o["name"] == "cylinder")
    assert per_obj[("rw3", "cylinder")][1] == _kn(k_cyl, len(sel))
    csv_lines = (run_dirs / "a" / "table3.csv").read_text().splitlines()
    assert csv_lines[0] == "scenario,method,unit,k,n,rate,wilson95_low,wilson95_high"
    assert f"all,torm,trials,{kt},{nt}," in "\n".join(csv_lines)
    assert any(line.startswith(f"rw3,cylinder,depth,{k_cyl},{len(sel)},")
               for line in (run_dirs / "a" / "objects.csv").read_text().splitlines())
    # failure categories: one crashed trial per method (crash=rw3/2 hits both methods)
    fail = {r[0]: r[1:] for r in _table(md, "Trial failure")}
    assert fail == {"crashed": ["1", "1"]}
    outcome = {r[0]: r[1:] for r in _table(md, "Outcome")}
    assert outcome["crashed"] == ["2", "2"]
    assert int(outcome["success"][0]) == k
    # reconstruction: IoU only for torm rows, found/present summed
    rec = {(r[0], r[1]): r for r in _table(md.split("## Reconstruction")[1], "Scenario")}
    sel = [r for r in rows if r["scenario"] == "rw4" and r["method"] == "torm"]
    mean_iou = sum(r["perception"]["silhouette_iou_mean"] for r in sel) / len(sel)
    assert rec[("rw4", "torm")][3].startswith(f"{mean_iou:.3f}")
    assert rec[("rw4", "depth")][3] == "–"
    found = sum(r["perception"]["n_objects_found"] for r in sel)
    assert rec[("rw4", "torm")][5] == f"{found}/{3 * len(sel)}"
    # timing means (fake timings are fixed: total 4.0 s for torm)
    timing = {r[0]: r for r in _table(md, "Method | setup")}
    assert timing["torm"][1:9] == ["0.10", "0.20", "0.30", "1.00", "0.40", "2.00", "0.00", "4.00"]  # other = 0
    # throughput from the manifest session timestamps
    sess = throughput(load_run(run_dirs / "a"))
    assert len(sess) == 1 and sess[0]["trials"] == 18
    assert "trials/hour" in md
    for name in ("success_by_scenario.png", "iou_vs_outcome.png", "timing_stack.png"):
        data = (run_dirs / "a" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 2000
    html = (run_dirs / "a" / "report.html").read_text()
    assert "<table>" in html and "success_by_scenario.png" in html


def test_report_cli_compares_two_runs_and_reports_corrupted_lines(run_dirs, tmp_path):
    import shutil

    b = tmp_path / "b"
    shutil.copytree(run_dirs / "b", b)
    lines = (b / "results.jsonl").read_bytes().split(b"\n")
    lines[4] = b'{"key": "rw/rw1/1/depth", truncated garbage'
    (b / "results.jsonl").write_bytes(b"\n".join(lines))
    out = tmp_path / "cmp"
    done = subprocess.run([sys.executable, "-m", "torm.cli", "report", str(run_dirs / "a"), str(b), "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["runs"][1]["rows"] == 17
    assert any("line 5 is corrupted" in p for p in summary["runs"][1]["problems"])
    md = (out / "report.md").read_text()
    assert "line 5 is corrupted" in md
    cmp_rows = _table(md, "Scenario | Method")
    total = [r for r in cmp_rows if r[0] == "**all**" and r[1] == "torm"][0]
    rows_a, rows_b = read_results(run_dirs / "a" / "results.jsonl").rows, read_results(b / "results.jsonl").rows
    ka, na = success_counts(rows_a, None, "torm")
    kb, nb = success_counts(rows_b, None, "torm")
    d, lo, hi = difference_interval(kb, nb, ka, na)
    assert total[5:] == [_kn(ka, na), _kn(kb, nb), f"{100 * d:+.0f} [{100 * lo:+.0f}, {100 * hi:+.0f}]"]
    ta, tb = trial_counts(rows_a, None, "torm"), trial_counts(rows_b, None, "torm")
    assert total[2:4] == [_kn(*ta), _kn(*tb)]
    assert (out / "a_success_by_scenario.png").exists() and (out / "b_timing_stack.png").exists()
    assert (out / "a_table3.csv").exists() and (out / "b_objects.csv").exists()
    assert re.search(r"Throughput: A [\d.]+ trials/hour, B [\d.]+ trials/hour", md)


def test_report_errors(tmp_path):
    with pytest.raises(BenchmarkError, match="no results.jsonl"):
        write_report([tmp_path])
    with pytest.raises(BenchmarkError, match="two to compare"):
        write_report([tmp_path, tmp_path, tmp_path])


def test_report_header_names_what_ran_and_a_comparison_warns_on_different_worlds(run_dirs, tmp_path):
    import shutil

    from torm.bench.report import grid_difference, what_ran

    md = write_report([run_dirs / "a"], tmp_path / "one") and (tmp_path / "one" / "report.md").read_text()
    header = _table(md, "Method | Realism")
    assert ["torm", "measured", "–", "gt", "–", "–", "–", "mujoco", "–", "–", "ideal", "declared", "sim"] in header
    assert re.search(r"run identity [0-9a-f]{16}", md) and "config hash" not in md
    b = tmp_path / "b"
    shutil.copytree(run_dirs / "b", b)
    rows = [json.loads(x) for x in (b / "results.jsonl").read_text().splitlines()]
    for r in rows:
        r["context"]["realism"] = "ideal"
    (b / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    a_run, b_run = load_run(run_dirs / "a"), load_run(b)
    assert what_ran(b_run.rows)["torm"][0] == "ideal"
    assert "torm: realism A measured, B ideal" in grid_difference(a_run, b_run)
    write_report([run_dirs / "a", b], tmp_path / "cmp")
    md = (tmp_path / "cmp" / "report.md").read_text()
    assert "**Warning: the two runs differ in what they ran" in md and "realism A measured, B ideal" in md


def test_html_page_escapes_renders_bold_and_keeps_intervals_on_one_line():
    from torm.bench.report_html import to_html

    page = to_html([("h2", "A <b>tag</b>"), ("p", "**Warning:** `x` & y"),
                    ("table", ["Method", "Trials"], [["torm", "12/20 (60% [39-78])"]]),
                    ("img", "plot.png", "success by scenario")], "t")
    assert "A &lt;b&gt;tag&lt;/b&gt;" in page and "<b>Warning:</b> <code>x</code> &amp; y" in page
    assert "**" not in page and "white-space: nowrap" in page
    assert "<td>12/20 (60% [39-78])</td>" in page and '<img src="plot.png" alt="success by scenario">' in page


def test_report_lists_failed_trials_with_their_message_and_the_plugin_that_failed(run_dirs, tmp_path):
    import shutil

    from torm.bench.identity import grid_hash

    a = tmp_path / "a"
    shutil.copytree(run_dirs / "a", a)
    rows = [json.loads(x) for x in (a / "results.jsonl").read_text().splitlines()]
    crashed = [r for r in rows if r["status"] == "crashed"]
    assert len(crashed) == 2  # rw3 trial 2 of both methods
    for r in rows:  # the depth method becomes a plug-in that raised in one trial
        if r["method"] == "depth":
            r.setdefault("context", {}).update(method_source="entry point my_lab.methods:depth_v2",
                                               method_name="depth_v2", method_version="1.2.3")
            if r["scenario"] == "rw1" and r["trial"] == 0:
                r.update(status="error", failure="error",
                         message="ValueError: my_lab could not read the depth image\nTraceback (most recent ...")
    (a / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    write_report([a], tmp_path / "rep")
    md = (tmp_path / "rep" / "report.md").read_text()
    failed = _table(md, "Scenario | Trial | Method | Status")
    assert len(failed) == 3
    plugin_row = next(r for r in failed if r[0] == "rw1")
    assert plugin_row[2] == "depth (depth_v2 1.2.3)" and plugin_row[3] == "error"
    assert plugin_row[5] == "ValueError: my_lab could not read the depth image"  # the first line only
    crash_row = next(r for r in failed if r[0] == "rw3" and r[2] == "torm")
    assert crash_row[3] == "crashed" and crash_row[5] and "[log](" in crash_row[6]
    methods = _table(md, "Method | Source | Version")
    assert ["depth", "entry point my_lab.methods:depth_v2", "1.2.3", "antipodal (built-in)", "–"] in methods
    assert ["torm", "built-in (torm)", "(this code)", "antipodal (built-in)", "–"] in methods
    manifest = json.loads((a / "manifest.json").read_text())
    assert f"grid {manifest['grid']['hash'][:16]}" in md
    assert manifest["grid"]["hash"] == grid_hash(r["key"] for r in rows)
    assert grid_hash(["rw/rw1/0/torm"]) != grid_hash(["rw/rw1/0/torm", "rw/rw1/1/torm"])
    page = (tmp_path / "rep" / "report.html").read_text()
    assert '<div class="scroll"><table>' in page and "*trials*" not in page and '<a href="' in page
