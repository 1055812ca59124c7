"""The paper's success test and the outcome categories of a pick.

Success (TORM, Sec. IV-E): the object is lifted 25 cm above the table, translated 20 cm sideways,
lowered and released back onto the table. In simulation it is judged from the object's true pose,
sampled during the motion; on the real robot from the gripper's object detection (plus an optional
operator confirmation). Tolerances are stated in :class:`SuccessCriteria`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from torm.errors import ConfigError


class Outcome(str, Enum):
    """Outcome category of one pick (string values are what result files store)."""

    SUCCESS = "success"
    NOT_RECONSTRUCTED = "not_reconstructed"  # the object has no reconstructed counterpart
    NO_GRASP = "no_grasp_found"  # no collision-free grasp in the stroke
    UNREACHABLE = "unreachable"  # IK failed for every candidate
    COLLISION = "collision_on_approach"  # hit the object or a neighbour before closing
    SLIPPED = "slipped_during_lift"
    DROPPED = "dropped_during_translation"
    NOT_RELEASED = "not_released"  # the object did not end up back on the table
    PHYSICS = "physics_error"  # NaN / exploding contacts: the trial aborts
    OTHER = "other"


@dataclass(frozen=True)
class SuccessCriteria:
    """Distances in metres.

    Attributes:
        lift_height: required rise of the object above its resting height.
        translation: required horizontal displacement while lifted.
        slip_tolerance: largest allowed drift of the object relative to the TCP during lift and
            translation (the object must stay in the hand, small slip allowed).
        height_tolerance: slack on the lift height and on "back on the table".
    """

    lift_height: float = 0.25
    translation: float = 0.20
    slip_tolerance: float = 0.02
    height_tolerance: float = 0.01

    def __post_init__(self) -> None:
        if min(self.lift_height, self.translation, self.slip_tolerance, self.height_tolerance) <= 0:
            raise ConfigError("SuccessCriteria: every distance must be positive (m)")


@dataclass
class PickTrace:
    """Object and TCP positions (m, world) sampled during a pick.

    ``rest`` is the object's position before the pick; ``lift`` and ``translate`` hold (T, 3) object
    positions relative to the TCP, expressed in the world frame, sampled during those phases;
    ``lift_end``/``translate_end``/``final`` are object positions at the end of those phases.
    """

    rest: np.ndarray
    lift: list[np.ndarray] = field(default_factory=list)
    translate: list[np.ndarray] = field(default_factory=list)
    lift_end: np.ndarray | None = None
    translate_end: np.ndarray | None = None
    final: np.ndarray | None = None


@dataclass(frozen=True)
class Judgement:
    """The verdict and the measured quantities behind it (m)."""

    outcome: Outcome
    lift: float
    translation: float
    slip_lift: float
    slip_translate: float
    final_height_change: float

    def as_dict(self) -> dict:
        return {
            "outcome": self.outcome.value,
            "lift_m": self.lift,
            "translation_m": self.translation,
            "slip_lift_m": self.slip_lift,
            "slip_translate_m": self.slip_translate,
            "final_height_change_m": self.final_height_change,
        }


def _drift(rel_txn: list[np.ndarray]) -> float:
    if len(rel_txn) < 2:
        return 0.0
    rel = np.asarray(rel_txn)
    return float(np.max(np.linalg.norm(rel - rel[0], axis=1)))


def judge_pick(trace: PickTrace, criteria: SuccessCriteria = SuccessCriteria()) -> Judgement:
    """Apply the paper's success test to a sampled pick; the first failed stage names the category."""
    c = criteria
    rest = np.asarray(trace.rest, float)
    lift = float(trace.lift_end[2] - rest[2]) if trace.lift_end is not None else 0.0
    moved = float(np.linalg.norm((trace.translate_end - rest)[:2])) if trace.translate_end is not None else 0.0
    slip_l, slip_t = _drift(trace.lift), _drift(trace.translate)
    final_dz = float(trace.final[2] - rest[2]) if trace.final is not None else float("nan")

    def verdict(o: Outcome) -> Judgement:
        return Judgement(o, lift, moved, slip_l, slip_t, final_dz)

    if lift < c.lift_height - c.height_tolerance or slip_l > c.slip_tolerance:
        return verdict(Outcome.SLIPPED)
    if trace.translate_end is None:
        return verdict(Outcome.DROPPED)
    still_up = float(trace.translate_end[2] - rest[2]) >= c.lift_height - c.height_tolerance
    if slip_t > c.slip_tolerance or not still_up or moved < c.translation - c.slip_tolerance:
        return verdict(Outcome.DROPPED)
    if not np.isfinite(final_dz) or abs(final_dz) > c.height_tolerance:
        return verdict(Outcome.NOT_RELEASED)
    return verdict(Outcome.SUCCESS)
