"""The pick sequence, backend-agnostic: open, pre-grasp, approach, close, lift, translate, lower, release, retreat.

Talks only to the :class:`~torm.backend.protocol.Backend` protocol and an :class:`~torm.execution.ik.IKSolver`,
so the same code drives the simulator and the real robot. Units: m, rad, s, N; world = robot base frame, z up.
Planning (grasp -> TCP frame, IK along straight lines, timing) lives in :mod:`torm.execution.pick_plan`,
settings in :mod:`torm.execution.pick_config`; both are re-exported here.

Sequence. The first reachable candidate (score order; each also tried rotated 180 deg about its approach axis
and with each given translation direction) is executed: open to the grasp width plus a margin, move to the
pre-grasp (``pre_grasp_distance`` back along the approach; through a transit pose above it when it is low),
approach on a straight line, close, lift ``lift_height``, translate ``translate_distance`` horizontally, lower
back to the grasp height (+ ``place_clearance``), release and retreat along the approach axis.

Blind execution. The pick reads only what a real robot has: the arm's state and the gripper's object
detection. After the lift and after the translation the gripper must still report an object, else the pick
stops there and opens (``slipped_during_lift`` / ``dropped_during_translation`` as the robot believes it);
otherwise it lowers, releases, retreats and believes it succeeded (optionally confirmed by ``operator_confirm``).
What really happened is not decided here: in simulation a :class:`~torm.execution.observer.PickObserver` (the
judge in ``sim/judge.py``) watches the phases and scores the attempt from the physics afterwards.

Tracking check. After every motion the measured TCP is compared with the forward kinematics of the last
commanded joints; the error is recorded per motion in :attr:`PickResult.tcp_errors` (a warning above
``PickConfig.tcp_tolerance``) and the TCP positions before and after the carrying phases go into the trace, so
the success test tells an arm that fell short (``arm_tracking_error``) from an object that slipped. The grip
force (requested, applied, measured pad force in N, when the gripper reports it) is recorded in
:attr:`PickResult.grip_force`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from torm.backend.protocol import Backend
from torm.backend.safety import SafetyError
from torm.errors import ConfigError, ExecutionError
from torm.execution.errors import PhysicsError
from torm.execution.ik import IKSolver
from torm.execution.observer import PickObserver
from torm.execution.pick_config import PickConfig
from torm.execution.pick_plan import (
    ROTATION_RADIUS,
    PickPlan,
    ToolFrame,
    free_direction,
    free_directions,
    grasp_to_tcp,
    make_ik_solver,
    plan_first_reachable,
    plan_pick,
    time_line,
)
from torm.execution.robot_collision import RobotCollisionChecker
from torm.execution.success import Judgement, Outcome, PickTrace
from torm.execution.trajectory import chain_waypoints
from torm.types import Grasp

__all__ = [
    "ROTATION_RADIUS", "PhaseTiming", "PickConfig", "PickPlan", "PickResult", "ToolFrame", "execute_pick",
    "free_direction", "free_directions", "grasp_to_tcp", "make_ik_solver", "plan_first_reachable", "plan_pick",
    "time_line",
]

log = logging.getLogger(__name__)

#: Wait after the release before the pick ends (s): the released object comes to rest (judged afterwards).
SETTLE_AFTER_RELEASE_S = 0.2


def _limits_of(arm: Any, cfg: PickConfig) -> tuple[np.ndarray, np.ndarray, float]:
    lim = getattr(arm, "limits", None)
    if lim is None:
        raise ConfigError("execute_pick needs an arm wrapped in torm.backend.safety.SafeArm (it reads the joint "
                          "velocity/acceleration limits from arm.limits)")
    return np.asarray(lim.qd_max, float), np.asarray(lim.qdd_max, float), min(cfg.speed_scale, lim.speed_scale)


# ------------------------------------------------------------------------------------------------ execution
@dataclass(frozen=True)
class PhaseTiming:
    """One phase of the pick: its name, simulated/robot-clock duration (s) and wall-clock duration (s)."""

    name: str
    sim_s: float
    wall_s: float


@dataclass
class PickResult:
    """What happened in one pick.

    Attributes:
        outcome: the category (:class:`Outcome`): what the robot believes after :func:`execute_pick`, what the judge
            decided once a judge scored it (``sim.judge.PickJudge.verdict``).
        loop_outcome: what the robot believed, kept when a judge replaced :attr:`outcome` (None before).
        object_id: the target object's instance id (-1 when there was no candidate).
        grasp: the executed grasp candidate (None when none was reachable).
        candidate_index: its index in the candidate list (-1 when none).
        flipped: whether the grasp was executed rotated 180 deg about its approach axis.
        translate_direction: (2,) unit horizontal direction of the translation used (None when none was planned).
        unreachable: (index, reason) for the candidates skipped as unreachable.
        judgement: the success test's measurements (filled by the judge, simulation only).
        trace: the sampled object/TCP trace (filled by the judge, simulation only).
        phases: per-phase timings.
        disturbed: other objects' displacement (m) between the start and the end of the pick (judge only).
        target_id: the real object the judge found the attempt acted on (None: none, a phantom attempt).
        neighbours_disturbed: whether any of them moved more than ``PickConfig.neighbour_tolerance``.
        gripper_width: pad gap after closing (m), None if the gripper never closed.
        grip_force: the grip after closing: ``requested_n`` (pad force asked for, N) and, when the gripper reports
            them (simulation), ``commanded_n`` (after clipping to the gripper's range), ``applied_n`` (from its
            force map), ``setting`` (actuator force limit), ``width_m`` and ``measured_n`` (MuJoCo contact forces).
        tcp_errors: one entry per motion: ``phase``, ``position_m`` / ``rotation_rad`` between the measured TCP and
            the forward kinematics of the last commanded joints after the motion settled.
        message: a human-readable explanation for failures.
    """

    outcome: Outcome
    loop_outcome: Outcome | None = None
    target_id: int | None = None
    object_id: int = -1
    grasp: Grasp | None = None
    candidate_index: int = -1
    flipped: bool = False
    translate_direction: np.ndarray | None = None
    unreachable: list[tuple[int, str]] = field(default_factory=list)
    judgement: Judgement | None = None
    trace: PickTrace | None = None
    phases: list[PhaseTiming] = field(default_factory=list)
    disturbed: dict[int, float] = field(default_factory=dict)
    neighbours_disturbed: bool = False
    gripper_width: float | None = None
    grip_force: dict[str, float] | None = None
    tcp_errors: list[dict[str, Any]] = field(default_factory=list)
    message: str = ""

    @property
    def success(self) -> bool:
        return self.outcome is Outcome.SUCCESS

    @property
    def sim_time(self) -> float:
        """Total simulated / robot-clock time of the executed phases (s)."""
        return float(sum(p.sim_s for p in self.phases))

    @property
    def wall_time(self) -> float:
        """Total wall-clock time of the executed phases (s)."""
        return float(sum(p.wall_s for p in self.phases))

    def as_dict(self) -> dict:
        """JSON-ready summary (outcome string, timings, judgement numbers, disturbances)."""
        return {
            "outcome": self.outcome.value,
            "loop_outcome": None if self.loop_outcome is None else self.loop_outcome.value,
            "target_id": self.target_id,
            "object_id": self.object_id,
            "candidate_index": self.candidate_index,
            "flipped": self.flipped,
            "translate_direction": None if self.translate_direction is None else self.translate_direction.tolist(),
            "unreachable": [{"index": i, "reason": r} for i, r in self.unreachable],
            "judgement": None if self.judgement is None else self.judgement.as_dict(),
            "phases": [{"name": p.name, "sim_s": p.sim_s, "wall_s": p.wall_s} for p in self.phases],
            "sim_time_s": self.sim_time,
            "wall_time_s": self.wall_time,
            "disturbed_m": {str(k): v for k, v in self.disturbed.items()},
            "neighbours_disturbed": self.neighbours_disturbed,
            "gripper_width_m": self.gripper_width,
            "grip_force": self.grip_force,
            "tcp_errors": self.tcp_errors,
            "tcp_error_max_m": max((e["position_m"] for e in self.tcp_errors), default=None),
            "message": self.message,
        }


class _Runner:
    """Executes motions and records phase timings."""

    def __init__(self, backend: Backend, cfg: PickConfig, observer: PickObserver | None = None) -> None:
        self.b, self.cfg, self.observer = backend, cfg, observer
        self.vmax, self.amax, self.scale = _limits_of(backend.arm, cfg)
        self.phases: list[PhaseTiming] = []
        self.tcp_errors: list[dict[str, Any]] = []
        self._phase = ""

    def phase(self, name: str, fn: Callable[[], Any]) -> Any:
        t_sim, t_wall = self.b.clock.now(), time.perf_counter()
        self._phase = name
        if self.observer is not None:
            self.observer.phase_started(name)
        try:
            return fn()
        finally:
            self.phases.append(PhaseTiming(name, self.b.clock.now() - t_sim, time.perf_counter() - t_wall))
            if self.observer is not None:
                self.observer.phase_ended(name)

    def _follow(self, t: np.ndarray, q: np.ndarray) -> None:
        """Send the trajectory, then the tracking check: measured TCP vs FK of the last commanded joints."""
        arm = self.b.arm
        st = arm.follow_trajectory(t, q)
        T_cmd = arm.forward_kinematics(np.asarray(q)[-1])
        T = st.T_world_tcp
        pos = float(np.linalg.norm(T[:3, 3] - T_cmd[:3, 3]))
        cos = np.clip((np.trace(T_cmd[:3, :3].T @ T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
        self.tcp_errors.append({"phase": self._phase, "position_m": pos, "rotation_rad": float(np.arccos(cos)),
                                "vector_m": (T[:3, 3] - T_cmd[:3, 3]).tolist()})
        if pos > self.cfg.tcp_tolerance:
            log.warning("TCP %.1f mm off its commanded pose after the %s motion (tolerance %.1f mm)", pos * 1e3,
                        self._phase, self.cfg.tcp_tolerance * 1e3)

    def joint_move(self, q_goal: np.ndarray) -> None:
        q0 = self.b.arm.state().q
        t, q = chain_waypoints(q0, [q_goal], self.vmax, self.amax, self.scale, self.cfg.control_dt)
        self._follow(t, q)

    def line(self, q_wxn: np.ndarray, length: float, speed: float) -> None:
        q_path = np.array(q_wxn, float)
        q_path[0] = self.b.arm.state().q  # start exactly where the arm is (the safety check starts there too)
        t, q = time_line(q_path, length, speed, self.vmax, self.amax, self.scale, self.cfg.control_dt)
        self._follow(t, q)


def execute_pick(backend: Backend, grasp_candidates: Sequence[Grasp], translate_direction: np.ndarray,
                 config: PickConfig | None = None, *,
                 ik: IKSolver | None = None, tool: ToolFrame | None = None,
                 collision: RobotCollisionChecker | None = None,
                 operator_confirm: Callable[[PickResult], bool] | None = None,
                 observer: PickObserver | None = None) -> PickResult:
    """Pick one object: the first reachable candidate (in order) is executed, blind (see the module docstring).

    Args:
        backend: the robot (its ``arm`` must be a SafeArm); only its arm, gripper, clock and robot model are used.
        grasp_candidates: grasps on one object, best first.
        translate_direction: (2,) horizontal direction of the 20 cm translation, or (K, 2) alternatives best first
            (see :func:`free_directions`); the first reachable one is used.
        config: pick settings.
        ik: IK solver on a robot-only model; default built from ``backend.robot_config``.
        tool: TCP axes of the gripper; default from ``backend.robot_config``.
        collision: self/table collision checker; default from ``backend.robot_config`` when
            ``config.check_robot_collisions`` (none without a robot config).
        operator_confirm: real robot only: called after the release with the provisional result; returning False
            turns a success into ``not_released``.
        observer: told of the attempt and of every phase (the simulator's judge); it cannot change the pick.

    Returns the :class:`PickResult` the robot believes (:attr:`PickResult.outcome`); errors of the motion itself
    (physics blow-ups, safety refusals) are reported as outcomes, not raised.
    """
    cfg = config or PickConfig()
    if not len(grasp_candidates):
        return PickResult(Outcome.NO_GRASP, message="no grasp candidates were given")
    rcfg = getattr(backend, "robot_config", None)
    if ik is None or tool is None:
        if rcfg is None:
            raise ConfigError("execute_pick needs ik= and tool= when the backend has no robot_config")
        ik = ik or make_ik_solver(rcfg, cfg.ik)
        tool = tool or ToolFrame.from_robot_config(rcfg)
    if collision is None and cfg.check_robot_collisions and rcfg is not None:
        collision = RobotCollisionChecker.from_robot_config(rcfg, cfg.table_height)
    lim = getattr(backend.arm, "limits", None)
    box = None if lim is None else (np.asarray(lim.workspace_min, float), np.asarray(lim.workspace_max, float))

    q_start = backend.arm.state().q
    plan, idx, failed = plan_first_reachable(grasp_candidates, ik, tool, q_start, translate_direction, cfg, box,
                                             collision)
    if plan is None:
        n_tried = min(len(grasp_candidates), cfg.max_candidates)
        return PickResult(Outcome.UNREACHABLE, object_id=int(grasp_candidates[0].object_id), unreachable=failed,
                          message=f"no reachable candidate among the first {n_tried}")
    g = plan.grasp
    res = PickResult(Outcome.OTHER, object_id=int(g.object_id), grasp=g, candidate_index=idx, flipped=plan.flipped,
                     translate_direction=plan.direction, unreachable=failed)
    run = _Runner(backend, cfg, observer)
    res.phases = run.phases
    res.tcp_errors = run.tcp_errors
    if observer is not None:
        observer.attempt_started(g)
    try:
        _run_pick(backend, plan, run, res, cfg, tool, operator_confirm)
    except PhysicsError as exc:
        res.outcome, res.message = Outcome.PHYSICS, str(exc)
        log.warning("pick aborted: %s", exc)
    except (SafetyError, ExecutionError) as exc:
        res.outcome = Outcome.SAFETY_STOP if isinstance(exc, SafetyError) else Outcome.OTHER
        res.message = f"{type(exc).__name__}: {exc}"
        log.warning("pick aborted: %s", exc)
        backend.arm.stop()
    finally:
        if observer is not None:
            observer.attempt_ended(res)
    return res


def _run_pick(backend: Backend, plan: PickPlan, run: _Runner, res: PickResult, cfg: PickConfig, tool: ToolFrame,
              operator_confirm: Callable[[PickResult], bool] | None) -> None:
    g, grip = plan.grasp, backend.gripper
    open_w = min(tool.max_opening, g.width + cfg.open_margin)
    run.phase("open", lambda: grip.move(open_w, cfg.grip_speed, cfg.grip_force))

    def pre_grasp() -> None:
        if "free" in plan.lines:
            run.line(*plan.lines["free"], cfg.transport_speed)
        else:
            run.joint_move(plan.q_free)
        if "descend" in plan.lines:
            run.line(*plan.lines["descend"], cfg.approach_speed)

    run.phase("pre_grasp", pre_grasp)
    q, n = plan.lines["approach"]
    run.phase("approach", lambda: run.line(q, n, cfg.approach_speed))

    def close():
        st = grip.move(cfg.close_width, cfg.grip_speed, cfg.grip_force)
        backend.clock.sleep(cfg.settle_after_close)
        return st

    res.gripper_width = float(run.phase("close", close).width)
    report = getattr(grip, "grip_report", None)
    res.grip_force = dict(report()) if callable(report) else {"requested_n": float(cfg.grip_force)}

    # Each carrying phase is checked right after it with what the robot can sense: the gripper's object detection.
    stages = (("lift", Outcome.SLIPPED, "did not stay in the hand during the lift"),
              ("translate", Outcome.DROPPED, "was dropped during the translation"))
    for phase, failure, why in stages:
        q, n = plan.lines[phase]
        run.phase(phase, lambda q=q, n=n: run.line(q, n, cfg.transport_speed))
        if not grip.state().object_detected:
            res.outcome, res.message = failure, f"the gripper reports no object: it {why}"
            run.phase("release", lambda: grip.move(open_w, cfg.grip_speed, cfg.grip_force))
            return

    q, n = plan.lines["lower"]
    run.phase("lower", lambda: run.line(q, n, cfg.transport_speed))
    run.phase("release", lambda: grip.move(open_w, cfg.grip_speed, cfg.grip_force))
    q, n = plan.lines["retreat"]

    def retreat() -> None:
        run.line(q, n, cfg.approach_speed)
        backend.clock.sleep(SETTLE_AFTER_RELEASE_S)  # let the released object come to rest

    run.phase("retreat", retreat)
    res.outcome = Outcome.SUCCESS
    if operator_confirm is not None and not operator_confirm(res):
        res.outcome, res.message = Outcome.NOT_RELEASED, "the operator did not confirm the placement"
