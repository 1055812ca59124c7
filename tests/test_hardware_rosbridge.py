"""The real-arm adapter against a fake rosbridge server on loopback speaking the JSON rosbridge v2 protocol.

The fake answers ``call_service`` for /robot/enable, /robot/disable and /robot/switch_controller,
publishes /joint_states at 100 Hz to subscribers, accepts FollowJointTrajectory goals on the actionlib
``.../goal`` topic, "moves" to the last point after ``time_scale`` x the trajectory duration and
publishes the result. Tests check the exact messages the adapter sends.
"""

from __future__ import annotations

import contextlib
import json
import socket
import threading
import time

import numpy as np
import pytest
from websockets.sync.server import serve

from sim.robot_config import load_robot_config
from torm.backend.safety import SafetyError
from torm.errors import HardwareError
from torm.hardware.command_log import CommandLog
from torm.hardware.config import GripperSettings, HardwareConfig, RealCaptureSettings
from torm.hardware.rosbridge import InovoArm, MujocoKinematics, ros_duration
from torm.types import CameraView

ACTION = "/robot/joint_trajectory_controller/follow_joint_trajectory"
RCFG = load_robot_config("inovo_2f85")
JOINTS = tuple(RCFG.arm.joints)


class FakeRosbridge:
    """A rosbridge_server stand-in (127.0.0.1, ephemeral port) recording every message it receives."""

    def __init__(self, q0: np.ndarray, time_scale: float = 0.05, hold_result: bool = False) -> None:
        self.q = np.asarray(q0, float).copy()
        self.time_scale = time_scale
        self.hold_result = hold_result
        self.received: list[dict] = []
        self.publishing = True
        self._conns: list = []
        self._lock = threading.Lock()
        self._server = serve(self._handler, "127.0.0.1", 0)
        self.port = self._server.socket.getsockname()[1]
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)
        self._thread.start()

    def msgs(self, op: str | None = None, **match) -> list[dict]:
        with self._lock:
            out = list(self.received)
        return [m for m in out if (op is None or m.get("op") == op) and all(m.get(k) == v for k, v in match.items())]

    def _send(self, ws, msg: dict) -> None:
        try:
            with self._lock:
                ws.send(json.dumps(msg))
        except Exception:
            pass

    def _handler(self, ws) -> None:
        subs: set[str] = set()
        self._conns.append(ws)
        stop = threading.Event()

        def publisher() -> None:
            while not stop.wait(0.01):
                if self.publishing and "/joint_states" in subs:
                    self._send(ws, {"op": "publish", "topic": "/joint_states", "msg": {
                        "header": {"stamp": {"secs": 0, "nsecs": 0}, "frame_id": ""},
                        "name": list(JOINTS), "position": self.q.tolist(), "velocity": [0.0] * len(JOINTS),
                        "effort": []}})

        threading.Thread(target=publisher, daemon=True).start()
        try:
            for raw in ws:
                msg = json.loads(raw)
                with self._lock:
                    self.received.append(msg)
                op = msg.get("op")
                if op == "subscribe":
                    subs.add(msg["topic"])
                elif op == "call_service":
                    self._send(ws, {"op": "service_response", "id": msg.get("id"), "service": msg["service"],
                                    "values": {"success": True, "message": ""}, "result": True})
                elif op == "publish" and msg["topic"] == f"{ACTION}/goal":
                    threading.Thread(target=self._execute, args=(ws, msg["msg"], subs), daemon=True).start()
        except Exception:
            pass
        finally:
            stop.set()

    def _execute(self, ws, goal: dict, subs: set[str]) -> None:
        pts = goal["goal"]["trajectory"]["points"]
        tfs = pts[-1]["time_from_start"]
        time.sleep((tfs["secs"] + tfs["nsecs"] * 1e-9) * self.time_scale)
        if self.hold_result:
            return
        self.q = np.array(pts[-1]["positions"], float)
        if f"{ACTION}/result" in subs:
            self._send(ws, {"op": "publish", "topic": f"{ACTION}/result", "msg": {
                "header": {"stamp": {"secs": 0, "nsecs": 0}},
                "status": {"goal_id": goal["goal_id"], "status": 3, "text": ""},
                "result": {"error_code": 0, "error_string": ""}}})

    def drop_connections(self) -> None:
        for ws in list(self._conns):
            with contextlib.suppress(Exception):
                ws.close()

    def close(self) -> None:
        self.drop_connections()
        self._server.shutdown()


