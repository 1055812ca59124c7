"""The paper's success test and the outcome categories of a pick.

Success (TORM, Sec. IV-E): the object is lifted 25 cm above the table, translated 20 cm sideways,
lowered and released back onto the table. In simulation it is judged from the object's true pose,
sampled during the motion; on the real robot from the gripper's object detection (plus an optional
operator confirmation). Tolerances are stated in :class:`SuccessCriteria`.

Arm tracking vs slip. The heights and distances are the object's, but an arm that does not reach its commanded
pose (sag without gravity compensation, a weak servo, injected tracking error) carries a firmly held object short
of the targets too. So the trace also holds the TCP's own positions: when a stage falls short while the object
stayed with the TCP (drift within the slip tolerance) and the TCP itself fell short by the same measure, the
outcome is ``arm_tracking_error``, never ``slipped_during_lift`` / ``dropped_during_translation``.
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
    TRACKING = "arm_tracking_error"  # the object stayed in the hand but the arm fell short of the commanded motion
    PHANTOM = "phantom_attempt"  # an attempt at a reconstructed object that is not there (the judge's verdict)
    SAFETY_STOP = "safety_stop"  # the safety layer refused a motion (joint, speed or workspace limit): nothing sent
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
    ``lift_end``/``translate_end``/``final`` are object positions at the end of those phases;
    ``tcp_rest``/``tcp_lift_end``/``tcp_translate_end`` the TCP's measured positions before the lift and at the end
    of the lift and the translation (None when not recorded: then no stage counts as a tracking error).
    """

    rest: np.ndarray
    lift: list[np.ndarray] = field(default_factory=list)
    translate: list[np.ndarray] = field(default_factory=list)
    lift_end: np.ndarray | None = None
    translate_end: np.ndarray | None = None
    final: np.ndarray | None = None
    tcp_rest: np.ndarray | None = None
    tcp_lift_end: np.ndarray | None = None
    tcp_translate_end: np.ndarray | None = None


@dataclass(frozen=True)
class Judgement:
    """The verdict and the measured quantities behind it (m)."""

    outcome: Outcome
    lift: float
    translation: float
    slip_lift: float
    slip_translate: float
    final_height_change: float
    tcp_lift: float | None = None
    tcp_translation: float | None = None

    def as_dict(self) -> dict:
        return {
            "outcome": self.outcome.value,
            "lift_m": self.lift,
            "translation_m": self.translation,
            "slip_lift_m": self.slip_lift,
            "slip_translate_m": self.slip_translate,
            "final_height_change_m": self.final_height_change,
            "tcp_lift_m": self.tcp_lift,
            "tcp_translation_m": self.tcp_translation,
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
    t0, t1, t2 = trace.tcp_rest, trace.tcp_lift_end, trace.tcp_translate_end
    tcp_lift = float(t1[2] - t0[2]) if t0 is not None and t1 is not None else None
    tcp_up = float(t2[2] - t0[2]) if t0 is not None and t2 is not None else None
    tcp_moved = float(np.linalg.norm((t2 - t1)[:2])) if t1 is not None and t2 is not None else None

    def verdict(o: Outcome) -> Judgement:
        return Judgement(o, lift, moved, slip_l, slip_t, final_dz, tcp_lift, tcp_moved)

    if lift < c.lift_height - c.height_tolerance or slip_l > c.slip_tolerance:
        arm_short = tcp_lift is not None and tcp_lift < c.lift_height - c.height_tolerance
        return verdict(Outcome.TRACKING if slip_l <= c.slip_tolerance and arm_short else Outcome.SLIPPED)
    if trace.translate_end is None:
        return verdict(Outcome.DROPPED)
    still_up = float(trace.translate_end[2] - rest[2]) >= c.lift_height - c.height_tolerance
    if slip_t > c.slip_tolerance or not still_up or moved < c.translation - c.slip_tolerance:
        arm_short = ((tcp_up is not None and not still_up and tcp_up < c.lift_height - c.height_tolerance)
                     or (tcp_moved is not None and moved < c.translation - c.slip_tolerance
                         and tcp_moved < c.translation - c.slip_tolerance))
        return verdict(Outcome.TRACKING if slip_t <= c.slip_tolerance and arm_short else Outcome.DROPPED)
    if not np.isfinite(final_dz) or abs(final_dz) > c.height_tolerance:
        return verdict(Outcome.NOT_RELEASED)
    return verdict(Outcome.SUCCESS)
