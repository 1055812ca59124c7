"""`torm capture` and `torm scenes` end to end on the real scenario worlds (small renders)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from torm.capture import load_capture
from torm.cli import main


def _run(capsys, argv: list[str]) -> tuple[int, dict]:
    rc = main(argv)
    out = capsys.readouterr().out
    return rc, json.loads(out) if out.strip() else {}


def test_capture_command_writes_a_loadable_folder(tmp_path: Path, capsys):
    out = tmp_path / "rw3"
    rc, summary = _run(capsys, ["capture", "--scenario", "rw3", "--seed", "1", "--views", "6", "--width", "160",
                                "--height", "90", "--out", str(out), "--rrd", str(tmp_path / "cap.rrd")])
    assert rc == 0
    assert (tmp_path / "cap.rrd").stat().st_size > 10_000
    assert summary["views"] == 6 and (summary["width"], summary["height"]) == (160, 90)
    assert 0.0 <= summary["occlusion_ratio"] <= 1.0
    cap = load_capture(out)
    assert cap.scenario == "rw3" and cap.seed == 1 and cap.object_ids == (1, 2)
    assert cap.object_names == ("cylinder", "hexagonal_prism")
    assert cap.table_height == 0.0 and cap.workspace_bounds.shape == (2, 3)
    assert cap.metadata["occlusion"]["occlusion_ratio"] == pytest.approx(summary["occlusion_ratio"], rel=1e-5)
    assert set(cap.metadata["occlusion"]["per_object_occluded_share"]) == {"1", "2"}
    # both objects are seen; both are glass, so the sensor depth never equals the ideal depth on them
    masks = cap.masks()
    assert set(np.unique(masks)) == {0, 1, 2}
    v = cap.views[0]
    on_obj = v.mask > 0
    assert np.all(v.sensor_depth[on_obj] > v.depth[on_obj])


def test_scenes_list_check_show(tmp_path: Path, capsys):
    rc, listing = _run(capsys, ["scenes", "list", "--suite", "rw"])
    assert rc == 0
    names = [s["name"] for s in listing["scenarios"]]
    assert names[:3] == ["rw1", "rw2", "rw3"]
    assert {"cylinder", "cup"} <= {o["name"] for o in listing["objects"]}
    rc, report = _run(capsys, ["scenes", "check", "--scenario", "rw1", "--scenario", "rw4", "--seconds", "0.2"])
    assert rc == 0 and report["ok"] and report["checked"] == 2
    rrd = tmp_path / "show.rrd"
    rc, shown = _run(capsys, ["scenes", "show", "--scenario", "rw4", "--views", "2", "--width", "160", "--height",
                              "90", "--out", str(tmp_path / "show"), "--rrd", str(rrd)])
    assert rc == 0 and len(shown["files"]) == 8
    assert all(Path(f).stat().st_size > 0 for f in shown["files"])
    assert rrd.stat().st_size > 10_000


def test_unknown_scenario_is_an_error(tmp_path: Path, capsys):
    rc = main(["capture", "--scenario", "nope", "--out", str(tmp_path / "x")])
    assert rc == 2
    assert "valid choices" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["scenes", "check", "--scenario", "nope"]])
def test_scenes_check_rejects_unknown_names(argv, capsys):
    assert main(argv) == 2