@pytest.fixture()
def server():
    s = FakeRosbridge(RCFG.arm.home_q)
    yield s
    s.close()


def make_arm(port: int, armed: bool = True, dry_run: bool = False, watchdog_s: float = 0.5,
             log: CommandLog | None = None) -> InovoArm:
    kin = MujocoKinematics(RCFG.mjcf, JOINTS, RCFG.arm.tcp_site, RCFG.arm.flange_site)
    return InovoArm("127.0.0.1", port, JOINTS, kin, armed=armed, dry_run=dry_run, watchdog_s=watchdog_s,
                    connect_timeout_s=2.0, result_timeout_s=2.0, command_log=log or CommandLog(None))


def _small_move(q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    times = np.array([0.1, 0.25, 1.5])
    q = np.stack([q0 + d * np.array([0.01, -0.01, 0.02, 0, 0.01, 0.03]) for d in (0.2, 0.6, 1.0)])
    return times, q


def test_ros_duration_splits_seconds():
    assert ros_duration(1.25) == {"secs": 1, "nsecs": 250_000_000}
    assert ros_duration(0.9999999999) == {"secs": 1, "nsecs": 0}


def test_enable_switch_and_trajectory_goal_messages(server, tmp_path):
    log = CommandLog(tmp_path / "cmd.jsonl")
    arm = make_arm(server.port, log=log)
    try:
        np.testing.assert_allclose(arm.state().q, RCFG.arm.home_q)
        arm.enable()
        arm.switch_controller("trajectory")
        times, q = _small_move(arm.state().q)
        st = arm.follow_trajectory(times, q)
    finally:
        arm.close()
    calls = [(m["service"], m["args"]) for m in server.msgs("call_service")]
    assert calls == [("/robot/enable", {}), ("/robot/switch_controller", {"data": "trajectory"})]
    subs = {m["topic"]: m["type"] for m in server.msgs("subscribe")}
    assert subs["/joint_states"] == "sensor_msgs/JointState"
    assert subs["/default_move_group/tcp_pose"] == "geometry_msgs/PoseStamped"
    adv = {m["topic"]: m["type"] for m in server.msgs("advertise")}
    assert adv[f"{ACTION}/goal"] == "control_msgs/FollowJointTrajectoryActionGoal"
    goals = server.msgs("publish", topic=f"{ACTION}/goal")
    assert len(goals) == 1
    traj = goals[0]["msg"]["goal"]["trajectory"]
    assert traj["joint_names"] == list(JOINTS)
    assert [p["time_from_start"] for p in traj["points"]] == [
        {"secs": 0, "nsecs": 100_000_000}, {"secs": 0, "nsecs": 250_000_000}, {"secs": 1, "nsecs": 500_000_000}]
    np.testing.assert_allclose([p["positions"] for p in traj["points"]], q)
    assert goals[0]["msg"]["goal_id"]["id"]
    np.testing.assert_allclose(st.q, q[-1])  # the fake moved to the last point and reported it
    np.testing.assert_allclose(st.T_world_tcp, arm.forward_kinematics(q[-1]))
    lines = [json.loads(s) for s in (tmp_path / "cmd.jsonl").read_text().splitlines()]
    kinds = [r["kind"] for r in lines]
    assert kinds.count("call_service") == 2 and "send_goal" in kinds and "goal_result" in kinds
    assert all("t" in r and "iso" in r for r in lines)


def test_not_armed_refuses_and_sends_no_goal(server):
    log = CommandLog(None)
    arm = make_arm(server.port, armed=False, log=log)
    try:
        times, q = _small_move(arm.state().q)
        with pytest.raises(HardwareError, match="not armed"):
            arm.follow_trajectory(times, q)
        with pytest.raises(HardwareError, match="not armed"):
            arm.enable()
        with pytest.raises(HardwareError, match="not armed"):
            arm.switch_controller("zerog")
        time.sleep(0.1)
    finally:
        arm.close()
    assert server.msgs("publish", topic=f"{ACTION}/goal") == []
    assert server.msgs("call_service") == []
    assert [r["kind"] for r in log.records].count("refused") == 3


def test_dry_run_sends_nothing_and_tracks_the_plan(server):
    log = CommandLog(None)
    arm = make_arm(server.port, armed=True, dry_run=True, log=log)
    try:
        arm.enable()
        arm.switch_controller("trajectory")
        times, q = _small_move(arm.state().q)
        st = arm.follow_trajectory(times, q)
        arm.stop()
        time.sleep(0.1)
    finally:
        arm.close()
    assert server.msgs("publish") == [] and server.msgs("call_service") == [] and server.msgs("advertise") == []
    np.testing.assert_allclose(st.q, q[-1])
    dry = [r for r in log.records if r["kind"] == "dry_run" and r["command"] == "follow_trajectory"]
    assert len(dry) == 1 and dry[0]["n_points"] == 3


def test_unreachable_host_names_host_and_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(HardwareError, match=f"127.0.0.1:{port}.*rosbridge_server"):
        make_arm(port)


def test_disconnect_stops_the_arm_and_refuses_commands():
    srv = FakeRosbridge(RCFG.arm.home_q, time_scale=1.0, hold_result=True)
    arm = make_arm(srv.port, watchdog_s=5.0)
    try:
        times, q = _small_move(arm.state().q)
        threading.Timer(0.3, srv.drop_connections).start()
        t0 = time.monotonic()
        with pytest.raises(HardwareError, match="stopped.*dropped"):
            arm.follow_trajectory(times, q)
        assert time.monotonic() - t0 < 1.4  # aborted well before the 1.5 s trajectory + 2 s result slack
        with pytest.raises(HardwareError, match="refused"):
            arm.follow_trajectory(times, q)
        with pytest.raises(HardwareError, match="refused"):
            arm.enable()
    finally:
        arm.close()
        srv.close()


def test_watchdog_cancels_and_disables_when_joint_states_stop(server):
    arm = make_arm(server.port, watchdog_s=0.15)
    try:
        server.publishing = False
        deadline = time.monotonic() + 2.0
        while arm.fault is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert arm.fault is not None and "joint_states" in arm.fault
        time.sleep(0.1)
        cancels = server.msgs("publish", topic=f"{ACTION}/cancel")
        assert cancels and cancels[-1]["msg"]["id"] == ""
        assert [m["service"] for m in server.msgs("call_service")] == ["/robot/disable"]
        times, q = _small_move(arm.state().q)
        with pytest.raises(HardwareError, match="refused"):
            arm.follow_trajectory(times, q)
    finally:
        arm.close()


class _NullGripper:
    max_width = 0.085

    def activate(self) -> None: ...


class _FakeCamera:
    """A camera whose frame pose follows the arm's flange FK, like the D455 on the wrist."""

    def __init__(self, arm: InovoArm, T_flange_cam: np.ndarray) -> None:
        self.arm, self.T_flange_cam = arm, T_flange_cam
        self.K = np.array([[320.0, 0, 160], [0, 320.0, 90], [0, 0, 1]])

    def read(self) -> CameraView:
        q = self.arm.state().q
        return CameraView(K=self.K, T_world_cam=self.arm.flange_pose(q) @ self.T_flange_cam,
                          rgb=np.zeros((180, 320, 3), np.uint8))


def _backend(server, **hw):
    from torm.hardware.backend import RealBackend

    cfg = HardwareConfig(host="127.0.0.1", port=server.port, armed=True, command_log=None,
                         gripper=GripperSettings(activate=False), **hw)
    arm = make_arm(server.port)
    return RealBackend(RCFG, cfg, arm=arm, gripper=_NullGripper()), arm


def test_safety_layer_rejects_out_of_box_target_before_sending(server):
    backend, arm = _backend(server)
    try:
        assert backend.name == "real" and backend.ground_truth is None
        q0 = backend.arm.state().q
        q_bad = q0.copy()
        q_bad[1] -= 0.9  # shoulder forward: the TCP dives below the table top (z < 0)
        assert arm.forward_kinematics(q_bad)[2, 3] < 0
        times = np.linspace(0.2, 4.0, 20)
        traj = q0 + (q_bad - q0) * (times / times[-1])[:, None]
        with pytest.raises(SafetyError, match="workspace box"):
            backend.arm.follow_trajectory(times, traj)
        time.sleep(0.1)
        assert server.msgs("publish", topic=f"{ACTION}/goal") == []
        # on start (armed) the backend enabled the robot and selected the trajectory controller
        assert [m["service"] for m in server.msgs("call_service")] == ["/robot/enable", "/robot/switch_controller"]
    finally:
        backend.close()
        arm.close()


def test_capture_moves_the_wrist_camera_over_the_hemisphere(server):
    server.time_scale = 0.01
    T_flange_cam = np.eye(4)
    T_flange_cam[:3, 3] = [0.0, 0.06, 0.03]
    backend, arm = _backend(server, capture=RealCaptureSettings(radius=0.5, return_home=False, settle_s=0.0))
    backend._camera = _FakeCamera(arm, T_flange_cam)
    try:
        cap = backend.capture(3)
    finally:
        backend.close()
        arm.close()
    goals = server.msgs("publish", topic=f"{ACTION}/goal")
    assert len(cap) == 2 and cap.metadata["view_indices"] == [1, 2] and len(goals) == len(cap)  # view 0: out of reach
    assert cap.table_height == 0.0 and cap.scenario == "real" and cap.workspace_bounds.shape == (2, 3)
    from sim.camera_rig import hemisphere_poses

    wanted = hemisphere_poses(3, 0.5, (0.55, 0.0, 0.0), 20.0, 80.0)
    for v, i in zip(cap.views, cap.metadata["view_indices"], strict=True):
        # each frame was taken at the requested camera pose (IK tolerance 1 mm / 0.01 rad)
        assert np.linalg.norm(v.T_world_cam[:3, 3] - wanted[i][:3, 3]) < 3e-3
        assert np.degrees(np.arccos(np.clip((np.trace(v.T_world_cam[:3, :3].T @ wanted[i][:3, :3]) - 1) / 2,
                                            -1, 1))) < 1.5


def test_dry_run_backend_moves_nothing(server):
    from torm.hardware.backend import DryRunGripper, RealBackend

    cfg = HardwareConfig(host="127.0.0.1", port=server.port, armed=True, dry_run=True, command_log=None)
    log = CommandLog(None)
    arm = make_arm(server.port, dry_run=True, log=log)
    backend = RealBackend(RCFG, cfg, arm=arm, command_log=log)
    try:
        assert isinstance(backend.gripper, DryRunGripper)  # no serial port opened in a dry run
        times, q = _small_move(backend.arm.state().q)
        backend.arm.follow_trajectory(times, q)
        assert backend.gripper.move(0.03).width == pytest.approx(0.03)
        time.sleep(0.1)
    finally:
        backend.close()
        arm.close()
    assert server.msgs("publish") == [] and server.msgs("call_service") == []
    kinds = [r.get("command") for r in log.records if r["kind"] == "dry_run"]
    assert "gripper_move" in kinds and "follow_trajectory" in kinds
