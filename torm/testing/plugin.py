"""pytest plugin: guard a robot config or pipeline change with a closed-loop smoke trial.

Registered through the ``pytest11`` entry point, so it is active wherever torm is installed.

Marker::

    @pytest.mark.torm_smoke(scenario="rw1", seed=0, method="oracle", min_success=1.0,
                            overrides=["capture.n_views=12"])
    def test_my_robot_still_picks(torm_smoke_result):
        assert torm_smoke_result["n_objects"] == 1

The marked test receives the trial's result record through the ``torm_smoke_result`` fixture (the trial runs
in the test's setup); the plugin fails the test when the success rate is below ``min_success``, as a test
failure (``FAILED``, in the call phase), not a setup error. The ``torm_trial`` fixture is a factory for ad-hoc
trials: ``record = torm_trial("rw3", seed=1, method="torm", overrides=[...])``.

Command-line options: ``--torm-robot-config FILE`` (robot YAML or folder name for every smoke trial),
``--torm-set KEY=VALUE`` (repeatable config overrides applied to every smoke trial) and ``--torm-record
none|failures|all`` with ``--torm-record-dir DIR`` (default ``torm-recordings``): a rerun recording of every
smoke trial, kept for failed tests only (``failures``) or for all; a failed test's report names its recording.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest

#: Small but complete defaults: a low-resolution capture and reconstruction keep a trial to seconds.
SMOKE_OVERRIDES = (
    "capture.n_views=16",
    "capture.scale=0.25",
    "reconstruction.grid_res=32",
    "reconstruction.refine_iters=0",
    "reconstruction.points_per_object=1024",
)


#: ``--torm-record`` choices.
RECORD_MODES = ("none", "failures", "all")


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("torm", "torm smoke trials")
    group.addoption("--torm-robot-config", default=None, help="robot folder name or robot YAML for smoke trials")
    group.addoption("--torm-set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override applied to every torm smoke trial (repeatable)")
    group.addoption("--torm-record", choices=RECORD_MODES, default="none",
                    help="rerun recordings of smoke trials: none (default), failures (kept for failed tests), all")
    group.addoption("--torm-record-dir", default="torm-recordings", metavar="DIR",
                    help="where --torm-record writes its .rrd files (default torm-recordings)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "torm_smoke(scenario='rw1', seed=0, method='oracle', min_success=1.0, overrides=()): run a closed-loop "
        "torm trial and fail when its success rate is below min_success",
    )


def run_smoke_trial(scenario: str = "rw1", seed: int = 0, method: str = "oracle",
                    overrides: Sequence[str] = (), robot: str | None = None,
                    record: str | Path | None = None) -> dict[str, Any]:
    """Run one trial with the smoke defaults (:data:`SMOKE_OVERRIDES`) plus ``overrides``; returns the record.
    ``record``: a rerun ``.rrd`` path to record the trial to (best effort: a recording problem is logged)."""
    from torm import config as cfgmod
    from torm.pipeline import TrialConfig, run_trial

    ov = [*SMOKE_OVERRIDES, f"scenario={scenario}", f"seed={seed}", f"method={method}", *overrides]
    if robot:
        ov.append(f"robot={robot}")
    cfg = cfgmod.from_dict(TrialConfig, {}, ov)
    if record is None:
        return run_trial(cfg)
    from torm.viz import TrialRecorder

    return run_trial(cfg, record=TrialRecorder(str(record), best_effort=True, recording_id=f"{scenario}-{seed}"))


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


@pytest.fixture
def torm_trial(request: pytest.FixtureRequest) -> Callable[..., dict[str, Any]]:
    """Factory fixture: ``torm_trial(scenario, seed=0, method="oracle", overrides=())`` -> result record."""
    opts = request.config.getoption
    mode = opts("torm_record")
    made: list[Path] = []
    request.node._torm_recordings = made  # the report hook keeps or removes them

    def _run(scenario: str = "rw1", seed: int = 0, method: str = "oracle", overrides: Sequence[str] = ()):
        rec = None
        if mode != "none":
            folder = Path(opts("torm_record_dir"))
            folder.mkdir(parents=True, exist_ok=True)
            rec = folder / f"{_safe(request.node.nodeid)}-{scenario}-{seed}-{method}-{len(made)}.rrd"
            made.append(rec)
        return run_smoke_trial(scenario, seed, method, [*opts("torm_set"), *overrides], opts("torm_robot_config"),
                               record=rec)

    return _run


@pytest.fixture
def torm_smoke_result(request: pytest.FixtureRequest, torm_trial) -> dict[str, Any]:
    """The result record of the trial described by the test's ``torm_smoke`` marker."""
    marker = request.node.get_closest_marker("torm_smoke")
    if marker is None:
        raise pytest.UsageError("torm_smoke_result needs @pytest.mark.torm_smoke(...) on the test")
    kw = dict(marker.kwargs)
    min_success = float(kw.pop("min_success", 1.0))
    record = torm_trial(kw.pop("scenario", "rw1"), kw.pop("seed", 0), kw.pop("method", "oracle"),
                        kw.pop("overrides", ()))
    if kw:
        raise pytest.UsageError(f"torm_smoke: unknown argument(s) {sorted(kw)}; valid: scenario, seed, method, "
                                "min_success, overrides")
    request.node._torm_smoke = (record, min_success)  # judged in the call phase (pytest_pyfunc_call)
    return record


def smoke_failure(record: dict[str, Any], min_success: float) -> str | None:
    """The failure message of a smoke trial below ``min_success``, or None when it passed."""
    rate = record["success_rate"]
    if rate >= min_success:
        return None
    outcomes = [(o["name"], o["outcome"], o.get("message", "")) for o in record["objects"]]
    return (f"torm smoke trial {record['scenario']} seed {record['seed']} ({record['method']}): success rate "
            f"{rate:.2f} < {min_success:.2f}; outcomes: {outcomes}")


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem: pytest.Function) -> None:
    """A smoke trial below its ``min_success`` fails the test in its call phase (a FAILED test, not a setup
    ERROR), before the test body runs."""
    smoke = getattr(pyfuncitem, "_torm_smoke", None)
    if smoke is not None and (why := smoke_failure(*smoke)):
        pytest.fail(why, pytrace=False)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Any:
    """``--torm-record failures``: keep the recordings of failed tests (named in their report), remove the rest."""
    report = yield
    made = getattr(item, "_torm_recordings", None)
    if made and report.when == "call" or (made and report.when == "setup" and report.failed):
        mode = item.config.getoption("torm_record")
        kept = [p for p in made if p.exists()]
        if report.failed:
            report.sections.append(("torm recordings", "\n".join(str(p) for p in kept) or "none written"))
        elif mode == "failures":
            for p in kept:
                p.unlink()
    return report


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A test marked ``torm_smoke`` gets the ``torm_smoke_result`` fixture even if it does not ask for it."""
    for item in items:
        wants = item.get_closest_marker("torm_smoke") is not None and hasattr(item, "fixturenames")
        if wants and "torm_smoke_result" not in item.fixturenames:
            item.fixturenames.append("torm_smoke_result")
