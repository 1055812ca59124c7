"""The simulated backend: arm, gripper, clock, ground truth and camera rig on a :class:`sim.world.World`.

Implements :class:`torm.backend.protocol.Backend` on MuJoCo so the harness runs the same pick code on the
simulator and on the real robot. Units: m, rad, s, N; world = the table frame, z up (the robot base at its
``base_pose``; world = robot base frame when that is the identity).

* :class:`SimArm` streams joint targets into the arm's position actuators: the commanded waypoints are
  linearly interpolated at ``control_dt`` while physics steps at the model timestep, then the arm settles.
  Every control tick checks the simulation's health (finite state, no new MuJoCo warnings, bounded contact
  forces and object speeds) and raises :class:`~torm.execution.errors.PhysicsError` otherwise.
* :class:`SimGripper` maps an opening width to the command with the robot config's measured map (either
  direction: 0 = open or 255 = open), ramps the command at the requested speed, commands the requested *pad
  force* in newtons (clipped to 20-235 N, the 2F-85's range, and to what the gripper can produce) through the
  gripper's measured force map (:mod:`sim.robots.force_map`: pad force -> actuator force limit at the current width)
  and waits until the fingers stop; an object is detected when the fingers stall short of the commanded width
  (like the Robotiq's ``gOBJ``). :meth:`SimGripper.grip_report` gives the requested, applied and measured pad
  force (MuJoCo contact forces) for the trial record.
* The arm is exposed wrapped in :class:`~torm.backend.safety.SafeArm`: joint limits, speed limits and a TCP
  workspace box from the robot config and :class:`SimBackendConfig`.
* :meth:`SimBackend.add_step_callback` registers ``fn(t)`` called every control tick (simulated time ``t``
  in s), e.g. to sample object and TCP positions for the success test.
* At start-up the backend checks which share of the world's workspace box the arm reaches
  (:mod:`sim.robots.reach`) and refuses an arm that reaches too little, naming ``base_pose``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from sim.robots.force_map import measured_pad_force, pad_distance
from torm.backend.calibration import Calibration
from torm.backend.protocol import ArmState, GripperState
from torm.backend.safety import SafeArm, SafetyLimits
from torm.errors import ConfigError, SceneError, UnknownNameError
from torm.execution.errors import PhysicsError
from torm.types import TriMesh

if TYPE_CHECKING:
    from sim.robots.config import RobotConfig
    from sim.world import World
    from torm.types import Capture

log = logging.getLogger(__name__)

StepCallback = Callable[[float], None]


@dataclass(frozen=True)
class SimBackendConfig:
    """Simulated backend settings (s, m, N, rad/s).

    Attributes:
        control_dt: period at which joint/gripper targets are updated (s); a multiple of the model timestep.
        settle_time: longest wait after a trajectory for the arm to come to rest (s).
        settle_speed: joint speed below which the arm counts as at rest (rad/s).
        speed_scale: fraction of the joint velocity/acceleration limits the safety layer allows, (0, 1].
        workspace_min, workspace_max: TCP box corners in the world (m) enforced by the safety layer.
        gripper_force_range: the pad force range a command is clipped to (N); 2F-85: 20-235.
        gripper_timeout: longest wait for the fingers to stop after the command ramp (s).
        gripper_stall_speed: finger gap speed below which the fingers count as stopped (m/s).
        gripper_stall_time: how long the gap speed must stay below ``gripper_stall_speed`` (s).
        object_detect_tolerance: gap beyond the commanded width at which an object counts as held (m).
        max_contact_force: largest contact constraint force before the simulation counts as exploded (N).
        max_object_speed: largest free-body linear speed before the simulation counts as exploded (m/s).
        reach_check: check at start-up which share of the workspace the arm reaches (:mod:`sim.robots.reach`).
        reach_min_share: refuse the robot (SceneError naming ``base_pose``) when it reaches less than this share;
            None = the robot config's ``reach_min_share`` (robot YAML, default 0.75).
    """

    control_dt: float = 0.002
    settle_time: float = 0.5
    settle_speed: float = 0.01
    speed_scale: float = 0.5
    workspace_min: tuple[float, float, float] = (-0.2, -0.6, -0.005)
    workspace_max: tuple[float, float, float] = (1.0, 0.6, 1.0)
    gripper_force_range: tuple[float, float] = (20.0, 235.0)
    gripper_timeout: float = 2.0
    gripper_stall_speed: float = 0.002
    gripper_stall_time: float = 0.05
    object_detect_tolerance: float = 0.002
    max_contact_force: float = 5000.0
    max_object_speed: float = 10.0
    reach_check: bool = True
    reach_min_share: float | None = None

    def __post_init__(self) -> None:
        for name in ("control_dt", "settle_time", "settle_speed", "gripper_timeout", "gripper_stall_speed",
                     "gripper_stall_time", "object_detect_tolerance", "max_contact_force", "max_object_speed"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"SimBackendConfig.{name} must be positive, got {getattr(self, name)}")
        if not 0.0 < self.speed_scale <= 1.0:
            raise ConfigError(f"SimBackendConfig.speed_scale must be in (0, 1], got {self.speed_scale}")
        if not np.all(np.asarray(self.workspace_max) > np.asarray(self.workspace_min)):
            raise ConfigError("SimBackendConfig.workspace_max must exceed workspace_min on every axis (m)")
        lo, hi = self.gripper_force_range
        if not 0 < lo < hi:
            raise ConfigError(f"SimBackendConfig.gripper_force_range {self.gripper_force_range} must be "
                              "0 < lo < hi (N)")
        if self.reach_min_share is not None and not 0.0 <= self.reach_min_share <= 1.0:
            raise ConfigError(f"SimBackendConfig.reach_min_share must be in [0, 1], got {self.reach_min_share}")


def _site_pose(data: mujoco.MjData, site_id: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = data.site_xmat[site_id].reshape(3, 3)
    T[:3, 3] = data.site_xpos[site_id]
    return T


class _Sim:
    """The shared stepping core: holds the world, advances physics and checks its health every control tick."""

    def __init__(self, world: World, rcfg: RobotConfig, config: SimBackendConfig) -> None:
        self.world, self.rcfg, self.config = world, rcfg, config
        self.ids = world.robot_ids if world.robot_ids is not None else rcfg.resolve(world.model)
        m = self.model = world.model
        self.data = world.data
        ratio = config.control_dt / m.opt.timestep
        self.substeps = max(1, int(round(ratio)))
        if abs(ratio - self.substeps) > 1e-6:
            raise ConfigError(f"SimBackendConfig.control_dt {config.control_dt} s must be a multiple of the model "
                              f"timestep {m.opt.timestep} s")
        self.callbacks: list[StepCallback] = []
        self.execution: Any = None  # sim.realism.ExecutionErrors (latency, joint tracking error) or None
        obj_dofs = [m.jnt_dofadr[m.body_jntadr[o.body_id]] for o in world.objects]
        self._obj_lin = np.array([[a, a + 1, a + 2] for a in obj_dofs], dtype=int).reshape(-1, 3)
        self._warn0 = self._warning_counts()

    def _warning_counts(self) -> np.ndarray:
        return np.array(self.data.warning.number, dtype=np.int64)

    def reset_baseline(self) -> None:
        """Accept the current MuJoCo warning counters as the baseline (after a world reset)."""
        self._warn0 = self._warning_counts()

    def check(self) -> None:
        """Raise PhysicsError if the state is not finite, MuJoCo warned, or contacts/objects exploded.

        Runs after every control tick, so each test is a single reduction that rejects the healthy case at once; the
        offending values are looked up only when one trips (same errors as :meth:`check_reference`)."""
        d = self.data
        # a NaN or inf anywhere makes the sum non-finite (so does a sum beyond 1e308: an exploded state as well)
        if not np.isfinite(d.qpos.sum() + d.qvel.sum() + d.qacc.sum()):
            raise PhysicsError(f"simulation state became NaN/inf at t = {d.time:.3f} s; the trial is aborted")
        warn = d.warning.number
        if (warn > self._warn0).any():
            names = [mujoco.mjtWarning(i).name for i in np.nonzero(warn > self._warn0)[0]]
            raise PhysicsError(f"MuJoCo warning(s) {names} at t = {d.time:.3f} s; the trial is aborted")
        n = d.nefc
        # every constraint force within the limit -> every contact force within it (only contacts are tested)
        if n and np.abs(d.efc_force[:n]).max() > self.config.max_contact_force:
            contact = d.efc_type[:n] >= int(mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS)
            if np.any(contact):
                f = float(np.max(np.abs(d.efc_force[:n][contact])))
                if f > self.config.max_contact_force:
                    raise PhysicsError(f"contact force {f:.0f} N exceeds {self.config.max_contact_force:.0f} N at "
                                       f"t = {d.time:.3f} s (exploding contact); the trial is aborted")
        if len(self._obj_lin):
            v2 = float(np.square(d.qvel[self._obj_lin]).sum(axis=1).max())
            if v2 > self.config.max_object_speed ** 2:
                raise PhysicsError(f"an object moves at {np.sqrt(v2):.1f} m/s (> {self.config.max_object_speed} m/s)"
                                   f" at t = {d.time:.3f} s; the trial is aborted")

    def check_reference(self) -> None:
        """The plain form of :meth:`check` (each condition tested element by element), which tests compare it to."""
        d = self.data
        if not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel)) and np.all(np.isfinite(d.qacc))):
            raise PhysicsError(f"simulation state became NaN/inf at t = {d.time:.3f} s; the trial is aborted")
        warn = self._warning_counts()
        if np.any(warn > self._warn0):
            names = [mujoco.mjtWarning(i).name for i in np.nonzero(warn > self._warn0)[0]]
            raise PhysicsError(f"MuJoCo warning(s) {names} at t = {d.time:.3f} s; the trial is aborted")
        if d.nefc:
            contact = d.efc_type[: d.nefc] >= int(mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS)
            if np.any(contact):
                f = float(np.max(np.abs(d.efc_force[: d.nefc][contact])))
                if f > self.config.max_contact_force:
                    raise PhysicsError(f"contact force {f:.0f} N exceeds {self.config.max_contact_force:.0f} N at "
                                       f"t = {d.time:.3f} s (exploding contact); the trial is aborted")
        if len(self._obj_lin):
            v = float(np.max(np.linalg.norm(d.qvel[self._obj_lin], axis=1)))
            if v > self.config.max_object_speed:
                raise PhysicsError(f"an object moves at {v:.1f} m/s (> {self.config.max_object_speed} m/s) at "
                                   f"t = {d.time:.3f} s; the trial is aborted")

    def tick(self) -> None:
        """Advance one control period, check health, then call the step callbacks with the simulated time (s)."""
        if self.execution is not None:  # the realism profile's latency and joint error act on this step only
            self.execution.step(self.model, self.data, self.substeps)
        else:
            mujoco.mj_step(self.model, self.data, nstep=self.substeps)
        self.check()
        for fn in list(self.callbacks):
            fn(float(self.data.time))

    def run_for(self, seconds: float) -> None:
        """Hold the current controls for ``seconds`` (s) of simulated time."""
        for _ in range(max(0, int(round(seconds / self.config.control_dt)))):
            self.tick()


class SimArm:
    """Position-controlled simulated arm (implements :class:`torm.backend.protocol.Arm`)."""

    def __init__(self, sim: _Sim, robot_model: mujoco.MjModel) -> None:
        self._sim = sim
        ids = sim.ids
        self.joint_names: tuple[str, ...] = tuple(sim.rcfg.arm.joints)
        self._qadr = ids.arm_qadr
        self._dadr = ids.arm_dadr
        self._act = ids.arm_actuators
        self._tcp = ids.tcp_site
        self._fk_model = robot_model  # robot alone, base at base_pose: same world frame as the scene
        self._fk_data = mujoco.MjData(robot_model)
        fk = sim.rcfg.resolve(robot_model)
        self._fk_qadr = fk.arm_qadr
        self._fk_tcp = fk.tcp_site

    def state(self) -> ArmState:
        d = self._sim.data
        mujoco.mj_kinematics(self._sim.model, d)  # site poses of the current qpos (mj_step leaves them one step old)
        return ArmState(q=d.qpos[self._qadr].copy(), qd=d.qvel[self._dadr].copy(),
                        T_world_tcp=_site_pose(d, self._tcp), time=float(d.time))

    def target(self) -> np.ndarray:
        """(n,) joint targets (rad) currently sent to the position actuators."""
        return self._sim.data.ctrl[self._act].copy()

    def forward_kinematics(self, q: np.ndarray) -> np.ndarray:
        """TCP pose (4, 4) in the world for arm joints ``q`` (n,) rad, on the robot-only model (nothing moves)."""
        q = np.asarray(q, float)
        if q.shape != (len(self.joint_names),):
            raise ConfigError(f"forward_kinematics needs {len(self.joint_names)} joint values, got shape {q.shape}")
        self._fk_data.qpos[self._fk_qadr] = q
        mujoco.mj_kinematics(self._fk_model, self._fk_data)
        return _site_pose(self._fk_data, self._fk_tcp)

    def tcp_lever_arms(self) -> np.ndarray | None:
        """(n,) m/rad bounds on the TCP's distance from each joint axis, for the safety layer's path proof."""
        from torm.backend.safety import lever_arms_from_mujoco

        return lever_arms_from_mujoco(self._fk_model, self.joint_names, self._sim.rcfg.arm.tcp_site)

    def follow_trajectory(self, times_s: np.ndarray, q_txn: np.ndarray) -> ArmState:
        """Stream ``q_txn`` (T, n) rad at ``times_s`` (T,) s from now (linear interpolation between samples,
        starting from the current targets), then hold the last target until the arm is at rest."""
        times_s = np.asarray(times_s, float)
        q_txn = np.atleast_2d(np.asarray(q_txn, float))
        sim = self._sim
        knots_t = np.concatenate([[0.0], times_s])
        knots_q = np.vstack([self.target()[None], q_txn])
        dt = sim.config.control_dt
        n = int(np.ceil(knots_t[-1] / dt - 1e-9))
        if sim.execution is not None:
            sim.execution.new_motion(n)
        for k in range(1, n + 1):
            t = min(k * dt, knots_t[-1])
            i = int(np.clip(np.searchsorted(knots_t, t) - 1, 0, len(knots_t) - 2))
            f = (t - knots_t[i]) / (knots_t[i + 1] - knots_t[i])
            sim.data.ctrl[self._act] = knots_q[i] + f * (knots_q[i + 1] - knots_q[i])
            sim.tick()
        sim.data.ctrl[self._act] = knots_q[-1]
        if sim.execution is not None:  # let the delayed targets reach the servo before judging "at rest"
            sim.run_for(sim.execution.latency_s)
        self._settle()
        return self.state()

    def _settle(self) -> None:
        sim = self._sim
        for _ in range(max(1, int(round(sim.config.settle_time / sim.config.control_dt)))):
            if np.max(np.abs(sim.data.qvel[self._dadr])) < sim.config.settle_speed:
                break
            sim.tick()

    def stop(self) -> None:
        """Hold the current joint positions (targets := measured q)."""
        self._sim.data.ctrl[self._act] = self._sim.data.qpos[self._qadr]


class SimGripper:
    """Simulated gripper commanded by width and pad force (implements :class:`torm.backend.protocol.Gripper`)."""

    def __init__(self, sim: _Sim) -> None:
        self._sim = sim
        g = sim.rcfg.gripper
        m = sim.model
        self._g = g
        ids = sim.ids
        self._act = ids.gripper_actuator
        self._left, self._right = ids.left_pads, ids.right_pads
        # contacts with anything but an object (table, robot) do not count as grip force
        self._not_objects = frozenset(int(g) for g in np.nonzero(np.asarray(sim.world.geom_to_instance) == 0)[0])
        self.max_width: float = float(g.geometry.max_opening)
        #: (low, high) pad force a command is clipped to (N).
        self.force_range_n: tuple[float, float] = tuple(float(v) for v in sim.config.gripper_force_range)
        fmap = g.force_map
        #: (widths (m), most pad force there (N)) measured in the force map (``max_force``), or None: what a
        #: position servo or a linkage can squeeze at all, whatever the request.
        self.max_pad_force: tuple[tuple[float, ...], tuple[float, ...]] | None = (
            (tuple(fmap.widths), tuple(fmap.max_force)) if fmap is not None and fmap.max_force is not None else None)
        cmds = np.array([c for c, _ in g.command_to_width])
        widths = np.array([w for _, w in g.command_to_width])
        self._m_per_cmd = float(abs(widths[0] - widths[-1]) / (cmds[-1] - cmds[0]))  # mean gap change per command
        self._cmd_lo, self._cmd_hi = sorted(g.command_range)
        self._forcerange0 = m.actuator_forcerange[self._act].copy()
        self._forcelimited0 = int(m.actuator_forcelimited[self._act])
        self._target_width = self.width()
        self._closing = False
        self.force_n = float(g.force) if g.force is not None else float(self._forcerange0[1])
        self._requested_n = self.force_n
        self._setting = float(self._forcerange0[1])
        self._warned: set[str] = set()
        from sim.robots.ids import force_map_problem

        why = force_map_problem(m, sim.rcfg, ids)
        if why:  # a config built in Python without load_robot_config's check
            raise SceneError(why)

    def reset(self) -> None:
        """Forget the last command (after a world reset) and restore the actuator's force range."""
        m = self._sim.model
        m.actuator_forcerange[self._act] = self._forcerange0
        m.actuator_forcelimited[self._act] = self._forcelimited0
        self.force_n = self._requested_n = float(self._forcerange0[1])
        self._setting = float(self._forcerange0[1])
        self._target_width, self._closing = self.width(), False

    def width(self) -> float:
        """Measured gap between the pads (m): the smallest distance between a left and a right pad geom."""
        sim = self._sim
        mujoco.mj_kinematics(sim.model, sim.data)
        return max(0.0, pad_distance(sim.model, sim.data, self._left, self._right))

    def activate(self) -> None:
        """Nothing to do in simulation (the real 2F-85 needs an activation handshake)."""

    def _detected(self, width: float) -> bool:
        tol = self._sim.config.object_detect_tolerance
        return (width > self._target_width + tol) if self._closing else (width < self._target_width - tol)

    def state(self) -> GripperState:
        w = self.width()
        return GripperState(width=w, command=int(round(float(self._sim.data.ctrl[self._act]))),
                            object_detected=self._detected(w))

    def _warn_once(self, key: str, msg: str, *args: Any) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning(msg, *args)

    def _apply_force(self, width: float) -> None:
        """Set the actuator force limit that gives ``self.force_n`` of pad force at pad gap ``width`` (m)."""
        fmap = self._g.force_map
        f = self.force_n
        if fmap is None:
            setting = f
        else:
            lo, hi = fmap.force_range(width)
            if f > hi + 1e-6:
                self._warn_once("hi", "requested pad force %.1f N exceeds the %.1f N the gripper's force map reaches "
                                "at %.1f mm; using %.1f N", f, hi, width * 1e3, hi)
            elif f < lo - 1e-6:
                self._warn_once("lo", "requested pad force %.1f N is below the %.1f N the gripper's force map starts "
                                "at (%.1f mm); using %.1f N", f, lo, width * 1e3, lo)
            setting = fmap.setting_for(f, width)
        authored = float(self._forcerange0[1]) if self._forcelimited0 else float("inf")
        if setting > authored + 1e-9:
            self._warn_once("above_mjcf", "pad force %.1f N needs an actuator force limit of %.3g at %.1f mm, above "
                            "the MJCF's own %.3g; the limit is raised to it (grip_force.setting records the value "
                            "used)", f, setting, width * 1e3, authored)
        self._setting = float(setting)
        m = self._sim.model
        m.actuator_forcelimited[self._act] = 1
        m.actuator_forcerange[self._act] = (-self._setting, self._setting)

    def applied_force(self, width: float | None = None) -> float:
        """Pad force (N) the current setting gives at ``width`` (m, default: now), from the force map."""
        fmap = self._g.force_map
        if fmap is None:
            return self._setting
        return fmap.pad_force_at(self._setting, self.width() if width is None else width)

    def measured_force(self) -> float:
        """Pad force (N) in the current state: each finger's summed normal contact force on the objects (MuJoCo
        contact forces), averaged over the two fingers."""
        return measured_pad_force(self._sim.model, self._sim.data, self._left, self._right, self._not_objects)

    def grip_report(self) -> dict[str, float]:
        """Requested / applied pad force (N), the actuator setting, the gap (m) and the measured pad force (N)."""
        w = self.width()
        return {"requested_n": self._requested_n, "commanded_n": self.force_n, "applied_n": self.applied_force(w),
                "setting": self._setting, "width_m": w, "measured_n": self.measured_force()}

    def move(self, width_m: float, speed_mps: float = 0.1, force_n: float = 100.0) -> GripperState:
        """Go to pad gap ``width_m`` (m) at ``speed_mps`` (m/s, command ramp) squeezing with ``force_n`` (N) of pad
        force; ``force_n`` is clipped to ``gripper_force_range`` (20-235 N) and to the gripper's force map."""
        sim, g = self._sim, self._g
        if not (np.isfinite(width_m) and np.isfinite(speed_mps) and np.isfinite(force_n)) or speed_mps <= 0:
            raise ConfigError(f"gripper move needs a finite width (m), positive speed (m/s) and force (N); "
                              f"got {width_m}, {speed_mps}, {force_n}")
        width_m = float(np.clip(width_m, 0.0, self.max_width))
        lo, hi = sim.config.gripper_force_range
        self._requested_n = float(force_n)
        self.force_n = float(np.clip(force_n, lo, hi))
        if self.force_n != self._requested_n and "force_clip" not in self._warned:
            self._warned.add("force_clip")
            log.warning("gripper: a pad force of %g N was asked for, outside the %g-%g N range; %g N is commanded "
                        "(the trial record's grip_force shows both)", self._requested_n, lo, hi, self.force_n)
        target = float(np.clip(g.width_to_command(width_m), self._cmd_lo, self._cmd_hi))
        w0 = self.width()
        self._closing = width_m < w0
        self._target_width = width_m
        self._apply_force(w0)
        cmd = float(sim.data.ctrl[self._act])
        rate = speed_mps / self._m_per_cmd * sim.config.control_dt  # command units per control tick
        while abs(target - cmd) > 1e-9:
            cmd = cmd + float(np.clip(target - cmd, -rate, rate))
            sim.data.ctrl[self._act] = cmd
            sim.tick()
            self._apply_force(self.width())
        # wait until the gap stops changing (reached the width, or stalled on an object)
        dt = sim.config.control_dt
        need = max(1, int(round(sim.config.gripper_stall_time / dt)))
        still, w_prev = 0, self.width()
        for _ in range(int(round(sim.config.gripper_timeout / dt))):
            sim.tick()
            w = self.width()
            self._apply_force(w)
            still = still + 1 if abs(w - w_prev) / dt < sim.config.gripper_stall_speed else 0
            w_prev = w
            if still >= need:
                break
        st = self.state()
        log.debug("gripper to %.4f m: at %.4f m, object %s", width_m, st.width, st.object_detected)
        return st


