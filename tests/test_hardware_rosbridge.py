"""The real-arm adapter against a fake rosbridge server on loopback (torm/testing/fake_rosbridge.py) whose
controller model executes the streamed FollowJointTrajectory chunks in wall time.

Tests check the exact messages the adapter sends and what the modelled arm does with them, including
when the link goes silent in the middle of a motion.
"""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest

from sim.robots.config import load_robot_config
from torm.backend.safety import SafetyError
from torm.errors import HardwareError
from torm.hardware.command_log import CommandLog
from torm.hardware.config import GripperSettings, HardwareConfig, RealCaptureSettings
from torm.hardware.rosbridge import InovoArm, MujocoKinematics, ros_duration
from torm.hardware.streaming import StreamSettings, interp_path
from torm.testing.fake_rosbridge import ACTION, FakeRosbridge
from torm.types import CameraView

RCFG = load_robot_config("inovo_2f85")
JOINTS = tuple(RCFG.arm.joints)


@pytest.fixture()
def server():
    s = FakeRosbridge(RCFG.arm.home_q, JOINTS)
    yield s
    s.close()


#: A longer horizon than the default 0.3 s: a loaded CI machine must not make the stream fall behind.
TEST_STREAM = StreamSettings(horizon_s=0.6)


def make_arm(port: int, armed: bool = True, dry_run: bool = False, watchdog_s: float = 10.0,
             log: CommandLog | None = None, speed_scale: float = 0.25,
             stream: StreamSettings = TEST_STREAM) -> InovoArm:
    """The adapter against the fake server. The watchdog is generous (10 s) except in the test about it: the
    fake's joint-state thread can starve for over a second on a loaded 2-core machine."""
    kin = MujocoKinematics(RCFG.mjcf, JOINTS, RCFG.arm.tcp_site, RCFG.arm.flange_site)
    return InovoArm("127.0.0.1", port, JOINTS, kin, armed=armed, dry_run=dry_run, watchdog_s=watchdog_s,
                    connect_timeout_s=5.0, result_timeout_s=2.0, command_log=log or CommandLog(None),
                    accel_limits=speed_scale * np.asarray(RCFG.arm.acceleration_limits), stream=stream)


