"""The default trial function of ``torm bench``: one closed-loop trial of :mod:`torm.pipeline`.

Trial-function contract (what ``BenchConfig.trial_fn`` points at)::

    fn(spec: TrialSpec, overrides: tuple[str, ...], record_path: str | None) -> dict

It runs in a fresh worker process (:mod:`torm.bench.worker`) and returns a JSON-ready record with at
least ``objects: [{object_id, name, outcome, ...}]`` (``outcome`` = ``"success"`` for a success);
``n_objects``/``n_success``/``success_rate`` are filled in when missing. It should be deterministic
given ``spec.seed``. Raising is fine: the runner records the exception's category.

Recording hook: when ``record_path`` is given (``torm bench --record failures|all``) the function may
write a rerun ``.rrd`` recording there; the runner keeps it for failed trials (``failures``) or all
trials (``all``). This one writes the same recording as ``torm trial --record`` (:class:`torm.viz.TrialRecorder`:
saved layout, robot and true objects moving with physics, the capture, reconstructed meshes, grasps, the TCP
path and the outcome per object) in best-effort mode: a recording problem is logged and never fails the trial.

Stop hook (optional): ``safe_stop(spec, overrides) -> Callable[[], dict] | None`` is called by the benchmark's
driver before the trial starts (so nothing slow is left for the emergency), and the callable it returns is
called when the trial's process died without running its own stop path (SIGKILL, out of memory, a segfault,
a dead Ray worker). This module's hook stops a real arm from the driver
(:func:`torm.hardware.remote_stop.stop_arm`: cancel every goal, then disable; the callable returns what was
sent); None when the trial is not on an armed real arm.

Options per method in a grid: ``--set method_options.<method>.<key>=VALUE``, where ``<method>`` is a built-in or an
installed entry point's name (:func:`torm.methods.method_names`), goes to that method's trials only (as
``method_options.<key>``); ``--set method_options.<key>=VALUE`` goes to every method. A ``module:callable`` plug-in
takes its own options through an entry-point name or a grid of its own.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable
from typing import Any

from torm.bench.spec import TrialSpec

log = logging.getLogger(__name__)

#: What benchmark trials default to, under the run's overrides: the measured realism profile (a single
#: ``torm trial`` defaults to ``ideal``). ``--set world.realism=ideal`` runs a benchmark in the ideal world.
BENCH_DEFAULTS: dict[str, Any] = {"world": {"realism": "measured"}}


def method_overrides(overrides: tuple[str, ...], method: str) -> tuple[str, ...]:
    """``overrides`` as ``method``'s trials see them: ``method_options.<name>.<key>=v`` becomes
    ``method_options.<key>=v`` when ``<name>`` is ``method`` and is dropped when it names another method
    (:func:`torm.methods.method_names`); everything else is kept as it is."""
    from torm.methods import method_names

    names = set(method_names()) | {method}
    out = []
    for item in overrides:
        key, eq, value = item.partition("=")
        head, _, tail = key.removeprefix("method_options.").partition(".")
        if eq and key.startswith("method_options.") and tail and head in names:
            if head == method:
                out.append(f"method_options.{tail}={value}")
            continue
        out.append(item)
    return tuple(out)


def trial_config(spec: TrialSpec, overrides: tuple[str, ...] = ()) -> Any:
    """The :class:`torm.pipeline.TrialConfig` of ``spec``: :data:`BENCH_DEFAULTS` + ``overrides`` (per-method
    options routed by :func:`method_overrides`) + the grid cell."""
    from torm.config import from_dict
    from torm.pipeline import TrialConfig

    base = from_dict(TrialConfig, BENCH_DEFAULTS, method_overrides(tuple(overrides), spec.method))
    return dataclasses.replace(base, scenario=spec.scenario, seed=spec.seed, method=spec.method)


def check_overrides(overrides: tuple[str, ...]) -> dict[str, Any]:
    """The resolved base TrialConfig (defaults + overrides) as plain data, for the run's manifest.

    Raises ConfigError now, in the runner, when the overrides do not make a valid TrialConfig
    (instead of every trial failing with ``config_error``). ``scenario``/``seed``/``method`` are set per trial.
    """
    from torm.config import from_dict, to_dict
    from torm.pipeline import TrialConfig

    return to_dict(from_dict(TrialConfig, BENCH_DEFAULTS, overrides))


def run_spec(spec: TrialSpec, overrides: tuple[str, ...] = (), record_path: str | None = None) -> dict[str, Any]:
    """Run the closed-loop trial of ``spec`` and return :func:`torm.pipeline.run_trial`'s record."""
    from torm.pipeline import run_trial

    config = trial_config(spec, overrides)
    if record_path is None:
        return run_trial(config)
    from torm.viz import TrialRecorder

    return run_trial(config, record=TrialRecorder(record_path, best_effort=True, recording_id=spec.key))


def safe_stop(spec: TrialSpec, overrides: tuple[str, ...] = ()) -> Callable[[], dict[str, Any]] | None:
    """The driver-side stop of a trial (module docstring), prepared before the trial starts: a callable that
    cancels every goal and disables an armed real arm over a new connection and returns what was sent; None for
    simulated, unarmed or dry-run trials (nothing to stop)."""
    config = trial_config(spec, overrides)
    if config.backend != "real":
        return None
    from torm.hardware.config import resolve_hardware_config
    from torm.hardware.remote_stop import stop_arm

    hw = resolve_hardware_config(config)
    if not hw.armed or hw.dry_run:
        return None
    return functools.partial(stop_arm, hw, reason=f"trial {spec.key}: its process died without running its stop path")


__all__ = ["BENCH_DEFAULTS", "check_overrides", "run_spec", "safe_stop", "trial_config"]
