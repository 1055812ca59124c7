"""Options per method in a benchmark grid: ``method_options.<method>.<key>`` reaches that method's trials only."""

from __future__ import annotations

from torm.bench.spec import TrialSpec
from torm.bench.trial import method_overrides, trial_config


def _spec(method: str) -> TrialSpec:
    return TrialSpec(suite="rw", scenario="rw3", trial=0, method=method, seed=1, key=f"rw__rw3__0__{method}")


def test_per_method_options_reach_only_their_method():
    ov = ("method_options.depth.view=3", "method_options.oracle.noise=0.1", "method_options.shared=2",
          "grasp.n_samples=64")
    assert method_overrides(ov, "depth") == ("method_options.view=3", "method_options.shared=2", "grasp.n_samples=64")
    assert method_overrides(ov, "torm") == ("method_options.shared=2", "grasp.n_samples=64")
    cfg = trial_config(_spec("depth"), ov)
    assert cfg.method == "depth" and cfg.method_options == {"view": 3, "shared": 2} and cfg.grasp.n_samples == 64
    assert trial_config(_spec("oracle"), ov).method_options == {"noise": 0.1, "shared": 2}


def test_an_option_named_like_no_method_stays_shared():
    ov = ("method_options.solver.iters=5",)  # 'solver' is no method: a nested option for every method
    assert method_overrides(ov, "torm") == ov
    assert trial_config(_spec("torm"), ov).method_options == {"solver": {"iters": 5}}
