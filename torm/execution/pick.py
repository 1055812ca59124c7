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

Judgement. In simulation (``backend.ground_truth`` present) the object's position relative to the TCP is
sampled during lift and translation into a :class:`~torm.execution.success.PickTrace` and judged by
:func:`~torm.execution.success.judge_pick`; the target moving more than ``approach_tolerance`` (or a neighbour
more than ``neighbour_tolerance``) before the fingers close is ``collision_on_approach``. On the real robot
(no ground truth) success means the gripper still detects the object after lift and after translation,
optionally confirmed by ``operator_confirm``.

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
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from torm.backend.protocol import Backend
from torm.backend.safety import SafetyError
from torm.errors import ConfigError, ExecutionError
from torm.execution.errors import PhysicsError
from torm.execution.ik import IKSolver
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
from torm.execution.success import Judgement, Outcome, PickTrace, SuccessCriteria, judge_pick
from torm.execution.trajectory import chain_waypoints
from torm.types import Grasp

__all__ = [
    "ROTATION_RADIUS", "PhaseTiming", "PickConfig", "PickPlan", "PickResult", "ToolFrame", "execute_pick",
    "free_direction", "free_directions", "grasp_to_tcp", "make_ik_solver", "plan_first_reachable", "plan_pick",
    "time_line",
]

log = logging.getLogger(__name__)


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
        outcome: the category (:class:`Outcome`).
        object_id: the target object's instance id (-1 when there was no candidate).
        grasp: the executed grasp candidate (None when none was reachable).
        candidate_index: its index in the candidate list (-1 when none).
        flipped: whether the grasp was executed rotated 180 deg about its approach axis.
        translate_direction: (2,) unit horizontal direction of the translation used (None when none was planned).
        unreachable: (index, reason) for the candidates skipped as unreachable.
        judgement: the success test's measurements (simulation only).
        trace: the sampled object/TCP trace (simulation only).
        phases: per-phase timings.
        disturbed: other objects' displacement (m) between the start and the end of the pick (simulation only).
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


class _Sampler:
    """Step callback recording the object's position relative to the TCP (world frame, m) every ``period`` s."""

    def __init__(self, backend: Backend, object_id: int, period: float) -> None:
        self.backend, self.object_id, self.period = backend, object_id, period
        self.out: list[np.ndarray] | None = None
        self._next = -np.inf

    def rel(self) -> np.ndarray:
        p = self.backend.ground_truth.object_poses()[self.object_id][:3, 3]
        return p - self.backend.arm.state().T_world_tcp[:3, 3]

    def __call__(self, t: float) -> None:
        if self.out is not None and t >= self._next:
            self.out.append(self.rel())
            self._next = t + self.period

    def start(self, out: list[np.ndarray]) -> None:
        self.out, self._next = out, -np.inf
        out.append(self.rel())

    def stop(self) -> None:
        if self.out is not None:
            self.out.append(self.rel())
        self.out = None


class _Runner:
    """Executes motions and records phase timings."""

    def __init__(self, backend: Backend, cfg: PickConfig) -> None:
        self.b, self.cfg = backend, cfg
        self.vmax, self.amax, self.scale = _limits_of(backend.arm, cfg)
        self.phases: list[PhaseTiming] = []
        self.tcp_errors: list[dict[str, Any]] = []
        self._phase = ""

    def phase(self, name: str, fn: Callable[[], Any]) -> Any:
        t_sim, t_wall = self.b.clock.now(), time.perf_counter()
        self._phase = name
        try:
            return fn()
        finally:
            self.phases.append(PhaseTiming(name, self.b.clock.now() - t_sim, time.perf_counter() - t_wall))

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


def _positions(backend: Backend) -> dict[int, np.ndarray] | None:
    gt = backend.ground_truth
    return None if gt is None else {k: T[:3, 3].copy() for k, T in gt.object_poses().items()}


