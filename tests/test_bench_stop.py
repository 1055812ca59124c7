"""SIGTERM to ``torm bench --backend real`` stops the arm: the worker runs its stop path (cancel + disable)
before the grace period ends. The arm is the fake rosbridge server's modelled controller, the gripper a
fake Modbus gripper on a loopback socket; the bench, its worker and the real backend are the real code."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sim.robots.config import load_robot_config
from torm.bench.results import read_manifest, read_results
from torm.testing.fake_robotiq import FakeRobotiq, FakeRobotiqServer
from torm.testing.fake_rosbridge import ACTION, FakeRosbridge, write_cell_yaml

TESTS_DIR = str(Path(__file__).resolve().parent)


def _timeline(ros: FakeRosbridge, since: float) -> str:
    """What reached the fake rosbridge after ``since``: one line per message (s after it, op, topic or service)."""
    with ros._lock:
        pairs = [(t, m) for m, t in zip(ros.received, ros.received_at, strict=True) if t >= since]
    return "\n".join(f"{t - since:8.3f} {m.get('op')} {m.get('topic') or m.get('service') or ''}" for t, m in pairs)


@pytest.mark.parametrize("engine", ["pool", "ray"])
def test_sigterm_to_a_real_bench_cancels_and_disables_the_arm(tmp_path, engine):
    rcfg = load_robot_config("inovo_2f85")
    ros = FakeRosbridge(rcfg.arm.home_q, tuple(rcfg.arm.joints))
    gripper = FakeRobotiq()
    modbus = FakeRobotiqServer(gripper)
    hw = write_cell_yaml(tmp_path / "hw.yaml", ros.port, modbus.url, horizon_s=1.0)
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "torm.cli", "bench", "--suite", "rw", "--scenario", "rw1", "--trials", "1",
           "--method", "torm", "--out", str(out), "--trial-fn", "bench_fake_trials:real_arm", "--backend", "real",
           "--hardware-config", str(hw), "--arm-robot", "--set", "fake.move_s=60", "--no-progress",
           "--stop-grace", "20", "--engine", engine]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (TESTS_DIR, os.environ.get("PYTHONPATH")) if p)}
    bench = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and len(ros.goals()) < 3 and bench.poll() is None:
            time.sleep(0.05)
        assert len(ros.goals()) >= 3, bench.communicate(timeout=30)[1][-3000:]  # the arm is moving
        assert gripper.writes[:2] == [[0, 0, 0], [0x0100, 0, 0]]  # armed: the gripper was activated
        t_term = time.monotonic()
        bench.send_signal(signal.SIGTERM)
        _, err = bench.communicate(timeout=180)  # Ray: grace + the backstop stop + ray.shutdown, on a loaded machine
        assert bench.returncode == 130, err[-3000:]  # "torm: interrupted"
        # the worker's stop path reached the controller: cancel every goal, then disable the arm
        # (with Ray the driver also stops the arm over its own connection: its "advertise" is not a command)
        after = [m for m in ros.msgs(since=t_term) if m["op"] != "advertise"]
        kinds = [("cancel" if m.get("topic") == f"{ACTION}/cancel" else m.get("service"))
                 for m in after if m["op"] == "call_service" or m.get("topic") == f"{ACTION}/cancel"]
        assert "cancel" in kinds and "/robot/disable" in kinds
        assert kinds.index("cancel") < kinds.index("/robot/disable")
        assert [m["msg"]["id"] for m in after if m.get("topic") == f"{ACTION}/cancel"][-1] == ""
        # no motion was commanded after the cancel, and the modelled arm stands still. Pool: after the first cancel
        # (the worker's stop path). Ray: after the last cancel (a cancelled task can take a while to reach the trial on
        # a loaded machine; the driver's backstop cancel and disable come after every trial process is gone).
        cancels = [i for i, m in enumerate(after) if m.get("topic") == f"{ACTION}/cancel"]
        i_cancel = cancels[0] if engine == "pool" else cancels[-1]
        late_goals = [m for m in after[i_cancel:] if m.get("topic") == f"{ACTION}/goal" and m["op"] == "publish"]
        assert not late_goals, _timeline(ros, t_term) + "\n" + err[-3000:]
        assert any(m.get("service") == "/robot/disable" for m in after[i_cancel:])  # disabled after that cancel
        assert ros.controller.end_time() <= time.monotonic()
        # the interrupted trial left no row (it runs again on resume) and the session says why it ended
        assert read_results(out / "results.jsonl").rows == []
        assert [s["status"] for s in read_manifest(out)["sessions"]] == ["interrupted"]
    finally:
        if bench.poll() is None:
            bench.kill()
        ros.close()
        modbus.close()
