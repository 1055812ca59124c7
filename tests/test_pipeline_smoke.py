"""Closed-loop smoke trials through the pytest plugin (the same way a lab guards its own changes)."""

from __future__ import annotations

import pytest

from torm.errors import ConfigError, UnknownNameError


@pytest.mark.torm_smoke(scenario="rw1", seed=0, method="oracle", min_success=1.0)
def test_oracle_picks_single_cylinder(torm_smoke_result):
    rec = torm_smoke_result
    assert rec["n_objects"] == 1 and rec["objects"][0]["name"] == "cylinder"
    pick = rec["objects"][0]["pick"]
    assert pick["judgement"]["lift_m"] >= 0.24 and pick["judgement"]["translation_m"] >= 0.18
    for stage in ("capture", "grasp_planning", "execution", "total"):
        assert rec["timings"][stage] >= 0


@pytest.mark.torm_smoke(scenario="rw3", seed=0, method="torm", min_success=1.0)
def test_torm_reconstruction_trial_picks_both_objects(torm_smoke_result):
    rec = torm_smoke_result
    per = rec["perception"]
    assert per["n_objects_found"] == per["n_objects_present"] == 2
    assert per["chamfer_mm_mean"] < 5.0


def test_torm_trial_factory_reports_not_reconstructed_for_blank_masks(torm_trial):
    # Every mask missing in every view: the reconstruction fails and is recorded, not raised.
    rec = torm_trial("rw1", method="torm", overrides=["segmentation.segmenter=noisy",
                                                       "segmentation.options={preset: none, overrides: "
                                                       "{p_missing_view: 1.0}}"])
    assert rec["objects"][0]["outcome"] == "not_reconstructed"
    assert rec["failure"] == "reconstruction_failed"


def test_bad_trial_configs_name_the_problem():
    from torm import config as cfgmod
    from torm.pipeline import TrialConfig

    with pytest.raises(ConfigError, match=r"'magic' is not one of \['torm', 'depth', 'oracle'\]"):
        cfgmod.from_dict(TrialConfig, {}, ["method=magic"])
    with pytest.raises(UnknownNameError, match="valid choices: grounded_sam, gt, noisy"):
        cfgmod.from_dict(TrialConfig, {}, ["segmentation.segmenter=sam3"])
    with pytest.raises(ConfigError, match="unknown key"):
        cfgmod.from_dict(TrialConfig, {}, ["reconstruction.grid_rez=3"])
