"""What a benchmark run is: the grid scenario x trial x method, per-trial seeds, and the run config.

Seeds: :func:`trial_seed` derives each trial's scene seed from ``(base_seed, suite, scenario, trial)``
with SHA-256 (not Python's per-process salted ``hash()``), so the seed of any single trial is the
same in every process, on every machine, and can be re-run alone (``torm bench ... --scenario rw3``
with the same ``--trials`` gives the same seeds). The method is deliberately *not* part of the seed:
every method sees the same scene layouts, which makes the method comparison paired.

A trial is named by its key ``"<suite>/<scenario>/<trial>/<method>"`` (e.g. ``rw/rw3/7/torm``);
results files are keyed by it, which is what makes resuming exact.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Literal

from torm.config import check_finite, parse_override
from torm.errors import ConfigError, UnknownNameError
from torm.vocabulary import ENGINES, METHODS, RECORD_MODES, START_METHODS  # noqa: E402  (one definition, re-exported)

DEFAULT_TRIAL_FN = "torm.bench.trial:run_spec"
# TrialConfig fields the grid sets per trial; overriding them with --set would break the grid.
GRID_KEYS: tuple[str, ...] = ("scenario", "seed", "method")

TrialFn = Callable[..., dict[str, Any]]


def trial_seed(suite: str, scenario: str, trial: int, base_seed: int = 0) -> int:
    """Deterministic 31-bit scene seed of trial ``trial`` of ``scenario`` in ``suite``.

    ``int.from_bytes(sha256(f"{base_seed}/{suite}/{scenario}/{trial}")[:4], "big") & 0x7FFFFFFF``:
    stable across processes and Python versions, in ``[0, 2**31)``.
    """
    if trial < 0:
        raise ConfigError(f"trial index must be >= 0, got {trial}")
    text = f"{int(base_seed)}/{suite}/{scenario}/{int(trial)}".encode()
    return int.from_bytes(hashlib.sha256(text).digest()[:4], "big") & 0x7FFFFFFF


def trial_key(suite: str, scenario: str, trial: int, method: str) -> str:
    """The key that names one trial in results files: ``suite/scenario/trial/method``."""
    return f"{suite}/{scenario}/{int(trial)}/{method}"


@dataclass(frozen=True)
class TrialSpec:
    """One cell of the grid: everything a trial function needs to know about which trial to run.

    Attributes:
        suite, scenario: where the scene comes from (``sim/scenes/suites``).
        trial: trial index within the scenario, 0-based.
        method: ``torm`` | ``depth`` | ``oracle``.
        seed: the scene seed, :func:`trial_seed` of (suite, scenario, trial).
        key: :func:`trial_key` of (suite, scenario, trial, method).
        objects: the scenario's object names in instance order (object k = position k-1); lets the
            runner fill per-object rows for trials that never returned (timeout, crash).
    """

    suite: str
    scenario: str
    trial: int
    method: str
    seed: int
    key: str
    objects: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["objects"] = list(self.objects)
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrialSpec:
        return cls(**{**data, "objects": tuple(data.get("objects", ()))})


@dataclass(frozen=True)
class BenchConfig:
    """A benchmark run. Times in s.

    Attributes:
        suite: scenario suite (``rw`` or ``syn``).
        scenarios: subset of the suite's scenarios (empty: all of them, in natural order).
        trials: trials per scenario and method.
        methods: perception methods compared.
        workers: trials run at the same time (processes for ``pool``, in-flight tasks for ``ray``).
        engine: ``pool`` (local subprocesses) or ``ray`` (Ray remote tasks).
        ray_address: Ray cluster address (``ray.init(address=...)``); None starts a local Ray.
        timeout_s: wall-clock limit of one trial; a trial over it is killed and recorded as ``timeout``.
        record: rerun recordings per trial: ``none``, ``failures`` (kept only for failed trials) or ``all``.
        overrides: ``a.b=c`` overrides of the base trial config (``--set``), applied to every trial.
        trial_fn: ``module:function`` run per trial as ``fn(spec, overrides, record_path) -> dict``.
        base_seed: mixed into every trial seed; change it to draw a different set of scene layouts.
        threads: torch/BLAS threads per trial (0: free cores // workers, at least 1).
        stop_grace_s: a worker that must stop (timeout, Ctrl-C, SIGTERM) gets SIGTERM and this long to run
            its stop path (a real backend cancels the motion and disables the arm) before SIGKILL.
        start_method: how a ``pool`` trial's process starts: ``forkserver`` (the default: a fork of a server
            that imported the heavy libraries once, :mod:`torm.bench.forkserver`; the 2.4-3.5 s of imports a
            trial paid on 2 cores are gone) or ``spawn`` (a fresh interpreter per trial). Not part of the run
            identity: the trial is the same. ``ray``, and more than one thread per trial, always spawn.
    """

    suite: str = "rw"
    scenarios: tuple[str, ...] = ()
    trials: int = 1
    methods: tuple[str, ...] = ("torm",)
    workers: int = 1
    engine: Literal["pool", "ray"] = "pool"
    ray_address: str | None = None
    timeout_s: float = 1800.0
    record: Literal["none", "failures", "all"] = "none"
    overrides: tuple[str, ...] = ()
    trial_fn: str = DEFAULT_TRIAL_FN
    base_seed: int = 0
    threads: int = 0
    stop_grace_s: float = 10.0
    start_method: Literal["spawn", "forkserver"] = "forkserver"

    def __post_init__(self) -> None:
        check_finite(self, "bench config")
        if self.start_method not in START_METHODS:
            raise UnknownNameError("start_method", self.start_method, START_METHODS)
        if self.trials < 1:
            raise ConfigError(f"trials must be >= 1, got {self.trials}")
        if self.workers < 1:
            raise ConfigError(f"workers must be >= 1, got {self.workers}")
        if self.base_seed < 0:
            raise ConfigError(f"base_seed must be a non-negative integer, got {self.base_seed}")
        if not self.timeout_s > 0:
            raise ConfigError(f"timeout_s must be > 0 seconds, got {self.timeout_s}")
        if not self.stop_grace_s >= 0:
            raise ConfigError(f"stop_grace_s must be >= 0 seconds, got {self.stop_grace_s}")
        if self.threads < 0:
            raise ConfigError(f"threads must be >= 0 (0 = automatic), got {self.threads}")
        if not self.methods:
            raise ConfigError("methods: give at least one method, e.g. --method torm")
        for m in self.methods:
            if m not in METHODS:  # a plug-in: an installed torm.methods entry point or module:callable
                from torm.methods import check_method_name

                check_method_name(m)
        if len(set(self.methods)) != len(self.methods):
            raise ConfigError(f"methods: {list(self.methods)} lists a method twice")
        if self.engine not in ENGINES:
            raise UnknownNameError("engine", self.engine, ENGINES)
        if self.record not in RECORD_MODES:
            raise UnknownNameError("record mode", self.record, RECORD_MODES)
        if ":" not in self.trial_fn:
            raise ConfigError(f"trial_fn {self.trial_fn!r} must look like 'package.module:function'")
        for text in self.overrides:
            path, _ = parse_override(text)
            if path[0] in GRID_KEYS and len(path) == 1:
                raise ConfigError(f"override {text!r}: {path[0]!r} is set per trial by the benchmark grid; "
                                  "use --scenario/--method/--trials instead")
        if len(set(self.scenarios)) != len(self.scenarios):
            raise ConfigError(f"scenarios: {list(self.scenarios)} lists a scenario twice")

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        for k in ("scenarios", "methods", "overrides"):
            d[k] = list(d[k])
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BenchConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"bench config: unknown key(s) {unknown}; valid keys: {sorted(names)}")
        kw = dict(data)
        for k in ("scenarios", "methods", "overrides"):
            if k in kw:
                kw[k] = tuple(kw[k])
        return cls(**kw)


# Benchmark fields that define what a trial *is* (its seed, its config, its code); with the resolved trial
# config and the code version they make the run identity (torm.bench.identity). Changing one of these
# between invocations on the same run folder makes old and new rows incomparable: refused unless
# --fresh. The grid extent (scenarios, trials, methods) and how it runs (workers, engine, ...) may change.
IDENTITY_FIELDS: tuple[str, ...] = ("suite", "overrides", "trial_fn", "base_seed", "timeout_s")


def identity(config: BenchConfig) -> dict[str, Any]:
    """The identity part of a config (see :data:`IDENTITY_FIELDS`) as plain data."""
    d = config.as_dict()
    return {k: d[k] for k in IDENTITY_FIELDS}


def config_hash(config: BenchConfig) -> str:
    """SHA-256 (hex, 16 chars) of :func:`identity`; equal hashes mean rows are comparable."""
    import json

    text = json.dumps(identity(config), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def resolve_scenarios(config: BenchConfig) -> list[str]:
    """The config's scenarios, checked against the suite (UnknownNameError lists the valid ones)."""
    from sim.scenes.scenario import list_scenarios

    available = list_scenarios(config.suite)  # UnknownNameError for an unknown suite
    if not config.scenarios:
        return available
    for name in config.scenarios:
        if name not in available:
            raise UnknownNameError(f"scenario of suite {config.suite!r}", name, available)
    return list(config.scenarios)


