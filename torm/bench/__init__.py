"""The overnight benchmark harness: grid x seeds -> isolated trials -> ``results.jsonl`` -> report.

- :mod:`torm.bench.spec`: the grid (scenario x trial x method), per-trial seeds, :class:`BenchConfig`.
- :mod:`torm.bench.results`: crash-safe results file and manifest.
- :mod:`torm.bench.runner`: resumable runs on the local pool or on Ray (:mod:`.pool`, :mod:`.ray_engine`),
  each trial in its own process (:mod:`.isolate`, :mod:`.worker`).
- :mod:`torm.bench.trial`: the default trial function (one closed-loop trial of :mod:`torm.pipeline`).
- :mod:`torm.bench.report`: Markdown/HTML report with tables and plots.

CLI: ``torm bench ...`` and ``torm report RUN [RUN2]``.
"""

from __future__ import annotations

from torm.bench.runner import run_benchmark
from torm.bench.spec import BenchConfig, TrialSpec, build_grid, trial_key, trial_seed

__all__ = ["BenchConfig", "TrialSpec", "build_grid", "run_benchmark", "trial_key", "trial_seed"]