class SimClock:
    """Simulated time (implements :class:`torm.backend.protocol.Clock`); ``sleep`` steps physics."""

    def __init__(self, sim: _Sim) -> None:
        self._sim = sim

    def now(self) -> float:
        return float(self._sim.data.time)

    def sleep(self, seconds: float) -> None:
        """Hold all controls for ``seconds`` (s) of simulated time."""
        self._sim.run_for(seconds)


class SimGroundTruth:
    """True object poses and table height of the world (implements :class:`torm.backend.protocol.GroundTruth`)."""

    def __init__(self, world: World) -> None:
        self._world = world

    def object_poses(self) -> dict[int, np.ndarray]:
        return {o.instance_id: self._world.object_pose(o.instance_id) for o in self._world.objects}

    def table_height(self) -> float:
        return float(self._world.table_height)

    def object_meshes(self) -> dict[int, TriMesh]:
        """Instance id -> the object's outer surface in the world frame at its current pose (m)."""
        return self._world.object_outer_surfaces()


class SimBackend:
    """Everything a trial needs, simulated on a :class:`sim.world.World` (implements the Backend protocol).

    Args:
        world: a built world with a robot (``build_world(..., robot="inovo_2f85")``).
        config: control, settling, gripper and safety settings.
        camera_config: optional ``sim.cameras.rig.CameraRigConfig`` for :meth:`capture`.
        depth_model: optional :class:`sim.depth.DepthModel` making the captures' sensor depth (default ``ideal``).
        depth_seed: seed of the depth model's noise (default: the world's seed).
        renderer: who renders the capture's RGB images: ``mujoco`` (the rig's rasteriser) or ``pbr`` (Mitsuba 3
            path tracing, ``sim.render``); depth and instance masks always come from MuJoCo.
        render_settings: ``torm.capture.render_settings.PbrSettings`` for ``renderer="pbr"``.
        realism: the trial's :class:`sim.realism.RealismRecord` (default: ``world.realism``): its calibration
            errors perturb the camera poses and intrinsics each capture reports, its execution errors act on every
            physics step of the arm (the world builder applied its contact and mass values).

    Attributes:
        arm: the simulated arm wrapped in :class:`SafeArm`; ``arm.inner`` is the raw :class:`SimArm`.
        gripper, clock, ground_truth: see the classes above.
        robot_config: the robot's RobotConfig; ``robot_model`` a robot-only MjModel (for IK / FK), its base at
            ``base_pose`` like in the world.
        reach: the start-up :class:`sim.robots.reach.ReachReport` (None when ``config.reach_check`` is off).

    Raises:
        SceneError: when the arm reaches less than ``config.reach_min_share`` of the workspace (names ``base_pose``).
    """

    name = "sim"

    def __init__(self, world: World, config: SimBackendConfig | None = None, camera_config: Any = None,
                 realism: Any = None, *, renderer: str = "mujoco", render_settings: Any = None,
                 depth_model: Any = None, depth_seed: int | None = None) -> None:
        if world.robot_config is None:
            raise SceneError("SimBackend needs a world with a robot; build it with "
                             "build_world(..., robot='inovo_2f85')")
        self.world = world
        self.config = config or SimBackendConfig()
        self.robot_config: RobotConfig = world.robot_config
        self.robot_model = self.robot_config.robot_model()
        self.reach = None
        if self.config.reach_check:
            from sim.robots.reach import require_reach

            share = self.config.reach_min_share
            self.reach = require_reach(self.robot_config, world.workspace_bounds,
                                       self.robot_config.reach_min_share if share is None else share,
                                       table_height=world.table_height)
        self._sim = _Sim(world, self.robot_config, self.config)
        self.limits = safety_limits(self.robot_config, self.config)
        self.arm = SafeArm(SimArm(self._sim, self.robot_model), self.limits)
        self.gripper = SimGripper(self._sim)
        self.clock = SimClock(self._sim)
        self.ground_truth = SimGroundTruth(world)
        self._camera_config = camera_config
        self._depth_model, self._depth_seed = depth_model, depth_seed
        if renderer not in ("mujoco", "pbr"):
            raise UnknownNameError("capture.renderer", renderer, ("mujoco", "pbr"))
        self.renderer, self._render_settings = renderer, render_settings
        #: render each capture's reference pass (the empty workspace, ``CameraView.reference_rgb``)
        self.reference = False
        self._rgb_renderer: Any = None
        self._rig = None
        self.realism = realism if realism is not None else world.realism
        self._captures: list[dict[str, Any]] = []
        self._n_captures = 0
        self._true_capture: tuple[Any, Any] | None = None  # (reported, true) of the last capture
        if self.realism is not None and (self.realism.latency_s is not None or self.realism.joint_error_std_rad):
            from sim.realism import ExecutionErrors

            self._sim.execution = ExecutionErrors(self.realism, self.arm.inner._act, self.config.control_dt)

    @classmethod
    def from_scenario(cls, scenario: str, seed: int = 0, robot: str = "inovo_2f85",
                      config: SimBackendConfig | None = None) -> SimBackend:
        """Build the world for ``scenario``/``seed`` with ``robot`` and wrap it."""
        from sim.world import build_world

        return cls(build_world(scenario, seed, robot=robot), config)

    def add_step_callback(self, fn: StepCallback) -> StepCallback:
        """Call ``fn(t)`` (simulated time, s) after every control tick until removed; returns ``fn``."""
        self._sim.callbacks.append(fn)
        return fn

    def remove_step_callback(self, fn: StepCallback) -> None:
        """Stop calling ``fn`` (no error if it is not registered)."""
        if fn in self._sim.callbacks:
            self._sim.callbacks.remove(fn)

    def reset(self) -> None:
        """Restore the world's settled state (robot at home, gripper open)."""
        self.world.reset()
        self._sim.reset_baseline()
        self.gripper.reset()
        if self._sim.execution is not None:
            self._sim.execution.reset()

    def _get_rig(self) -> Any:
        if self._rig is None:
            from sim.cameras.rig import SimCameraRig

            if self.renderer != "mujoco" and self._rgb_renderer is None:
                from sim.cameras.renderers import make_renderer

                self._rgb_renderer = make_renderer(self.renderer, self.world, self._render_settings)
            self._rig = SimCameraRig.from_world(self.world, self._camera_config, rgb_renderer=self._rgb_renderer,
                                                depth_model=self._depth_model, depth_seed=self._depth_seed)
        return self._rig

    def capture(self, n_views: int | None = None) -> Capture:
        """Render a multi-view capture with :class:`sim.cameras.rig.SimCameraRig` (robot hidden); RGB from
        :attr:`renderer`.

        With a realism record, the views carry the *reported* poses and intrinsics (hand-eye error, per-view
        jitter, intrinsics error: :func:`sim.realism.perturb_capture`); the images are rendered with the true ones.
        """
        return self._report(self._get_rig().capture(n_views, reference=self.reference))

    def _report(self, capture: Capture) -> Capture:
        """``capture`` as the realism record's calibration errors report it (unchanged without a record)."""
        if self.realism is None:
            return capture
        from sim.realism import perturb_capture

        reported, summary = perturb_capture(self.realism, capture, self._n_captures)
        self._n_captures += 1
        if summary:
            self._captures.append(summary)
        self._true_capture = (reported, capture)
        return reported

    def capture_poses(self, n_views: int | None = None) -> np.ndarray:
        """(V, 4, 4) camera-to-world poses (OpenCV axes, m) of the capture layout, without rendering."""
        return self._get_rig().poses(n_views)

    def capture_views(self, n_views: int | None, indices: Any, channels: Any = None,
                      reference: bool | None = None) -> Capture:
        """Render only the layout views ``indices`` (of ``n_views``) with ``channels`` (default: the rig's);
        ``reference`` (default :attr:`reference`): also each view's reference pass over the empty workspace."""
        ref = self.reference if reference is None else bool(reference)
        return self._report(self._get_rig().capture(n_views, indices=indices, channels=channels, reference=ref))

    def calibration(self) -> Calibration:
        """What the simulated cell declares, as a lab would: the table height and the scenario's fixture (its
        drawing, as boxes, and its pose on the table). Under the ``ideal`` profile they are the values the scene was
        built with (stated error 0); under ``measured`` (and ``stress``) the lab measured them with a tape, so each
        is off by the realism record's draw (``table_height_error_m``, ``fixture_error``: sourced in
        ``sim/REALISM.md``) and the stated error is the range's bound. The decision loop gets nothing else about the
        scene; :meth:`calibration_record` keeps declared, true and error for the judge's record."""
        from sim.world import TABLE_HEIGHT

        rec = self.realism
        dz = float(rec.table_height_error_m) if rec is not None and rec.table_height_error_m is not None else 0.0
        stated = 0.0
        src = f"scenario {self.world.scenario!r} declaration"
        if rec is not None and rec.table_height_error_m is not None:
            from sim.realism import MEASURED

            stated = max(abs(MEASURED.table_height_error.lo), abs(MEASURED.table_height_error.hi))
            src += f", measured by tape (realism {rec.profile})"
        fx = getattr(self.world, "fixture", None)
        fixtures = ()
        if fx is not None:
            decl = fx.declaration()
            if rec is not None and rec.fixture_error is not None:
                from dataclasses import replace

                decl = replace(decl, T_world_fixture=_nudge(decl.T_world_fixture, rec.fixture_error))
            fixtures = (decl,)
        return Calibration(float(TABLE_HEIGHT) + dz, stated, src, fixtures)

    def calibration_record(self) -> dict[str, Any]:
        """The declared calibration beside the truth and their difference (the judge's record; m, rad)."""
        from sim.world import TABLE_HEIGHT

        decl = self.calibration()
        true_z = float(getattr(self.world, "table_height", TABLE_HEIGHT))
        out: dict[str, Any] = {"table_height_m": {"declared": decl.table_height, "true": true_z,
                                                  "error": decl.table_height - true_z}}
        fx = getattr(self.world, "fixture", None)
        if fx is not None:
            Td, Tt = decl.fixtures[0].T_world_fixture, fx.T_world_fixture
            yaw = float(np.arctan2(Td[1, 0], Td[0, 0]) - np.arctan2(Tt[1, 0], Tt[0, 0]))
            out["fixture"] = {"declared_xyz_m": Td[:3, 3].tolist(), "true_xyz_m": Tt[:3, 3].tolist(),
                              "error_xy_m": (Td[:2, 3] - Tt[:2, 3]).tolist(),
                              "error_yaw_rad": float((yaw + np.pi) % (2 * np.pi) - np.pi)}
        return out

    def realism_summary(self) -> dict[str, Any]:
        """What the realism record did in this trial so far: per-capture view jitter, motions and joint errors."""
        out: dict[str, Any] = {"captures": list(self._captures)}
        if self._sim.execution is not None:
            out["execution"] = self._sim.execution.summary()
        return out

    def occlusion_ratio(self, capture: Capture) -> float:
        """The paper's OCC of ``capture`` (taken by :meth:`capture` in the current state): share of views
        in which at least one object is partly hidden by another (0..1)."""
        from sim.cameras.occlusion import occlusion_ratio

        if self._true_capture is not None and capture is self._true_capture[0]:
            capture = self._true_capture[1]  # measure OCC with the true cameras, not the reported ones
        return float(occlusion_ratio(self._get_rig(), capture).ratio)

    def close(self) -> None:
        """Free the camera rig's GL context (and the RGB renderer)."""
        if self._rig is not None:
            self._rig.close()
            self._rig = None
        if self._rgb_renderer is not None:
            self._rgb_renderer.close()
            self._rgb_renderer = None


def _nudge(T_world_x: np.ndarray, error_xy_yaw: tuple[float, float, float]) -> np.ndarray:
    """``T_world_x`` moved by (dx, dy) m in the world and turned by dyaw rad about its own z axis."""
    dx, dy, dyaw = (float(v) for v in error_xy_yaw)
    T = np.array(T_world_x, dtype=np.float64)
    c, s = np.cos(dyaw), np.sin(dyaw)
    T[:3, :3] = T[:3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T[:2, 3] += (dx, dy)
    return T


def safety_limits(rcfg: RobotConfig, config: SimBackendConfig | None = None) -> SafetyLimits:
    """SafetyLimits from a robot config (joint, velocity, acceleration limits) and the backend's box/speed scale."""
    config = config or SimBackendConfig()
    a = rcfg.arm
    return SafetyLimits(
        q_min=tuple(float(v) for v in a.lower), q_max=tuple(float(v) for v in a.upper),
        qd_max=tuple(float(v) for v in a.velocity_limits), qdd_max=tuple(float(v) for v in a.acceleration_limits),
        workspace_min=tuple(config.workspace_min), workspace_max=tuple(config.workspace_max),
        speed_scale=config.speed_scale,
    )
