"""A SIGKILLed trial under the Ray engine does not leave the real arm enabled: the driver side (the Ray worker
that ran the trial, or the Ray driver when that worker dies too) cancels every goal and disables the arm within
the stated bound. The arm is the fake rosbridge server's modelled controller, the gripper a fake Modbus gripper;
the bench, Ray, the worker and the real backend are the real code."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest

from sim.robots.config import load_robot_config
from torm.bench import BenchConfig, run_benchmark
from torm.bench.ray_engine import check_address
from torm.bench.results import read_results
from torm.errors import BenchmarkError
from torm.hardware.remote_stop import STOP_TIMEOUT_S
from torm.testing.fake_robotiq import FakeRobotiq, FakeRobotiqServer
from torm.testing.fake_rosbridge import ACTION, FakeRosbridge, write_cell_yaml


def _trial_pids(marker: str) -> list[int]:
    """Pids of running ``python -m torm.bench.worker`` processes whose job names ``marker`` (this test's trial,
    not another benchmark's on the same machine)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes().decode().split("\0")
                if "torm.bench.worker" in cmd and marker in Path(cmd[cmd.index("torm.bench.worker") + 1]).read_text():
                    pids.append(int(d.name))
            except (OSError, ValueError, IndexError):
                continue
    return pids


def _stop_kinds(ros: FakeRosbridge, since: float) -> list[tuple[str, float]]:
    out = []
    with ros._lock:
        pairs = [(m, t) for m, t in zip(ros.received, ros.received_at, strict=True) if t >= since]
    for m, t in pairs:
        if m.get("topic") == f"{ACTION}/cancel":
            out.append(("cancel", t))
        elif m.get("op") == "call_service" and m.get("service") == "/robot/disable":
            out.append(("disable", t))
    return out


def _parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


@pytest.mark.parametrize("kill", ["trial", "ray_worker_and_trial"])
def test_sigkilled_ray_trial_is_cancelled_and_disabled_from_the_driver(local_ray, tmp_path, kill):
    rcfg = load_robot_config("inovo_2f85")
    ros = FakeRosbridge(rcfg.arm.home_q, tuple(rcfg.arm.joints))
    modbus = FakeRobotiqServer(FakeRobotiq())
    hw = write_cell_yaml(tmp_path / "hw.yaml", ros.port, modbus.url, horizon_s=1.0)
    config = BenchConfig(suite="rw", scenarios=("rw1",), trials=1, engine="ray", workers=1, timeout_s=300.0,
                         trial_fn="bench_fake_trials:real_arm",
                         overrides=("backend=real", f"hardware_config={hw}", "arm_robot=true", "fake.move_s=60"))
    box: dict = {}
    bench = threading.Thread(target=lambda: box.update(run_benchmark(config, tmp_path / "run", progress=False)))
    bench.start()
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(ros.goals()) < 3 and bench.is_alive():
            time.sleep(0.05)
        assert len(ros.goals()) >= 3, box  # the arm is moving
        pids = _trial_pids(str(hw))
        assert len(pids) == 1
        victims = [pids[0]] if kill == "trial" else [_parent(pids[0]), pids[0]]
        t_kill = time.monotonic()
        for pid in victims:  # no stop path can run in the trial process (nor in the Ray worker that ran it)
            os.kill(pid, signal.SIGKILL)
        bench.join(timeout=60)
        assert not bench.is_alive()
        kinds = _stop_kinds(ros, t_kill)
        names = [k for k, _ in kinds]
        assert "cancel" in names and "disable" in names, kinds
        assert names.index("cancel") < names.index("disable")
        t_disable = next(t for k, t in kinds if k == "disable")
        assert t_disable - t_kill <= STOP_TIMEOUT_S + 2.0  # the stated bound (+ the poll of the dead process)
        assert not [m for m in ros.msgs("publish", since=t_disable, topic=f"{ACTION}/goal")]  # no motion after
        row = read_results(tmp_path / "run" / "results.jsonl").rows[0]
        assert row["failure"] == "crashed"
        assert ("SIGKILL" if kill == "trial" else "ray task failed") in row["message"]
        stop = row["run"]["driver_stop"]
        assert stop["cancel"] and stop["disable"] and stop["error"] is None
    finally:
        bench.join(timeout=30)
        ros.close()
        modbus.close()


def test_dead_ray_address_is_refused_quickly():
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t = time.monotonic()
    with pytest.raises(BenchmarkError, match="cannot reach the Ray cluster"):
        check_address(f"127.0.0.1:{port}", timeout_s=2.0)
    assert time.monotonic() - t < 5.0