def execute_pick(backend: Backend, grasp_candidates: Sequence[Grasp], translate_direction: np.ndarray,
                 criteria: SuccessCriteria | None = None, config: PickConfig | None = None, *,
                 ik: IKSolver | None = None, tool: ToolFrame | None = None,
                 collision: RobotCollisionChecker | None = None,
                 operator_confirm: Callable[[PickResult], bool] | None = None,
                 ignore_ids: Collection[int] = ()) -> PickResult:
    """Pick one object: the first reachable candidate (in order) is executed and judged.

    Args:
        backend: the robot (its ``arm`` must be a SafeArm; ``ground_truth`` None on the real robot).
        grasp_candidates: grasps on one object, best first.
        translate_direction: (2,) horizontal direction of the 20 cm translation, or (K, 2) alternatives best first
            (see :func:`free_directions`); the first reachable one is used.
        criteria: the success test's tolerances.
        config: pick settings.
        ik: IK solver on a robot-only model; default built from ``backend.robot_config``.
        tool: TCP axes of the gripper; default from ``backend.robot_config``.
        collision: self/table collision checker; default from ``backend.robot_config`` when
            ``config.check_robot_collisions`` (none without a robot config).
        operator_confirm: real robot only: called after the release with the provisional result; returning False
            turns a success into ``not_released``.
        ignore_ids: objects left out of the disturbance checks (e.g. ones this trial already picked and put
            down elsewhere: a released ball may still be rolling).

    Returns a :class:`PickResult`; errors of the motion itself (physics blow-ups, safety refusals) are reported as
    outcomes, not raised.
    """
    cfg = config or PickConfig()
    crit = criteria or SuccessCriteria()
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
    run = _Runner(backend, cfg)
    res.phases = run.phases
    res.tcp_errors = run.tcp_errors
    try:
        _run_pick(backend, plan, run, res, cfg, crit, tool, operator_confirm, frozenset(ignore_ids))
    except PhysicsError as exc:
        res.outcome, res.message = Outcome.PHYSICS, str(exc)
        log.warning("pick aborted: %s", exc)
    except (SafetyError, ExecutionError) as exc:
        res.outcome, res.message = Outcome.OTHER, f"{type(exc).__name__}: {exc}"
        log.warning("pick aborted: %s", exc)
        backend.arm.stop()
    return res


