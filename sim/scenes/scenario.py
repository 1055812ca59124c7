"""Scenario specs: which objects a scene holds and how densely they are placed (YAML suites).

A suite file (``sim/scenes/suites/<suite>.yaml``) looks like::

    suite: rw
    description: ...
    defaults: {spacing: moderate}          # any Scenario field except name/suite
    scenarios:
      - {name: rw1, objects: [cylinder]}
      - {name: rw7, objects: [ball, cylinder, toothpick_box], spacing: dense}
      - {name: lab4, objects: [test_tube_16x160, test_tube_12x100, beaker_50ml], fixture: tube_rack,
         fixture_objects: 2}                 # the first 2 objects stand in the rack, the rest on the table
      - name: demo
        objects: [cup, ball]
        poses: [[0.50, -0.08, 0.0], [0.60, 0.08, 1.57]]   # optional fixed [x (m), y (m), yaw (rad)]

Each scenario entry is merged over ``defaults`` and built with :func:`torm.config.from_dict`, so an
unknown or malformed field raises ConfigError naming the file, the scenario and the field.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from sim.scenes.objects import list_objects
from torm import vocabulary as _vocab
from torm.config import from_dict, load_yaml
from torm.errors import ConfigError, UnknownNameError

SUITES_DIR = Path(__file__).resolve().parent / "suites"

Spacing = Literal["moderate", "dense", "packed"]
SPACINGS: tuple[str, ...] = ("moderate", "dense", "packed")
#: classes a scenario's ``targets`` may name (the learned segmenter's prompt vocabulary, ``torm.segmentation.learned``)
TARGET_CLASSES: tuple[str, ...] = _vocab.CLASSES
#: Largest ``Scenario.gap`` bound (object widths): beyond it the objects no longer share a 40 cm workspace.
MAX_GAP_WIDTHS = 8.0


@dataclass(frozen=True)
class Scenario:
    """One scene: ordered object names (instance k = position k-1 + 1), spacing class, optional fixed poses.

    ``poses``: None (seeded random placement) or one ``(x, y, yaw)`` per object, world frame, m and rad.
    ``fixture``: an opaque fixture (``sim.scenes.fixtures``: ``tube_rack``, ``tray``) placed on the table; the first
    ``fixture_objects`` objects stand in it (rack slots, or the tray's inside at the scene's spacing).
    ``targets``: the classes the task picks (:data:`TARGET_CLASSES`), the prompt an image segmenter with classes is
    given, as the paper's text prompt: RW2 and RW5 name the opaque cup (``[transparent, opaque]``). Declared by the
    task, not read from the scene's objects.
    ``gap``: ``(lo, hi)`` in multiples of a pair's mean footprint width, replacing the spacing class's gap rule for
    this scenario (every gap >= max(the class's minimum gap, lo w); each new object within hi w of its anchor:
    ``sim.scenes.placement``); the class's minimum gap (20 mm: a finger fits) still holds. None: the class's rule.
    ``occ_paper``: the paper's occlusion ratio for this scenario (0..1, Table III), when it reports one; the scene's
    measured OCC is compared with it (``benchmarks/scene_occlusion.py``).
    """

    name: str
    objects: tuple[str, ...]
    spacing: Spacing = "moderate"
    poses: tuple[tuple[float, float, float], ...] | None = None
    suite: str = ""
    description: str = ""
    fixture: str | None = None
    fixture_objects: int = 0
    targets: tuple[str, ...] = ("transparent",)
    gap: tuple[float, float] | None = None
    occ_paper: float | None = None

    def __post_init__(self) -> None:
        if self.gap is not None:
            gap = tuple(float(g) for g in self.gap)
            if len(gap) != 2 or not 0.0 <= gap[0] <= gap[1] <= MAX_GAP_WIDTHS:
                raise ConfigError(f"scenario {self.name!r}: gap: need [lo, hi] with 0 <= lo <= hi <= "
                                  f"{MAX_GAP_WIDTHS:g} (multiples of the objects' width), got {list(self.gap)}")
            object.__setattr__(self, "gap", gap)
        if self.occ_paper is not None and not 0.0 <= self.occ_paper <= 1.0:
            raise ConfigError(f"scenario {self.name!r}: occ_paper: a share of views in [0, 1] (0.46 = 46 %), got "
                              f"{self.occ_paper}")
        object.__setattr__(self, "targets", tuple(self.targets))
        bad = [t for t in self.targets if t not in TARGET_CLASSES]
        if bad or not self.targets or len(set(self.targets)) != len(self.targets):
            raise ConfigError(f"scenario {self.name!r}: targets {list(self.targets)}: name each class once, among "
                              f"{', '.join(TARGET_CLASSES)}")
        if not self.name:
            raise ConfigError("name: a scenario needs a non-empty name")
        if not self.objects:
            raise ConfigError(f"scenario {self.name!r}: objects: list at least one object")
        valid = list_objects()
        for i, obj in enumerate(self.objects):
            if obj not in valid:
                raise ConfigError(
                    f"scenario {self.name!r}: objects[{i}]: unknown object {obj!r}; valid choices: {', '.join(valid)}"
                )
        if self.spacing not in SPACINGS:
            raise ConfigError(f"scenario {self.name!r}: spacing: {self.spacing!r} is not one of {list(SPACINGS)}")
        if self.fixture is not None:
            from sim.scenes.fixtures import list_fixtures

            if self.fixture not in list_fixtures():
                raise ConfigError(f"scenario {self.name!r}: fixture: unknown fixture {self.fixture!r}; valid "
                                  f"choices: {', '.join(list_fixtures())}")
            if self.poses is not None:
                raise ConfigError(f"scenario {self.name!r}: a fixture scene is placed by seed; drop 'poses'")
        if not 0 <= self.fixture_objects <= len(self.objects) or (self.fixture_objects and self.fixture is None):
            raise ConfigError(f"scenario {self.name!r}: fixture_objects must be 0..{len(self.objects)} and needs a "
                              f"fixture, got {self.fixture_objects} (fixture {self.fixture!r})")
        if self.poses is not None and len(self.poses) != len(self.objects):
            raise ConfigError(
                f"scenario {self.name!r}: poses: {len(self.poses)} poses for {len(self.objects)} objects; "
                "give one [x, y, yaw] per object or drop 'poses'"
            )


_SUITE_KEYS = {"suite", "description", "defaults", "scenarios"}


def load_suite(path: str | Path) -> tuple[Scenario, ...]:
    """Parse one suite YAML file into scenarios (errors name the file, scenario index/name and field)."""
    p = Path(path)
    data = load_yaml(p)
    unknown = sorted(set(data) - _SUITE_KEYS)
    if unknown:
        raise ConfigError(f"{p}: unknown top-level key(s) {unknown}; valid keys: {sorted(_SUITE_KEYS)}")
    suite = data.get("suite", p.stem)
    if not isinstance(suite, str):
        raise ConfigError(f"{p}: suite: expected a string, got {suite!r}")
    defaults = data.get("defaults") or {}
    if not isinstance(defaults, dict):
        raise ConfigError(f"{p}: defaults: expected a mapping of Scenario fields, got {defaults!r}")
    for bad in ("name", "suite"):
        if bad in defaults:
            raise ConfigError(f"{p}: defaults.{bad}: '{bad}' cannot have a suite-wide default")
    entries = data.get("scenarios")
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{p}: scenarios: expected a non-empty list of scenario mappings")
    out: list[Scenario] = []
    seen: set[str] = set()
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise ConfigError(f"{p}: scenarios[{i}]: expected a mapping, got {entry!r}")
        label = f"{p}: scenarios[{i}]" + (f" ({entry['name']})" if isinstance(entry.get("name"), str) else "")
        if "name" not in entry:
            raise ConfigError(f"{label}: name: missing; every scenario needs a name")
        merged: dict[str, Any] = {**defaults, **entry, "suite": suite}
        try:
            sc = from_dict(Scenario, merged, where=label)
        except ConfigError as exc:
            msg = str(exc)
            raise ConfigError(msg if msg.startswith(str(p)) else f"{label}: {msg}") from exc
        if sc.name in seen:
            raise ConfigError(f"{label}: name: duplicate scenario name {sc.name!r}")
        seen.add(sc.name)
        out.append(sc)
    return tuple(out)


@functools.cache
def _all_scenarios() -> dict[str, Scenario]:
    out: dict[str, Scenario] = {}
    for path in sorted(SUITES_DIR.glob("*.yaml")):
        for sc in load_suite(path):
            if sc.name in out:
                raise ConfigError(f"{path}: scenario {sc.name!r} is also defined in suite {out[sc.name].suite!r}")
            out[sc.name] = sc
    return out


def list_suites() -> list[str]:
    """Suite names (YAML file stems in ``sim/scenes/suites``)."""
    return sorted(p.stem for p in SUITES_DIR.glob("*.yaml"))


def list_scenarios(suite: str | None = None) -> list[str]:
    """Scenario names in natural order (syn1, syn2, ..., syn10), optionally only those of ``suite``."""
    if suite is not None and suite not in list_suites():
        raise UnknownNameError("suite", suite, list_suites())
    names = [n for n, s in _all_scenarios().items() if suite is None or s.suite == suite]
    return sorted(names, key=_natural_key)


def get_scenario(name: str | Scenario) -> Scenario:
    """The scenario ``name`` (a Scenario passes through); UnknownNameError lists the valid names."""
    if isinstance(name, Scenario):
        return name
    scenarios = _all_scenarios()
    if name not in scenarios:
        raise UnknownNameError("scenario", name, scenarios)
    return scenarios[name]


def _natural_key(name: str) -> tuple:
    head = name.rstrip("0123456789")
    tail = name[len(head):]
    return (head, int(tail) if tail else -1)
