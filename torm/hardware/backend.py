"""The real-robot backend behind ``--backend real`` (implements :class:`torm.backend.protocol.Backend`).

:class:`RealBackend` puts the Inovo arm (rosbridge), the Robotiq 2F-85 (Modbus RTU) and the wrist D455
behind the same interface as ``sim.backend.SimBackend``: ``name``, ``arm`` (a
:class:`~torm.backend.safety.SafeArm` with the robot config's joint/speed limits, the hardware config's
TCP box and ``speed_scale``), ``gripper``, ``clock`` (wall time), ``ground_truth = None``,
``robot_config``, :meth:`capture` and :meth:`close`.

Capture: the wrist camera is moved through camera poses on the hemisphere band around the workspace
centre (the simulator's Fibonacci layout, :func:`sim.cameras.rig.hemisphere_poses`); each pose becomes a
flange target ``T_world_cam @ inv(T_flange_cam)`` solved with :class:`torm.execution.ik.IKSolver` on the
robot model's flange site; unreachable poses (IK residual, joint limits, flange below
``min_flange_height``) are skipped with a log line; each move is a rest-to-rest minimum-jerk joint
motion through the SafeArm; after ``settle_s`` one frame is read.

Success on the real robot is judged by the pick executor from the gripper (object still detected after
the lift and the translation) plus the optional operator confirmation :func:`operator_prompt`.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from torm.backend.protocol import GripperState
from torm.backend.safety import SafeArm, SafetyError, SafetyLimits
from torm.errors import HardwareError
from torm.execution.trajectory import chain_waypoints
from torm.geometry import invert_T
from torm.hardware.command_log import CommandLog
from torm.hardware.config import HardwareConfig, resolve_hardware_config
from torm.hardware.robotiq import FORCE_RANGE_N
from torm.hardware.rosbridge import InovoArm, MujocoKinematics
from torm.types import Capture

log = logging.getLogger(__name__)


class WallClock:
    """Wall time (implements :class:`torm.backend.protocol.Clock`): ``now`` is ``time.monotonic()`` (s)."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(max(0.0, float(seconds)))


class DryRunGripper:
    """Stands in for the gripper in a dry run: logs every command, moves nothing, reports the commanded width."""

    def __init__(self, command_log: CommandLog, max_width: float = 0.085) -> None:
        self.max_width = float(max_width)
        self.force_range_n = FORCE_RANGE_N  # what the real 2F-85 would clip a command to (N)
        self._log = command_log
        self._width = self.max_width

    def activate(self) -> None:
        self._log.write("dry_run", command="gripper_activate")

    def move(self, width_m: float, speed_mps: float = 0.1, force_n: float = 100.0) -> GripperState:
        self._log.write("dry_run", command="gripper_move", width_m=width_m, speed_mps=speed_mps, force_n=force_n)
        self._width = float(np.clip(width_m, 0.0, self.max_width))
        return self.state()

    def state(self) -> GripperState:
        return GripperState(width=self._width, command=-1, object_detected=False)


def real_safety_limits(rcfg: Any, hw: HardwareConfig) -> SafetyLimits:
    """SafetyLimits from the robot config's joint limits and the hardware config's TCP box and speed scale."""
    a = rcfg.arm
    return SafetyLimits(
        q_min=tuple(float(v) for v in a.lower), q_max=tuple(float(v) for v in a.upper),
        qd_max=tuple(float(v) for v in a.velocity_limits), qdd_max=tuple(float(v) for v in a.acceleration_limits),
        workspace_min=tuple(hw.workspace_min), workspace_max=tuple(hw.workspace_max), speed_scale=hw.speed_scale,
    )


def operator_prompt(result: Any = None, stream_in=None, stream_out=None) -> bool:
    """Ask the operator on stdin whether the object was lifted, carried and put down; True for y/yes.

    Matches the executor's ``operator_confirm(result) -> bool`` hook. Interactive by design (writes the
    question to stdout).
    """
    import sys

    fin, fout = stream_in or sys.stdin, stream_out or sys.stdout
    desc = ""
    if result is not None:
        desc = f" (object {getattr(result, 'object_id', '?')}, provisional outcome {getattr(result, 'outcome', '?')})"
    fout.write(f"Was the object lifted, carried and set down intact{desc}? [y/N] ")
    fout.flush()
    answer = fin.readline().strip().lower()
    return answer in ("y", "yes")