def _run_pick(backend: Backend, plan: PickPlan, run: _Runner, res: PickResult, cfg: PickConfig,
              crit: SuccessCriteria, tool: ToolFrame, operator_confirm: Callable[[PickResult], bool] | None,
              ignore_ids: frozenset[int] = frozenset()) -> None:
    g, arm, grip = plan.grasp, backend.arm, backend.gripper
    k = int(g.object_id)
    before = _positions(backend)
    if before is not None:
        before = {j: p for j, p in before.items() if j == k or j not in ignore_ids}
    if before is not None and k not in before:
        raise ExecutionError(f"grasp targets object {k} but the scene has objects {sorted(before)}")
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

    def disturbance() -> dict[int, float]:
        now = _positions(backend) or {}
        return {j: float(np.linalg.norm(now[j] - p)) for j, p in (before or {}).items()}

    if before is not None:
        moved = disturbance()
        hit = [j for j, dist in moved.items()
               if dist > (cfg.approach_tolerance if j == k else cfg.neighbour_tolerance)]
        if hit:
            res.outcome = Outcome.COLLISION
            res.message = "objects moved before the gripper closed: " + ", ".join(
                f"{j}: {moved[j] * 1000:.1f} mm" for j in hit)
            q, n = plan.lines["approach"]
            run.phase("retreat", lambda: run.line(q[::-1], n, cfg.approach_speed))
            _finish(res, disturbance(), k, cfg)
            return

    def close():
        st = grip.move(cfg.close_width, cfg.grip_speed, cfg.grip_force)
        backend.clock.sleep(cfg.settle_after_close)
        return st

    res.gripper_width = float(run.phase("close", close).width)
    report = getattr(grip, "grip_report", None)
    res.grip_force = dict(report()) if callable(report) else {"requested_n": float(cfg.grip_force)}

    trace = PickTrace(rest=before[k]) if before is not None else None
    res.trace = trace
    sampler = None
    add_cb = getattr(backend, "add_step_callback", None)
    if trace is not None and callable(add_cb):
        sampler = _Sampler(backend, k, cfg.sample_dt)
        add_cb(sampler)

    def transport(name: str, out: list[np.ndarray] | None) -> None:
        q, n = plan.lines[name]
        if sampler is not None and out is not None:
            sampler.start(out)
        elif trace is not None and out is not None:  # no per-step hook: sample the ends only
            out.append(backend.ground_truth.object_poses()[k][:3, 3] - arm.state().T_world_tcp[:3, 3])
        try:
            run.phase(name, lambda: run.line(q, n, cfg.transport_speed))
        finally:
            if sampler is not None and out is not None:
                sampler.stop()
            elif trace is not None and out is not None:
                out.append(backend.ground_truth.object_poses()[k][:3, 3] - arm.state().T_world_tcp[:3, 3])

    def obj() -> np.ndarray:
        return backend.ground_truth.object_poses()[k][:3, 3].copy()

    def tcp() -> np.ndarray:
        return np.asarray(arm.state().T_world_tcp[:3, 3], float).copy()

    if trace is not None:
        trace.tcp_rest = tcp()

    # Each carrying phase is judged right after it: from the true pose in simulation, from the gripper's object
    # detection on the real robot.
    stages = (("lift", "lift_end", Outcome.SLIPPED, "did not stay in the hand during the lift"),
              ("translate", "translate_end", Outcome.DROPPED, "was dropped during the translation"))
    try:
        for phase, end_field, failure, why in stages:
            transport(phase, getattr(trace, phase) if trace is not None else None)
            if trace is not None:
                setattr(trace, end_field, obj())
                setattr(trace, f"tcp_{end_field}", tcp())
                j = judge_pick(trace, crit)
                if j.outcome is failure:
                    return _abort(backend, run, res, cfg, j, f"the object {why}", disturbance, k)
            elif not grip.state().object_detected:
                res.outcome, res.message = failure, f"the gripper reports no object: it {why}"
                run.phase("release", lambda: grip.move(open_w, cfg.grip_speed, cfg.grip_force))
                return
    finally:
        remove = getattr(backend, "remove_step_callback", None)
        if sampler is not None and callable(remove):
            remove(sampler)

    q, n = plan.lines["lower"]
    run.phase("lower", lambda: run.line(q, n, cfg.transport_speed))
    run.phase("release", lambda: grip.move(open_w, cfg.grip_speed, cfg.grip_force))
    q, n = plan.lines["retreat"]

    def retreat() -> None:
        run.line(q, n, cfg.approach_speed)
        if trace is not None:
            backend.clock.sleep(0.2)  # let the released object come to rest before judging

    run.phase("retreat", retreat)
    if trace is not None:
        trace.final = obj()
        res.judgement = judge_pick(trace, crit)
        res.outcome = res.judgement.outcome
        if res.outcome is Outcome.NOT_RELEASED:
            dz_mm = res.judgement.final_height_change * 1000
            res.message = f"the object ended {dz_mm:.1f} mm above/below its rest height"
    else:
        res.outcome = Outcome.SUCCESS
        if operator_confirm is not None and not operator_confirm(res):
            res.outcome, res.message = Outcome.NOT_RELEASED, "the operator did not confirm the placement"
    _finish(res, disturbance(), k, cfg)


def _abort(backend: Backend, run: _Runner, res: PickResult, cfg: PickConfig, j: Judgement, why: str,
           disturbance: Callable[[], dict[int, float]], k: int) -> None:
    """Stop after a failed stage: open the gripper where the arm is and record the verdict."""
    res.judgement, res.outcome, res.message = j, j.outcome, why
    run.phase("release", lambda: backend.gripper.move(backend.gripper.max_width, cfg.grip_speed, cfg.grip_force))
    _finish(res, disturbance(), k, cfg)


def _finish(res: PickResult, moved: dict[int, float], k: int, cfg: PickConfig) -> None:
    res.disturbed = {j: d for j, d in moved.items() if j != k}
    res.neighbours_disturbed = any(d > cfg.neighbour_tolerance for d in res.disturbed.values())
