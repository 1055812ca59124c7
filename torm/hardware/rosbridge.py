"""The Inovo arm over its rosbridge websocket (implements :class:`torm.backend.protocol.Arm`).

Protocol (HARDWARE.md; ROS 1 Noetic behind rosbridge v2 JSON):

- state: ``/joint_states`` (sensor_msgs/JointState) and ``/default_move_group/tcp_pose`` (PoseStamped);
- services: ``/robot/enable``, ``/robot/disable`` (std_srvs/Trigger), ``/robot/switch_controller``
  (``"trajectory"`` | ``"velocity"`` | ``"zerog"``);
- motion: control_msgs/FollowJointTrajectory goals published on the actionlib topic
  ``<action_ns>/goal`` (FollowJointTrajectoryActionGoal), results on ``<action_ns>/result``, cancel on
  ``<action_ns>/cancel`` (actionlib_msgs/GoalID). A motion is **streamed** as short goals that each end
  at rest (:mod:`torm.hardware.streaming`): a new goal replaces the running one every ``period_s``;
  when none arrives (link down, process dead or hung) the controller finishes the last one and
  stands still within :attr:`InovoArm.stop_within_s`. Each goal carries per-joint path and goal
  tolerances and a goal time tolerance, so the controller aborts (and holds) when tracking fails.

Safety, on top of :class:`~torm.backend.safety.SafeArm` (which every backend's arm goes through):

- nothing that can move the robot is sent unless ``armed=True``: otherwise ``HardwareError("not armed: ...")``;
- ``dry_run=True`` logs every planned trajectory to the command log and sends nothing; the arm then
  reports the last planned waypoint as its position so a whole pick can be rehearsed;
- a watchdog thread stops the arm (cancel goal, optionally /robot/disable) when no /joint_states
  message arrived for ``watchdog_s`` or the websocket drops; after that every command raises
  HardwareError until a new :class:`InovoArm` is made;
- :meth:`InovoArm.shutdown` (what the backend's ``close`` calls, also on SIGTERM) cancels every goal and
  calls /robot/disable;
- every command (sent, refused, or withheld in a dry run) is appended to a JSONL :class:`CommandLog`.

Forward kinematics uses the robot config's MuJoCo model (the same MJCF as the simulator), so the TCP pose
the planner uses is the model's ``tcp_site``; the controller's own ``tcp_pose`` is kept in
:attr:`InovoArm.reported_tcp_pose` for comparison.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from torm.backend.protocol import ArmState
from torm.backend.safety import lever_arms_from_mujoco
from torm.errors import HardwareError
from torm.geometry import quat_wxyz_to_R
from torm.hardware.command_log import CommandLog
from torm.hardware.rosbridge_client import RosbridgeClient
from torm.hardware.streaming import StreamPlan, StreamSettings

log = logging.getLogger(__name__)

CONTROLLERS = ("trajectory", "velocity", "zerog")
GOAL_TYPE = "control_msgs/FollowJointTrajectoryActionGoal"
RESULT_TYPE = "control_msgs/FollowJointTrajectoryActionResult"
CANCEL_TYPE = "actionlib_msgs/GoalID"
#: actionlib_msgs/GoalStatus codes.
STATUS_NAMES = {0: "PENDING", 1: "ACTIVE", 2: "PREEMPTED", 3: "SUCCEEDED", 4: "ABORTED", 5: "REJECTED",
                6: "PREEMPTING", 7: "RECALLING", 8: "RECALLED", 9: "LOST"}
PREEMPTED, SUCCEEDED = 2, 3
TERMINAL = {2, 3, 4, 5, 8, 9}


def ros_duration(seconds: float) -> dict[str, int]:
    """ROS 1 duration ``{secs, nsecs}`` for ``seconds`` >= 0."""
    secs = int(np.floor(seconds))
    nsecs = int(round((seconds - secs) * 1e9))
    if nsecs >= 1_000_000_000:
        secs, nsecs = secs + 1, nsecs - 1_000_000_000
    return {"secs": secs, "nsecs": nsecs}


def _pose_to_T(pose: dict[str, Any]) -> np.ndarray:
    p, o = pose.get("position", {}), pose.get("orientation", {})
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_R(np.array([o.get("w", 1.0), o.get("x", 0.0), o.get("y", 0.0), o.get("z", 0.0)]))
    T[:3, 3] = [p.get("x", 0.0), p.get("y", 0.0), p.get("z", 0.0)]
    return T


class MujocoKinematics:
    """Forward kinematics of the robot MJCF: TCP and flange site poses (4, 4) for arm joints (n,) rad."""

    def __init__(self, mjcf: str | Path | mujoco.MjModel, joint_names: tuple[str, ...], tcp_site: str,
                 flange_site: str) -> None:
        self.model = mjcf if isinstance(mjcf, mujoco.MjModel) else mujoco.MjModel.from_xml_path(str(mjcf))
        self.data = mujoco.MjData(self.model)
        self._qadr = np.array([self.model.jnt_qposadr[self.model.joint(j).id] for j in joint_names])
        self._tcp = self.model.site(tcp_site).id
        self._flange = self.model.site(flange_site).id
        self._lock = threading.Lock()
        self.joint_names, self.tcp_site = tuple(joint_names), tcp_site

    def _site(self, q: np.ndarray, sid: int) -> np.ndarray:
        q = np.asarray(q, float)
        if q.shape != self._qadr.shape:
            raise HardwareError(f"forward kinematics needs {len(self._qadr)} joint values, got shape {q.shape}")
        with self._lock:
            self.data.qpos[self._qadr] = q
            mujoco.mj_kinematics(self.model, self.data)
            T = np.eye(4)
            T[:3, :3] = self.data.site_xmat[sid].reshape(3, 3)
            T[:3, 3] = self.data.site_xpos[sid]
        return T

    def tcp(self, q: np.ndarray) -> np.ndarray:
        return self._site(q, self._tcp)

    def flange(self, q: np.ndarray) -> np.ndarray:
        return self._site(q, self._flange)

    def tcp_lever_arms(self) -> np.ndarray | None:
        """(n,) m/rad bounds on the TCP's distance from each joint axis (:func:`lever_arms_from_mujoco`)."""
        return lever_arms_from_mujoco(self.model, self.joint_names, self.tcp_site)


