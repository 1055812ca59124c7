"""Rerun trial recordings: the outcome text, the saved layout, and best-effort mode for the benchmark runner."""

from __future__ import annotations

import numpy as np
import pytest

from torm.viz import TrialRecorder, outcome_markdown, trial_blueprint


def test_outcome_markdown_lists_every_object():
    record = {"scenario": "rw3", "seed": 2, "method": "torm", "failure": None,
              "context": {"method": "torm", "segmenter": "gt", "realism": "measured", "renderer": None},
              "objects": [{"object_id": 1, "name": "cylinder", "outcome": "success", "message": ""},
                          {"object_id": 2, "name": "hexagonal_prism", "outcome": "slipped_during_lift",
                           "message": "slipped 31 mm | during lift"}]}
    text = outcome_markdown(record)
    assert "rw3 seed 2: torm" in text and "**1/2 objects picked**" in text
    assert "| 2: hexagonal_prism | slipped_during_lift | slipped 31 mm / during lift |" in text
    assert "realism: `measured`" in text and "renderer" not in text  # None entries left out


def test_blueprint_builds():
    bp = trial_blueprint(n_image_views=2)
    assert bp is not None


def test_best_effort_recorder_swallows_errors(tmp_path, caplog):
    class Broken:
        model = None  # scene() on this fails

    strict = TrialRecorder(str(tmp_path / "a.rrd"))
    with pytest.raises(AttributeError):
        strict.scene(Broken())
    strict.close()
    lenient = TrialRecorder(str(tmp_path / "b.rrd"), best_effort=True)
    lenient.scene(Broken())  # logged, not raised
    lenient.step(0.0, np.eye(4))
    lenient.finish({"objects": []})
    lenient.close()
    assert "_scene failed" in caplog.text


@pytest.mark.slow
def test_every_panel_of_the_layout_is_logged(tmp_path):
    """The saved layout shows only views whose images were logged (no blank panel), and the time-series panel
    has the gripper opening, the pad force, the TCP error and every object's height."""
    from torm import config
    from torm.pipeline import TrialConfig, run_trial

    rec = TrialRecorder(str(tmp_path / "t.rrd"))
    paths: set[str] = set()
    log = rec.rec.log

    def spy(path, *args, **kwargs):
        paths.add(path)
        return log(path, *args, **kwargs)

    rec.rec.log = spy
    trial = config.from_dict(TrialConfig, {"scenario": "rw1", "method": "oracle"},
                             overrides=["capture.n_views=6", "capture.scale=0.25"])
    run_trial(trial, record=rec)
    assert len(rec.image_views) == 2
    for i in rec.image_views:
        assert f"world/capture/view_{i:03d}/rgb" in paths and f"world/capture/view_{i:03d}/mask" in paths
    assert "outcome" in paths
    assert {"signals/gripper_opening_m", "signals/pad_force_n", "signals/tcp_error_mm"} <= paths
    assert "signals/object_height_m/1_cylinder" in paths
    assert "events" in paths  # the pick's phases, beside the time series
    assert (tmp_path / "t.rrd").stat().st_size > 10_000