def build_grid(config: BenchConfig) -> list[TrialSpec]:
    """Every trial of the run, ordered trial-major (trial 0 of every scenario and method first).

    Trial-major order means an interrupted run has an even spread of results over the grid.
    """
    from sim.scenes.scenario import get_scenario

    scenarios = resolve_scenarios(config)
    objects = {name: tuple(get_scenario(name).objects) for name in scenarios}
    return [
        TrialSpec(suite=config.suite, scenario=sc, trial=t, method=m,
                  seed=trial_seed(config.suite, sc, t, config.base_seed),
                  key=trial_key(config.suite, sc, t, m), objects=objects[sc])
        for t in range(config.trials) for sc in scenarios for m in config.methods
    ]


def load_trial_fn(path: str) -> TrialFn:
    """Import ``module:function``; ConfigError names what is missing."""
    module_name, _, fn_name = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"trial_fn {path!r}: cannot import module {module_name!r} ({exc})") from exc
    fn = getattr(module, fn_name, None)
    if not callable(fn):
        raise ConfigError(f"trial_fn {path!r}: module {module_name!r} has no function {fn_name!r}")
    return fn


def validate_for_trial_fn(config: BenchConfig) -> Any:
    """Let the trial function's module check the overrides up front (its optional ``check_overrides``).

    Catches a misspelt ``--set`` before hours of trials fail one by one. Returns what
    ``check_overrides(overrides)`` returns (the default trial module: the resolved base trial config),
    or None when the module has no such hook.
    """
    load_trial_fn(config.trial_fn)
    module = importlib.import_module(config.trial_fn.partition(":")[0])
    check = getattr(module, "check_overrides", None)
    return check(config.overrides) if callable(check) else None


def parse_list(values: Iterable[str]) -> tuple[str, ...]:
    """Flatten repeatable and comma-separated CLI values (``--method torm,depth --method oracle``)."""
    out: list[str] = []
    for v in values:
        out.extend(p.strip() for p in str(v).split(",") if p.strip())
    return tuple(out)


__all__ = ["BenchConfig", "DEFAULT_TRIAL_FN", "ENGINES", "IDENTITY_FIELDS", "METHODS", "RECORD_MODES", "TrialSpec",
           "build_grid", "config_hash", "identity", "load_trial_fn", "parse_list", "resolve_scenarios", "trial_key",
           "trial_seed", "validate_for_trial_fn"]