def _small_move(q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    times = np.array([0.1, 0.25, 1.5])
    q = np.stack([q0 + d * np.array([0.01, -0.01, 0.02, 0, 0.01, 0.03]) for d in (0.2, 0.6, 1.0)])
    return times, q


def test_ros_duration_splits_seconds():
    assert ros_duration(1.25) == {"secs": 1, "nsecs": 250_000_000}
    assert ros_duration(0.9999999999) == {"secs": 1, "nsecs": 0}


def _points(goal: dict) -> tuple[np.ndarray, np.ndarray]:
    pts = goal["goal"]["trajectory"]["points"]
    t = np.array([p["time_from_start"]["secs"] + p["time_from_start"]["nsecs"] * 1e-9 for p in pts])
    return t, np.array([p["positions"] for p in pts])


def test_enable_switch_and_streamed_goal_messages(server, tmp_path):
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
    goals = server.goals()
    # a 1.5 s motion streamed every 0.1 s: about 15 chunks, each replacing the previous one
    assert 8 <= len(goals) <= 16 and len({g["goal_id"]["id"] for g in goals}) == len(goals)
    knots_t, knots_q = np.r_[0.0, times], np.vstack([RCFG.arm.home_q, q])
    for g in goals:
        traj = g["goal"]
        assert traj["trajectory"]["joint_names"] == list(JOINTS)
        assert [t["name"] for t in traj["path_tolerance"]] == list(JOINTS)
        assert all(t["position"] == 0.1 for t in traj["path_tolerance"])
        assert all(t["position"] == 0.01 for t in traj["goal_tolerance"])
        assert traj["goal_time_tolerance"] == {"secs": 0, "nsecs": 500_000_000}
        t, pts = _points(g)
        assert t[0] > 0 and np.all(np.diff(t) > 0)
        # every point lies on the path the safety layer checked (the piecewise-linear joint path)
        dense = interp_path(knots_t, knots_q, np.linspace(0, times[-1], 20001))
        assert max(np.min(np.max(np.abs(dense - p), axis=1)) for p in pts) < 2e-4
    # every chunk but the last ends at rest: its final step is slow enough to stop within the acceleration limit
    a_lim = 0.25 * np.asarray(RCFG.arm.acceleration_limits)
    for g in goals[:-1]:
        t, pts = _points(g)
        v_last = np.abs(pts[-1] - pts[-2]) / (t[-1] - t[-2])
        assert np.all(v_last <= a_lim * (t[-1] - t[-2]) + 1e-9) and t[-1] <= arm.stop_within_s + 1e-6
    t_last, q_last = _points(goals[-1])
    np.testing.assert_allclose(q_last[-1], q[-1])
    np.testing.assert_allclose(st.q, q[-1], atol=1e-9)  # the modelled arm reached the end and reported it
    np.testing.assert_allclose(st.T_world_tcp, arm.forward_kinematics(q[-1]))
    lines = [json.loads(s) for s in (tmp_path / "cmd.jsonl").read_text().splitlines()]
    kinds = [r["kind"] for r in lines]
    assert kinds.count("call_service") == 2 and kinds.count("send_goal") == len(goals) and "goal_result" in kinds
    assert [r for r in lines if r["kind"] == "send_trajectory"][0]["stop_within_s"] == arm.stop_within_s
    assert all("t" in r and "iso" in r for r in lines)


def _long_move(q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 3 s minimum-jerk move of the shoulder and elbow (within the speed limits at speed_scale 0.25)."""
    from torm.execution.trajectory import min_jerk_segment

    return min_jerk_segment(q0, q0 + np.array([0.3, -0.25, 0.3, 0.0, 0.2, 0.0]), 3.0, 0.02)


@pytest.mark.parametrize("how", ["silent", "dropped"])
def test_arm_stops_by_itself_when_the_link_dies_mid_trajectory(how):
    """The link goes silent (or the socket drops) 1 s into a 3 s motion: no stop command can arrive, yet the
    modelled controller brings the arm to rest within the arm's stated bound, short of the goal."""
    srv = FakeRosbridge(RCFG.arm.home_q, JOINTS)
    arm = make_arm(srv.port, watchdog_s=1.0)  # the watchdog is what notices the silent link
    try:
        q0 = arm.state().q
        times, q = _long_move(q0)
        t0 = time.monotonic()
        cut: dict[str, float] = {}
        done = threading.Event()

        def kill_link() -> None:
            # record the time before cutting: the arm may raise (and the test read it) before this returns
            if how == "silent":
                cut["t"] = srv.freeze()
            else:
                cut["t"] = time.monotonic()
                srv.drop_connections()
            cut["done"] = time.monotonic()  # the link is dead by now (closing sockets takes time on a loaded box)
            done.set()

        threading.Timer(1.0, kill_link).start()
        with pytest.raises(HardwareError, match="stopped"):
            arm.follow_trajectory(times, q)
        assert done.wait(5.0)
        t_cut = cut["t"]
        bound = arm.stop_within_s
        assert bound is not None and bound < 1.5 and bound == pytest.approx(0.6 + 0.25, abs=0.01)  # horizon + braking
        t_rest = srv.controller.end_time()  # no goal arrived after the cut: the last one decides
        # The bound runs from the last goal the controller received: a goal can still arrive while the sockets
        # close (between cut["t"] and cut["done"]; 2 ms on a loaded AVX-512 box). None may arrive after the link
        # is dead, and the arm must rest within the bound of the later of the cut and that goal: a stop that never
        # happens (t_rest at the motion's end, 2 s later) still fails.
        with srv._lock:
            t_goal = max(t for m, t in zip(srv.received, srv.received_at, strict=True)
                         if m.get("op") == "publish" and m.get("topic", "").endswith("/goal"))
        assert t_goal <= cut["done"]
        assert t_rest - max(t_cut, t_goal) <= bound
        assert t_rest < t0 + times[-1] - 0.5  # it did not run on to the end of the motion
        while time.monotonic() < t_rest + 0.15:
            time.sleep(0.02)
        hist = [(t, x) for t, x in srv.history if t >= t_cut - 0.2]
        # displacement over the 0.2 s before the cut, not between two samples (their spacing depends on the
        # scheduler: two samples 1 ms apart moved 5.7e-5 rad in one CI run)
        before = [x for t, x in hist if t <= t_cut]
        moving_at_cut = np.max(np.abs(before[-1] - before[0]))
        assert len(before) >= 2 and moving_at_cut > 1e-3  # the arm was moving when the link died ...
        after = [x for t, x in hist if t > t_rest + 0.02]
        assert after and np.max(np.abs(np.asarray(after) - after[-1])) < 1e-9  # ... and is at rest now
        q_rest = after[-1]
        assert np.max(np.abs(q_rest - q[-1])) > 0.05  # well short of the goal
        # it stopped on the checked path, not somewhere else
        dense = interp_path(np.r_[0.0, times], np.vstack([q0, q]), np.linspace(0, times[-1], 20001))
        assert np.min(np.max(np.abs(dense - q_rest), axis=1)) < 1e-3
        # and it slowed down on the way (no step stop): the last 0.1 s before rest is slower than at the cut
        speeds = [(t, np.max(np.abs(b - a)) / (tb - t)) for (t, a), (tb, b) in zip(hist[:-1], hist[1:], strict=True)]
        v_cut = max(v for t, v in speeds if abs(t - t_cut) < 0.05)
        v_end = max(v for t, v in speeds if t_rest - 0.1 < t < t_rest)
        assert v_end < v_cut
        with pytest.raises(HardwareError, match="refused"):
            arm.follow_trajectory(times, q)
        with pytest.raises(HardwareError, match="refused"):
            arm.enable()
    finally:
        arm.close()
        srv.close()


def test_aborted_chunk_stops_the_motion(server):
    """The controller aborts a chunk (e.g. its path tolerance was violated): the adapter stops streaming."""
    arm = make_arm(server.port)
    try:
        server.abort_at_goal = 4
        times, q = _long_move(arm.state().q)
        t0 = time.monotonic()
        with pytest.raises(HardwareError, match="ABORTED"):
            arm.follow_trajectory(times, q)
        assert time.monotonic() - t0 < 2.0 and 4 <= len(server.goals()) <= 6  # no more chunks after the abort
    finally:
        arm.close()


def test_a_stream_that_falls_behind_brakes_to_a_stop(server, monkeypatch):
    """The process stalls longer than the horizon (here: one wait of 1 s): the arm runs into the braking tail
    of the last chunk and stops on the path; the adapter notices and abandons the motion."""
    arm = make_arm(server.port)
    try:
        q0 = arm.state().q
        times, q = _long_move(q0)
        real_watch, calls = arm._watch_chunks, []

        def stalling(*a):
            calls.append(1)
            if len(calls) == 5:
                time.sleep(1.0)
            return real_watch(*a)

        monkeypatch.setattr(arm, "_watch_chunks", stalling)
        with pytest.raises(HardwareError, match="beyond its 0.6 s horizon"):
            arm.follow_trajectory(times, q)
        t_last = server.msgs("publish", topic=f"{ACTION}/goal")
        assert len(t_last) == 5  # nothing was sent after the stall (the cancel only)
        time.sleep(max(0.0, server.controller.end_time() - time.monotonic()) + 0.05)
        q_rest = server.controller.q_at(time.monotonic())
        dense = interp_path(np.r_[0.0, times], np.vstack([q0, q]), np.linspace(0, times[-1], 20001))
        assert np.min(np.max(np.abs(dense - q_rest), axis=1)) < 1e-3 and np.max(np.abs(q_rest - q[-1])) > 0.05
    finally:
        arm.close()


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

    hw.setdefault("stream", TEST_STREAM)
    cfg = HardwareConfig(host="127.0.0.1", port=server.port, armed=True, command_log=None,
                         gripper=GripperSettings(activate=False), **hw)
    arm = make_arm(server.port, speed_scale=cfg.speed_scale, stream=cfg.stream)
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


# Two arm configurations with the TCP 4.6 and 6.1 cm above the table whose straight joint-space path between
# them dips 4.4 cm below it (found by a random search over the Inovo model, checked below).
DIP_A = np.array([-0.955, -0.78, 2.78, 0.483, 0.87, 1.571])
DIP_B = np.array([-0.118, -0.601, 1.765, -0.058, 1.178, 1.571])


def test_path_dipping_below_the_table_between_waypoints_is_refused(server):
    backend, arm = _backend(server)
    try:
        fk = arm.forward_kinematics
        assert fk(DIP_A)[2, 3] > 0.04 and fk(DIP_B)[2, 3] > 0.04  # both waypoints are above the table
        z = [fk(DIP_A + (DIP_B - DIP_A) * u)[2, 3] for u in np.linspace(0, 1, 101)]
        assert min(z) < -0.04  # ... the path between them is not
        server.controller.cancel(time.monotonic())
        server.controller.q = DIP_A[None].copy()  # the arm stands at A
        time.sleep(0.1)
        with pytest.raises(SafetyError, match="between waypoints"):
            backend.arm.follow_trajectory(np.array([4.0]), DIP_B[None])  # one waypoint: B
        assert server.goals() == []
    finally:
        backend.close()
        arm.close()


def test_backend_close_sends_cancel_then_disable(server):
    backend, arm = _backend(server)
    try:
        t0 = time.monotonic()
        backend.close()
        cancel = server.msgs("publish", since=t0, topic=f"{ACTION}/cancel")
        calls = server.msgs("call_service", since=t0)
        assert cancel and cancel[-1]["msg"]["id"] == ""  # every goal of the action server
        assert [m["service"] for m in calls] == ["/robot/disable"]
        backend.close()  # idempotent: nothing more is sent
        assert len(server.msgs("call_service", since=t0)) == 1
    finally:
        arm.close()


def test_capture_moves_the_wrist_camera_over_the_hemisphere(server):
    T_flange_cam = np.eye(4)
    T_flange_cam[:3, 3] = [0.0, 0.06, 0.03]
    # fast moves keep the test short (0.85 x the limits; gentle braking tails keep the config valid); three
    # moves of ~15 chunks each: a 1.5 s horizon so that a stall of the loaded CI machine (0.6 s seen) does not
    # abandon the motion (what a stall does is the subject of test_a_stream_that_falls_behind_brakes_to_a_stop)
    backend, arm = _backend(server, speed_scale=0.85, stream=StreamSettings(horizon_s=1.5, brake_fraction=0.1),
                            capture=RealCaptureSettings(radius=0.5, return_home=False, settle_s=0.0))
    backend._camera = _FakeCamera(arm, T_flange_cam)
    try:
        cap = backend.capture(3)
    finally:
        backend.close()
        arm.close()
    moves = {g["goal_id"]["id"].rsplit(".", 1)[0] for g in server.goals()}  # chunk ids are <trajectory>.<k>
    assert len(cap) == 2 and cap.metadata["view_indices"] == [1, 2] and len(moves) == len(cap)  # view 0: out of reach
    assert cap.table_height == 0.0 and cap.scenario == "real" and cap.workspace_bounds.shape == (2, 3)
    from sim.cameras.rig import hemisphere_poses

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