class InovoArm:
    """The real Inovo arm through rosbridge.

    Args:
        host, port: rosbridge websocket.
        joint_names: arm joints in the order of the robot config (must appear in /joint_states).
        kinematics: forward kinematics of the robot model.
        armed: allow commands that can move the robot.
        dry_run: log planned motions, send nothing that moves the robot.
        watchdog_s: stop when no /joint_states for this long (s).
        connect_timeout_s: handshake and first-message timeout (s).
        result_timeout_s: slack after the trajectory duration for the action result (s).
        command_log: where commands are recorded (a :class:`CommandLog`).
        disable_on_fault: also call the disable service when the watchdog trips.
        stream: how motions are cut into chunks that end at rest (:class:`StreamSettings`).
        accel_limits: (n,) rad/s^2 the braking tails are scaled from (the safety layer's speed_scale x
            qdd_max; None: each trajectory's own peak acceleration).
        path_tolerance_rad, goal_tolerance_rad, goal_time_tolerance_s: sent with every goal (controller-side
            abort when the tracking error exceeds them; 0 = the controller's defaults).
        topics/services: see :class:`torm.hardware.config.HardwareConfig`.
    """

    def __init__(self, host: str, port: int, joint_names: tuple[str, ...], kinematics: MujocoKinematics,
                 armed: bool = False, dry_run: bool = False, watchdog_s: float = 0.5,
                 connect_timeout_s: float = 5.0, result_timeout_s: float = 5.0,
                 command_log: CommandLog | None = None, disable_on_fault: bool = True,
                 joint_states_topic: str = "/joint_states", tcp_pose_topic: str = "/default_move_group/tcp_pose",
                 action_ns: str = "/robot/joint_trajectory_controller/follow_joint_trajectory",
                 enable_service: str = "/robot/enable", disable_service: str = "/robot/disable",
                 switch_controller_service: str = "/robot/switch_controller",
                 switch_controller_arg: str = "data", stream: StreamSettings | None = None,
                 accel_limits: np.ndarray | None = None, path_tolerance_rad: float = 0.1,
                 goal_tolerance_rad: float = 0.01, goal_time_tolerance_s: float = 0.5) -> None:
        self.joint_names: tuple[str, ...] = tuple(joint_names)
        self.stream = stream or StreamSettings()
        self.accel_limits = None if accel_limits is None else np.asarray(accel_limits, float)
        self.path_tolerance_rad, self.goal_tolerance_rad = float(path_tolerance_rad), float(goal_tolerance_rad)
        self.goal_time_tolerance_s = float(goal_time_tolerance_s)
        #: Stop bound (s) of the motion last sent: the arm is at rest this long after the last chunk arrived.
        self.stop_within_s: float | None = None
        self.kin = kinematics
        self.armed, self.dry_run = bool(armed), bool(dry_run)
        self.watchdog_s = float(watchdog_s)
        self.result_timeout_s = float(result_timeout_s)
        self.log = command_log or CommandLog(None)
        self.disable_on_fault = disable_on_fault
        self.action_ns = action_ns.rstrip("/")
        self.enable_service, self.disable_service = enable_service, disable_service
        self.switch_controller_service, self.switch_controller_arg = switch_controller_service, switch_controller_arg
        self.host, self.port = host, int(port)
        self.fault: str | None = None
        self.reported_tcp_pose: np.ndarray | None = None
        self._js_lock = threading.Lock()
        self._q: np.ndarray | None = None
        self._qd = np.zeros(len(self.joint_names))
        self._last_js = 0.0
        self._first_js = threading.Event()
        self._results: dict[str, dict[str, Any]] = {}
        self._result_cv = threading.Condition()
        self._goal_counter = 0
        self._active_goal: str | None = None
        self._virtual_q: np.ndarray | None = None
        self._stop_watchdog = threading.Event()
        self._trip_lock = threading.Lock()

        self.log.write("connect", host=host, port=self.port, armed=self.armed, dry_run=self.dry_run)
        self.client = RosbridgeClient(host, port, connect_timeout_s, on_disconnect=self._on_disconnect)
        try:
            self.client.subscribe(joint_states_topic, "sensor_msgs/JointState", self._on_joint_states)
            self.client.subscribe(tcp_pose_topic, "geometry_msgs/PoseStamped", self._on_tcp_pose)
            self.client.subscribe(f"{self.action_ns}/result", RESULT_TYPE, self._on_result, queue_length=10)
            if not self.dry_run:
                self.client.advertise(f"{self.action_ns}/goal", GOAL_TYPE)
                self.client.advertise(f"{self.action_ns}/cancel", CANCEL_TYPE)
            if not self._first_js.wait(connect_timeout_s):
                raise HardwareError(f"no {joint_states_topic} message from {host}:{self.port} within "
                                    f"{connect_timeout_s} s; is the robot driver running (rostopic hz "
                                    f"{joint_states_topic})?")
            if self.fault:
                raise HardwareError(f"arm fault right after connecting: {self.fault}")
        except BaseException:
            self.client.close()
            raise
        self._watchdog = threading.Thread(target=self._watchdog_loop, name="inovo-watchdog", daemon=True)
        self._watchdog.start()

    # -- incoming messages ---------------------------------------------------------------------------
    def _on_joint_states(self, msg: dict[str, Any]) -> None:
        names = list(msg.get("name") or [])
        pos = list(msg.get("position") or [])
        vel = list(msg.get("velocity") or [])
        try:
            idx = [names.index(j) for j in self.joint_names]
        except ValueError:
            self._trip(f"/joint_states lacks joints {[j for j in self.joint_names if j not in names]} "
                       f"(has {names}); fix arm.joints in the robot config")
            return
        q = np.array([pos[i] for i in idx], float)
        qd = np.array([vel[i] for i in idx], float) if len(vel) == len(names) else np.zeros(len(idx))
        with self._js_lock:
            self._q, self._qd, self._last_js = q, qd, time.monotonic()
        self._first_js.set()

    def _on_tcp_pose(self, msg: dict[str, Any]) -> None:
        self.reported_tcp_pose = _pose_to_T(msg.get("pose") or {})

    def _on_result(self, msg: dict[str, Any]) -> None:
        gid = ((msg.get("status") or {}).get("goal_id") or {}).get("id", "")
        with self._result_cv:
            self._results[gid] = msg
            self._result_cv.notify_all()

    def _on_disconnect(self, reason: str) -> None:
        self._trip(f"rosbridge connection to {self.host}:{self.port} dropped ({reason})")

    # -- watchdog ------------------------------------------------------------------------------------
    def _watchdog_loop(self) -> None:
        period = max(0.005, self.watchdog_s / 5)
        while not self._stop_watchdog.wait(period):
            with self._js_lock:
                age = time.monotonic() - self._last_js
            if age > self.watchdog_s:
                self._trip(f"no /joint_states for {age:.2f} s (watchdog {self.watchdog_s} s)")
                return
            if self.fault:
                return

    def _trip(self, reason: str) -> None:
        """Enter the fault state once: cancel motion while the socket is up, then refuse every command."""
        with self._trip_lock:
            if self.fault is not None:
                return
            self.fault = reason
        log.error("Inovo arm stopped: %s", reason)
        self.log.write("fault", reason=reason)
        if not self.dry_run and self.client.connected:
            try:
                self._send_cancel()
                if self.disable_on_fault:
                    self.log.write("call_service", service=self.disable_service, reason="watchdog")
                    self.client.call_service(self.disable_service, {}, wait=False)
            except HardwareError as exc:
                log.error("could not send the stop after a fault: %s", exc)
        with self._result_cv:
            self._result_cv.notify_all()

    def _check_ok(self, what: str) -> None:
        if self.fault is not None:
            raise HardwareError(f"{what} refused: the arm was stopped ({self.fault}); check the connection and "
                                "the robot, then reconnect (make a new backend)")

    def _require_armed(self, what: str, **payload: Any) -> None:
        if not self.armed:
            self.log.write("refused", command=what, reason="not armed", **payload)
            raise HardwareError(f"not armed: refusing to {what}; pass --arm-robot (or armed: true in the hardware "
                                "config) once the workspace is clear and an operator holds the e-stop")

    # -- services ------------------------------------------------------------------------------------
    def _service(self, what: str, service: str, args: dict[str, Any]) -> dict[str, Any]:
        if self.dry_run:
            self.log.write("dry_run", command="call_service", service=service, args=args)
            return {"success": True, "message": "dry run"}
        self.log.write("call_service", service=service, args=args)
        values = self.client.call_service(service, args)
        if values.get("success") is False:
            raise HardwareError(f"{what} failed: {values.get('message', '')!r}; check the robot's status (e-stop, "
                                "safe stop, power: /psu/estop/reset, /psu/safe_stop/reset)")
        return values

    def enable(self) -> None:
        """Enable the arm (/robot/enable, std_srvs/Trigger); requires ``armed``."""
        self._check_ok("enable")
        self._require_armed("enable the robot")
        self._service("enable", self.enable_service, {})

    def disable(self) -> None:
        """Disable the arm (/robot/disable); always allowed."""
        if self.client.connected:
            self._service("disable", self.disable_service, {})

    def switch_controller(self, name: str) -> None:
        """Switch the active controller to ``"trajectory"``, ``"velocity"`` or ``"zerog"``; requires ``armed``."""
        if name not in CONTROLLERS:
            raise HardwareError(f"unknown controller {name!r}; valid: {', '.join(CONTROLLERS)}")
        self._check_ok("switch_controller")
        self._require_armed(f"switch the controller to {name!r}")
        self._service("switch_controller", self.switch_controller_service, {self.switch_controller_arg: name})

    # -- Arm protocol --------------------------------------------------------------------------------
    def measured_q(self) -> np.ndarray:
        """(n,) joint positions (rad) from the latest /joint_states."""
        with self._js_lock:
            if self._q is None:
                raise HardwareError("no /joint_states received yet")
            return self._q.copy()

    def state(self) -> ArmState:
        """Latest joint state; in a dry run after a planned motion, the last planned waypoint (qd = 0)."""
        if self.dry_run and self._virtual_q is not None:
            q, qd = self._virtual_q.copy(), np.zeros(len(self.joint_names))
        else:
            with self._js_lock:
                if self._q is None:
                    raise HardwareError("no /joint_states received yet")
                q, qd = self._q.copy(), self._qd.copy()
        return ArmState(q=q, qd=qd, T_world_tcp=self.kin.tcp(q), time=time.monotonic())

    def forward_kinematics(self, q: np.ndarray) -> np.ndarray:
        """TCP pose (4, 4) in the base frame for joints ``q`` (n,) rad (MuJoCo model, nothing moves)."""
        return self.kin.tcp(q)

    def flange_pose(self, q: np.ndarray) -> np.ndarray:
        """Flange pose T_world_flange (4, 4) for joints ``q`` (n,) rad."""
        return self.kin.flange(q)

    def tcp_lever_arms(self) -> np.ndarray | None:
        """(n,) m/rad for the safety layer's path check (from the robot model)."""
        return self.kin.tcp_lever_arms() if hasattr(self.kin, "tcp_lever_arms") else None

    def _tolerances(self, value: float) -> list[dict[str, Any]]:
        return [{"name": j, "position": value, "velocity": 0.0, "acceleration": 0.0} for j in self.joint_names]

    def goal_message(self, times_s: np.ndarray, q_txn: np.ndarray, goal_id: str) -> dict[str, Any]:
        """The FollowJointTrajectoryActionGoal for waypoints ``q_txn`` (T, n) rad at ``times_s`` (T,) s from now.

        Position-only points (the controller interpolates linearly between them, the path the safety layer
        checked), per-joint path and goal tolerances (rad) and the goal time tolerance (s).
        """
        stamp = {"secs": 0, "nsecs": 0}
        points = [{"positions": [float(v) for v in q], "velocities": [], "accelerations": [], "effort": [],
                   "time_from_start": ros_duration(float(t))} for t, q in zip(times_s, q_txn, strict=True)]
        return {
            "header": {"seq": 0, "stamp": stamp, "frame_id": ""},
            "goal_id": {"stamp": stamp, "id": goal_id},
            "goal": {
                "trajectory": {"header": {"seq": 0, "stamp": stamp, "frame_id": ""},
                               "joint_names": list(self.joint_names), "points": points},
                "path_tolerance": self._tolerances(self.path_tolerance_rad),
                "goal_tolerance": self._tolerances(self.goal_tolerance_rad),
                "goal_time_tolerance": ros_duration(self.goal_time_tolerance_s),
            },
        }

    def follow_trajectory(self, times_s: np.ndarray, q_txn: np.ndarray) -> ArmState:
        """Stream the waypoints as chunks that end at rest (module docstring); block until the motion is done.

        Raises HardwareError (after cancelling) on a fault, an aborted chunk, a stream that fell behind
        (the arm then brakes to a stop on its own) or a missing final result.
        """
        times_s = np.asarray(times_s, float).reshape(-1)
        q_txn = np.atleast_2d(np.asarray(q_txn, float))
        if q_txn.shape != (len(times_s), len(self.joint_names)):
            raise HardwareError(f"trajectory needs ({len(times_s)}, {len(self.joint_names)}) joint values, "
                                f"got {q_txn.shape}")
        self._check_ok("follow_trajectory")
        q0 = self.state().q
        summary = {"n_points": len(times_s), "duration_s": float(times_s[-1]) if len(times_s) else 0.0,
                   "q_start": q0, "q_end": q_txn[-1] if len(q_txn) else None}
        if self.dry_run:
            self.log.write("dry_run", command="follow_trajectory", times_s=times_s, q=q_txn, **summary)
            log.info("dry run: trajectory of %d points over %.2f s not sent", len(times_s), summary["duration_s"])
            if len(q_txn):
                self._virtual_q = q_txn[-1].copy()
            return self.state()
        self._require_armed("follow a trajectory", **summary)
        if not len(times_s):
            return self.state()
        plan = StreamPlan(q0, times_s, q_txn, self.accel_limits, self.stream)
        with self._result_cv:
            self._results.clear()
        self.stop_within_s = plan.stop_within_s
        self._goal_counter += 1
        tid = f"torm-{self._goal_counter}-{time.time():.6f}"
        self.log.write("send_trajectory", trajectory=tid, times_s=times_s, q=q_txn, stop_within_s=plan.stop_within_s,
                       brake_s=plan.brake_s, **summary)
        try:
            final_gid = self._stream(plan, tid)
            result = self._wait_result(final_gid, time.monotonic() + self.result_timeout_s + plan.duration_s)
        except BaseException:
            self.stop()  # a fault, a refused chunk, Ctrl-C / SIGTERM in the middle: cancel what runs
            raise
        t_result = time.monotonic()
        self._active_goal = None
        status = int((result.get("status") or {}).get("status", -1))
        res = result.get("result") or {}
        self.log.write("goal_result", goal_id=final_gid, status=status, error_code=res.get("error_code"),
                       error_string=res.get("error_string", ""))
        if status != SUCCEEDED or int(res.get("error_code", 0)) != 0:
            raise HardwareError(f"trajectory {tid} ended {STATUS_NAMES.get(status, status)} (error_code "
                                f"{res.get('error_code')}: {res.get('error_string', '')!r}; "
                                f"{(result.get('status') or {}).get('text', '')})")
        self._wait_fresh_joint_states(t_result)
        return self.state()

    def _stream(self, plan: StreamPlan, tid: str) -> str:
        """Send the plan's chunks every ``period_s`` until the last one; returns the last chunk's goal id."""
        s = self.stream
        w0 = time.monotonic()
        last_send, k, replaced = w0, 0, set()  # replaced: chunks whose PREEMPTED result is still due
        while True:
            now = time.monotonic()
            if k and now - last_send > s.horizon_s - s.lead_s:
                raise HardwareError(
                    f"trajectory {tid}: chunk {k} is {now - last_send:.3f} s after the previous one, beyond its "
                    f"{s.horizon_s} s horizon; the arm braked to a stop on its own and the motion was abandoned "
                    "(is the machine overloaded? raise stream.horizon_s)")
            rel, qs, final = plan.chunk(now - w0)
            gid = f"{tid}.{k}"
            self._active_goal = gid
            try:
                self.client.publish(f"{self.action_ns}/goal", self.goal_message(rel, qs, gid))
            except HardwareError as exc:
                self._trip(f"streaming chunk {k} of trajectory {tid} failed ({exc})")
                raise HardwareError(f"trajectory {tid}: the link failed while streaming ({exc}); the arm was stopped: "
                                    f"it comes to rest on its own within {plan.stop_within_s:.2f} s of the last "
                                    "chunk it received") from exc
            self.log.write("send_goal", topic=f"{self.action_ns}/goal", goal_id=gid, chunk=k, final=final,
                           t_plan=now - w0, n_points=len(rel), until_s=float(rel[-1]))
            if k:
                replaced.add(f"{tid}.{k - 1}")
            last_send, k = now, k + 1
            if final:
                return gid
            self._watch_chunks(replaced, last_send + s.period_s, tid)

    def _watch_chunks(self, replaced: set[str], until: float, tid: str) -> None:
        """Wait until monotonic ``until``; HardwareError on a fault or a result other than PREEMPTED for a
        replaced chunk (a replaced chunk that SUCCEEDED means the arm ran into its braking tail)."""
        with self._result_cv:
            while True:
                self._check_ok("follow_trajectory")
                for gid in [g for g in replaced if g in self._results]:
                    replaced.discard(gid)
                    msg = self._results.pop(gid)
                    status = int((msg.get("status") or {}).get("status", -1))
                    if status != PREEMPTED:
                        text = (msg.get("status") or {}).get("text", "")
                        raise HardwareError(f"trajectory {tid}: chunk {gid} ended {STATUS_NAMES.get(status, status)} "
                                            f"while the next one was streamed ({text!r}); the motion was stopped")
                left = until - time.monotonic()
                if left <= 0:
                    return
                self._result_cv.wait(min(left, 0.05))

    def _wait_result(self, gid: str, deadline: float) -> dict[str, Any]:
        with self._result_cv:
            while gid not in self._results:
                self._check_ok("follow_trajectory")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise HardwareError(f"no result for trajectory goal {gid} by its end + {self.result_timeout_s} s; "
                                        "the goal was cancelled. Is the trajectory controller active "
                                        "(switch_controller('trajectory'))?")
                self._result_cv.wait(min(left, 0.05))
            msg = self._results.pop(gid)
            self._results.clear()  # the replaced chunks' PREEMPTED results
            return msg

    def _wait_fresh_joint_states(self, since: float) -> None:
        """Block until a /joint_states message newer than ``since`` (monotonic s) arrived (at most ``watchdog_s``)."""
        deadline = time.monotonic() + self.watchdog_s
        while time.monotonic() < deadline and self.fault is None:
            with self._js_lock:
                if self._last_js > since:
                    return
            time.sleep(0.002)

    def _send_cancel(self) -> None:
        stamp = {"secs": 0, "nsecs": 0}
        ids = [self._active_goal] if self._active_goal else []
        for gid in [*ids, ""]:  # the active goal, then "" = cancel every goal of this action server
            self.log.write("cancel", topic=f"{self.action_ns}/cancel", goal_id=gid)
            self.client.publish(f"{self.action_ns}/cancel", {"stamp": stamp, "id": gid})
        self._active_goal = None

    def stop(self) -> None:
        """Cancel the active goal (and all goals of the trajectory action); allowed when faulted or unarmed."""
        if self.dry_run:
            self.log.write("dry_run", command="stop")
            return
        if self.client.connected:
            self._send_cancel()

    def shutdown(self, disable: bool = True, timeout_s: float = 2.0) -> None:
        """The stop path: cancel every goal, then /robot/disable (when ``disable``, armed and not a dry run).

        Allowed when faulted; errors are logged, not raised (it runs in ``close`` and on SIGTERM).
        """
        try:
            self.stop()
            if disable and self.armed and not self.dry_run and self.client.connected:
                self.log.write("call_service", service=self.disable_service, args={}, reason="shutdown")
                self.client.call_service(self.disable_service, {}, timeout_s=timeout_s)
        except HardwareError as exc:
            log.error("stopping the arm on shutdown failed: %s", exc)

    def close(self) -> None:
        """Stop the watchdog and close the websocket (no motion command is sent; see :meth:`shutdown`)."""
        self._stop_watchdog.set()
        self.log.write("close")
        self.client.close()
