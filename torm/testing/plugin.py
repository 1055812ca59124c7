"""pytest plugin: guard a robot config or pipeline change with a closed-loop smoke trial.

Registered through the ``pytest11`` entry point, so it is active wherever torm is installed.

Marker::

    @pytest.mark.torm_smoke(scenario="rw1", seed=0, method="oracle", min_success=1.0,
                            overrides=["capture.n_views=12"])
    def test_my_robot_still_picks(torm_smoke_result):
        assert torm_smoke_result["n_objects"] == 1

The marked test receives the trial's result record through the ``torm_smoke_result`` fixture; the
plugin fails the test when the success rate is below ``min_success``. The ``torm_trial`` fixture is a
factory for ad-hoc trials: ``record = torm_trial("rw3", seed=1, method="torm", overrides=[...])``.

Command-line options: ``--torm-robot-config FILE`` (robot YAML or folder name for every smoke trial)
and ``--torm-set KEY=VALUE`` (repeatable config overrides applied to every smoke trial).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
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


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("torm", "torm smoke trials")
    group.addoption("--torm-robot-config", default=None, help="robot folder name or robot YAML for smoke trials")
    group.addoption("--torm-set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override applied to every torm smoke trial (repeatable)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "torm_smoke(scenario='rw1', seed=0, method='oracle', min_success=1.0, overrides=()): run a closed-loop "
        "torm trial and fail when its success rate is below min_success",
    )


def run_smoke_trial(scenario: str = "rw1", seed: int = 0, method: str = "oracle",
                    overrides: Sequence[str] = (), robot: str | None = None) -> dict[str, Any]:
    """Run one trial with the smoke defaults (:data:`SMOKE_OVERRIDES`) plus ``overrides``; returns the record."""
    from torm import config as cfgmod
    from torm.pipeline import TrialConfig, run_trial

    ov = [*SMOKE_OVERRIDES, f"scenario={scenario}", f"seed={seed}", f"method={method}", *overrides]
    if robot:
        ov.append(f"robot={robot}")
    return run_trial(cfgmod.from_dict(TrialConfig, {}, ov))


@pytest.fixture
def torm_trial(request: pytest.FixtureRequest) -> Callable[..., dict[str, Any]]:
    """Factory fixture: ``torm_trial(scenario, seed=0, method="oracle", overrides=())`` -> result record."""
    opts = request.config.getoption

    def _run(scenario: str = "rw1", seed: int = 0, method: str = "oracle", overrides: Sequence[str] = ()):
        return run_smoke_trial(scenario, seed, method, [*opts("torm_set"), *overrides], opts("torm_robot_config"))

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
    rate = record["success_rate"]
    if rate < min_success:
        outcomes = [(o["name"], o["outcome"], o.get("message", "")) for o in record["objects"]]
        pytest.fail(f"torm smoke trial {record['scenario']} seed {record['seed']} ({record['method']}): success "
                    f"rate {rate:.2f} < {min_success:.2f}; outcomes: {outcomes}", pytrace=False)
    return record


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A test marked ``torm_smoke`` gets the ``torm_smoke_result`` fixture even if it does not ask for it."""
    for item in items:
        wants = item.get_closest_marker("torm_smoke") is not None and hasattr(item, "fixturenames")
        if wants and "torm_smoke_result" not in item.fixturenames:
            item.fixturenames.append("torm_smoke_result")