class RealBackend:
    """The real Inovo + Robotiq 2F-85 + D455 (implements the Backend protocol).

    Args:
        robot_config: the robot config (joints, limits, sites, MJCF for FK/IK).
        hardware: the hardware config.
        arm: an already connected :class:`InovoArm` (made from ``hardware`` when None).
        gripper: a gripper (made on ``hardware.gripper.device`` when None).
        camera: a camera with ``read() -> CameraView`` (a RealSense made lazily on the first capture when None).
        command_log: shared JSONL command log (from ``hardware.command_log`` when None).

    Attributes:
        arm: :class:`SafeArm` around the :class:`InovoArm` (``arm.inner``).
        gripper, clock, ground_truth (None), robot_config, robot_model, hardware, command_log.
    """

    name = "real"

    def __init__(self, robot_config: Any, hardware: HardwareConfig, arm: InovoArm | None = None,
                 gripper: Any = None, camera: Any = None, command_log: CommandLog | None = None) -> None:
        self.robot_config = robot_config
        self.hardware = hardware
        self.command_log = command_log or CommandLog(hardware.command_log)
        self.ground_truth = None
        self.clock = WallClock()
        self.limits = real_safety_limits(robot_config, hardware)
        self._owned: list[Any] = []
        try:
            if arm is None:
                arm = make_inovo_arm(robot_config, hardware, self.command_log)
                self._owned.append(arm)
            self.arm = SafeArm(arm, self.limits)
            if gripper is None:
                gripper = (DryRunGripper(self.command_log, robot_config.gripper.geometry.max_opening)
                           if hardware.dry_run else make_robotiq_gripper(hardware, self.command_log))
            self.gripper = gripper
            self._camera = camera
            if hardware.armed and not hardware.dry_run and hardware.enable_on_start:
                arm.enable()
                arm.switch_controller("trajectory")
            # gated like the arm: an unarmed backend activates nothing (activation moves the fingers)
            if hardware.gripper.activate and hardware.armed and not hardware.dry_run:
                self.gripper.activate()
            elif hardware.gripper.activate and not hardware.dry_run:
                log.info("gripper not activated: the backend is not armed")
        except BaseException:
            self.close()
            raise
        self._ik = None

    # -- camera ----------------------------------------------------------------------------------------
    @property
    def camera(self) -> Any:
        """The wrist camera (a RealSense D455 opened on first use)."""
        if self._camera is None:
            from torm.hardware.handeye import load_hand_eye
            from torm.hardware.realsense import RealSenseCamera

            c = self.hardware.camera
            if not c.hand_eye:
                raise HardwareError("camera.hand_eye is not set in the hardware config; calibrate with "
                                    "`torm calibrate hand-eye ... --out hand_eye.yaml` and point camera.hand_eye to it")
            inner: InovoArm = self.arm.inner
            self._camera = RealSenseCamera(load_hand_eye(c.hand_eye), lambda: inner.flange_pose(inner.state().q),
                                           serial=c.serial, width=c.width, height=c.height, fps=c.fps,
                                           depth=c.depth, warmup_frames=c.warmup_frames, timeout_ms=c.timeout_ms)
            self._owned.append(self._camera)
        return self._camera

    def T_flange_cam(self) -> np.ndarray:
        """The hand-eye transform of the camera in use."""
        cam = self.camera
        T = getattr(cam, "T_flange_cam", None)
        if T is None:
            raise HardwareError("the camera has no T_flange_cam (hand-eye calibration)")
        return np.asarray(T, float)

    @property
    def robot_model(self):
        """A robot-only MuJoCo model (for IK / FK), like ``SimBackend.robot_model``."""
        if getattr(self, "_robot_model", None) is None:
            from torm.execution.robot_model import robot_model_of

            self._robot_model = robot_model_of(self.robot_config)
        return self._robot_model

    def _ik_solver(self):
        if self._ik is None:
            from torm.execution.ik import IKSolver

            arm = self.robot_config.arm
            self._ik = IKSolver(self.robot_model, tuple(arm.joints), arm.flange_site)
        return self._ik

    @staticmethod
    def _solve_ik(ik, T_target: np.ndarray, seeds: list[np.ndarray], rounds: int = 3):
        """IK from each seed, continuing from the last iterate up to ``rounds`` times; the best result."""
        best = None
        for seed in seeds:
            q = np.asarray(seed, float)
            for _ in range(rounds):
                res = ik.solve(T_target, q)
                if best is None or res.pos_err + 0.1 * res.rot_err < best.pos_err + 0.1 * best.rot_err:
                    best = res
                if res.converged or res.pos_err > 0.05:
                    break
                q = res.q
            if best is not None and best.converged:
                return best
        return best

    def capture_joint_targets(self, n_views: int, q_start: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """[(view index, joints (n,) rad)] reaching the hemisphere camera poses; unreachable ones skipped (logged)."""
        from sim.cameras.rig import hemisphere_poses

        c = self.hardware.capture
        poses = hemisphere_poses(n_views, c.radius, c.centre, c.elevation_min_deg, c.elevation_max_deg,
                                 c.target_height)
        T_cam_flange = invert_T(self.T_flange_cam())
        ik = self._ik_solver()
        lo, hi = self.robot_config.arm.lower, self.robot_config.arm.upper
        out, q_seed = [], np.asarray(q_start, float)
        for i, T_world_cam in enumerate(poses):
            T_world_flange = T_world_cam @ T_cam_flange
            if T_world_flange[2, 3] < c.min_flange_height:
                log.info("capture view %d skipped: flange at z %.3f m < %.3f m", i, T_world_flange[2, 3],
                         c.min_flange_height)
                continue
            res = self._solve_ik(ik, T_world_flange, [q_seed, self.robot_config.arm.home_q])
            if not res.converged or np.any(res.q < lo) or np.any(res.q > hi):
                log.info("capture view %d skipped: unreachable (IK residual %.1f mm / %.1f deg)", i,
                         res.pos_err * 1000, np.degrees(res.rot_err))
                continue
            tcp = self.arm.forward_kinematics(res.q)[:3, 3]
            if np.any(tcp < self.limits.workspace_min) or np.any(tcp > self.limits.workspace_max):
                log.info("capture view %d skipped: TCP %s outside the safety box", i, np.round(tcp, 3).tolist())
                continue
            out.append((i, res.q.copy()))
            q_seed = res.q
        return out

    def move_to(self, q_goal: np.ndarray) -> None:
        """Rest-to-rest minimum-jerk joint move to ``q_goal`` (rad) through the safety layer."""
        a = self.robot_config.arm
        q0 = self.arm.state().q
        if np.max(np.abs(np.asarray(q_goal) - q0)) < 1e-4:
            return
        times, q = chain_waypoints(q0, np.asarray(q_goal, float)[None], np.asarray(a.velocity_limits),
                                   np.asarray(a.acceleration_limits), self.hardware.speed_scale * 0.95, dt=0.02)
        self.arm.follow_trajectory(times, q)

    def capture(self, n_views: int | None = None) -> Capture:
        """Move the wrist camera over the hemisphere and read one frame per reachable pose."""
        c = self.hardware.capture
        n = int(n_views or 50)
        targets = self.capture_joint_targets(n, self.arm.state().q)
        if not targets:
            raise HardwareError(f"none of the {n} capture poses is reachable; check capture.radius/centre and "
                                "the hand-eye transform")
        if len(targets) < n:
            log.warning("capture: %d of %d views reachable", len(targets), n)
        views, qs, taken = [], [], []
        for i, q in targets:
            try:
                self.move_to(q)
            except SafetyError as exc:  # e.g. the joint-space path between two views dips below the table
                log.warning("capture view %d skipped: the move there was refused (%s)", i, exc)
                continue
            self.clock.sleep(c.settle_s)
            v = self.camera.read()
            views.append(v.with_(name=f"view_{i:03d}"))
            taken.append(i)
            qs.append(self.arm.state().q.tolist())
        if c.return_home:
            self.move_to(self.robot_config.arm.home_q)
        if not views:
            raise HardwareError("capture: every move to a capture pose was refused by the safety layer")
        return Capture(views=tuple(views), scenario=c.label, table_height=c.table_height,
                       workspace_bounds=np.asarray(c.workspace_bounds, float),
                       metadata={"backend": "real", "view_indices": taken, "requested_views": n,
                                 "joint_positions": qs, "dry_run": self.hardware.dry_run})

    def calibration(self) -> Any:
        """The cell's declared calibration from the hardware config (table height with its error, fixtures)."""
        return self.hardware.calibration()

    def operator_confirm(self):
        """The operator confirmation hook for the executor (None unless ``operator_confirm`` is set)."""
        return operator_prompt if self.hardware.operator_confirm else None

    def close(self) -> None:
        """The stop path (also on SIGTERM in a bench worker): cancel every arm goal and disable the arm
        (``disable_on_close``), then close the camera and the connections (idempotent)."""
        inner = getattr(getattr(self, "arm", None), "inner", None)
        if isinstance(inner, InovoArm) and not getattr(self, "_stopped", False):
            self._stopped = True
            inner.shutdown(disable=self.hardware.disable_on_close)
        for obj in reversed(self._owned):
            try:
                obj.close()
            except Exception as exc:  # keep closing the rest
                log.warning("closing %s failed: %s", type(obj).__name__, exc)
        self._owned.clear()
        g = getattr(self, "gripper", None)
        transport = getattr(getattr(g, "client", None), "transport", None)
        if transport is not None and hasattr(transport, "close"):
            transport.close()


def make_inovo_arm(robot_config: Any, hw: HardwareConfig, command_log: CommandLog) -> InovoArm:
    """Connect to the Inovo arm described by ``hw`` with FK on the robot config's MJCF."""
    a = robot_config.arm
    from torm.execution.robot_model import robot_model_of

    kin = MujocoKinematics(robot_model_of(robot_config), tuple(a.joints), a.tcp_site, a.flange_site)
    return InovoArm(hw.host, hw.port, tuple(a.joints), kin, armed=hw.armed, dry_run=hw.dry_run,
                    watchdog_s=hw.watchdog_s, connect_timeout_s=hw.connect_timeout_s,
                    result_timeout_s=hw.result_timeout_s, command_log=command_log,
                    disable_on_fault=hw.disable_on_fault, joint_states_topic=hw.joint_states_topic,
                    tcp_pose_topic=hw.tcp_pose_topic, action_ns=hw.action_ns, enable_service=hw.enable_service,
                    disable_service=hw.disable_service, switch_controller_service=hw.switch_controller_service,
                    switch_controller_arg=hw.switch_controller_arg, stream=hw.stream,
                    accel_limits=hw.speed_scale * np.asarray(a.acceleration_limits, float),
                    path_tolerance_rad=hw.path_tolerance_rad, goal_tolerance_rad=hw.goal_tolerance_rad,
                    goal_time_tolerance_s=hw.goal_time_tolerance_s)


def make_robotiq_gripper(hw: HardwareConfig, command_log: CommandLog):
    """Open the serial port and wrap the 2F-85 (calibration from ``hw.gripper.calibration`` when set)."""
    from torm.hardware.modbus import ModbusRTUClient, open_serial
    from torm.hardware.robotiq import GripperCalibration, RobotiqGripper

    g = hw.gripper
    cal = GripperCalibration.load(g.calibration) if g.calibration else None
    transport = open_serial(g.device, g.baudrate, g.timeout_s)
    client = ModbusRTUClient(transport, g.slave, port_label=f"{g.device} @ {g.baudrate}")
    return RobotiqGripper(client, cal, move_timeout_s=g.move_timeout_s, command_log=command_log, armed=hw.armed)


def make_real_backend(trial_config: Any = None, hardware: HardwareConfig | None = None) -> RealBackend:
    """The backend for ``--backend real``: robot config from ``trial_config.robot``, hardware config from
    ``trial_config.hardware_config`` / $TORM_HARDWARE_CONFIG (see :func:`resolve_hardware_config`)."""
    from sim.robots.config import load_robot_config

    hw = hardware or resolve_hardware_config(trial_config)
    rcfg = load_robot_config(getattr(trial_config, "robot", None) or "inovo_2f85")
    log.info("real backend: %s:%d, armed %s, dry run %s, speed scale %.2f", hw.host, hw.port, hw.armed,
             hw.dry_run, hw.speed_scale)
    return RealBackend(rcfg, hw)
