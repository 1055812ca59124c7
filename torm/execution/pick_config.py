"""Settings of the pick sequence (see :mod:`torm.execution.pick`). Units: m, m/s, s, N, rad."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Annotated

from torm.config import Range, check_finite
from torm.errors import ConfigError
from torm.execution.ik import IKConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PickConfig:
    """Pick sequence settings (m, m/s, s, N, rad).

    Attributes:
        pre_grasp_distance: stand-off of the pre-grasp pose back along the approach axis (m); also the retreat.
        transit_height: a pre-grasp TCP lower than this (m above the world origin = table top) is reached by a
            free move to the pose straight above it at this height, then a vertical line down; 0 disables.
            The free move itself is a straight Cartesian line (orientation slerped) when IK allows, else a
            joint move.
        approach_speed: peak TCP speed on the approach and the retreat lines (m/s).
        transport_speed: peak TCP speed while lifting, translating and lowering (m/s).
        lift_height: how far the TCP rises after closing (m); the success test asks for 0.25 of object rise.
        lift_margin: extra rise on top of ``lift_height`` so a little slip still passes the test (m).
        translate_distance: horizontal move while lifted (m).
        place_clearance: the object is released this far above where it was grasped (m).
        speed_scale: fraction of the arm's velocity/acceleration limits used, (0, 1] (capped by the safety layer).
        grip_force: pad force when closing (N): the normal force each finger's pads press on the object; the
            simulated gripper turns it into an actuator setting through its measured force map, clipped to 20-235 N.
        grip_speed: finger speed (m/s).
        open_margin: opening beyond the grasp width before the approach (m), capped at the gripper's stroke.
        close_width: commanded width when closing (m); 0 = close until the object stops the fingers.
        settle_after_close: hold time after closing before lifting (s).
        ik: IK tolerances and solver settings.
        max_candidates: how many grasp candidates (in the given order) are tried for reachability.
        control_dt: sample period of the joint trajectories sent to the arm (s).
        line_step: spacing of the IK waypoints on straight Cartesian segments (m).
        max_joint_step: largest joint change between neighbouring line waypoints before the line counts as
            passing a singularity / IK branch switch (rad).
        approach_tolerance: the target moving more than this before the fingers close is a collision (m).
        neighbour_tolerance: another object moving more than this during the approach is a collision (m);
            at the end of the pick it is reported as disturbance.
        sample_dt: period of the object/TCP samples taken during lift and translation (s).
        try_flipped: also try the grasp rotated 180 deg about its approach axis (same grasp for a symmetric
            parallel gripper), preferring the orientation closer to the current wrist.
        check_robot_collisions: reject configurations where the arm hits itself or the table (plan time).
        table_height: z of the table top for that check (m); world convention 0.
        tcp_tolerance: TCP position error after a motion above which a warning is logged (m); every error is
            recorded in the pick result either way.
    """

    pre_grasp_distance: float = 0.10
    transit_height: float = 0.25
    approach_speed: float = 0.10
    transport_speed: float = 0.25
    lift_height: float = 0.25
    lift_margin: float = 0.005
    translate_distance: float = 0.20
    place_clearance: float = 0.003
    speed_scale: float = 0.5
    grip_force: float = 130.0
    grip_speed: float = 0.1
    open_margin: float = 0.01
    close_width: float = 0.0
    settle_after_close: float = 0.2
    ik: IKConfig = field(default_factory=IKConfig)
    max_candidates: Annotated[int, Range(1, 1000, "grasps tried per object; each costs IK solves")] = 10
    control_dt: float = 0.01
    line_step: float = 0.01
    max_joint_step: float = 0.3
    approach_tolerance: float = 0.01
    neighbour_tolerance: float = 0.01
    sample_dt: float = 0.01
    try_flipped: bool = True
    check_robot_collisions: bool = True
    table_height: float = 0.0
    tcp_tolerance: float = 0.005

    def __post_init__(self) -> None:
        check_finite(self, "PickConfig")  # ranges and NaN / inf (torm.config), also when built in Python
        for name in ("pre_grasp_distance", "approach_speed", "transport_speed", "lift_height", "translate_distance",
                     "grip_force", "grip_speed", "control_dt", "line_step", "max_joint_step", "approach_tolerance",
                     "neighbour_tolerance", "sample_dt", "tcp_tolerance"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"PickConfig.{name} must be positive, got {getattr(self, name)}")
        for name in ("lift_margin", "place_clearance", "open_margin", "close_width", "settle_after_close",
                     "transit_height"):
            if getattr(self, name) < 0:
                raise ConfigError(f"PickConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 < self.speed_scale <= 1.0:
            raise ConfigError(f"PickConfig.speed_scale must be in (0, 1], got {self.speed_scale}")
        if self.max_candidates < 1:
            raise ConfigError(f"PickConfig.max_candidates must be >= 1, got {self.max_candidates}")


def check_grip_force(force_n: float, gripper: object, key: str = "pick.grip_force") -> None:
    """Refuse a pad force (N) the gripper cannot command, before any work starts.

    ``gripper.force_range_n`` (``(low, high)`` in N, e.g. 20-235 N for a Robotiq 2F-85) is the range a
    command is clipped to; a configured value outside it would be clipped without a word (1e-7 N commanded
    as 20 N). Grippers that do not state a range are not checked.

    Raises:
        ConfigError: naming ``key``, the value, the range and the fix.
    """
    rng = getattr(gripper, "force_range_n", None)
    if rng is not None:
        lo, hi = (float(v) for v in rng)
        if not lo <= float(force_n) <= hi:
            raise ConfigError(f"{key}={force_n:g} N is outside the gripper's pad force range {lo:g}-{hi:g} N (it would "
                              f"be commanded as {min(max(float(force_n), lo), hi):g} N); set {key} inside "
                              f"{lo:g}-{hi:g}")
    most = getattr(gripper, "max_pad_force", None)
    if most is None:
        return
    widths, forces = (tuple(float(v) for v in x) for x in most)
    peak = max(forces)
    if float(force_n) > peak:
        w_peak = widths[forces.index(peak)]
        raise ConfigError(
            f"{key}={force_n:g} N is more than this gripper squeezes at any opening: at most {peak:.3g} N (at "
            f"{w_peak * 1e3:.0f} mm; {min(forces):.3g} N at {widths[0] * 1e3:.0f} mm), measured in its "
            f"gripper.force_map.max_force (a position servo presses with stiffness x remaining travel); set {key} "
            f"to at most {peak:.3g}, or raise gripper.servo_gain_scale in the robot's YAML and re-measure the map "
            "(python -m sim.robots.measure_gripper ROBOT --force)")
    short = [w for w, f in zip(widths, forces, strict=True) if f < float(force_n)]
    if short:
        log.info("%s=%g N: the gripper squeezes less below a %.0f mm opening (%.3g N at %.0f mm); grips there "
                 "record the force they reach", key, force_n, max(short) * 1e3, min(forces), widths[0] * 1e3)
