"""How fast the real arm stops by itself when the link dies mid-motion (streamed chunks ending at rest).

The real adapter (:class:`torm.hardware.rosbridge.InovoArm`, default stream settings, the Inovo preset's
limits at speed_scale 0.25) streams a 3 s minimum-jerk move of the shoulder, elbow and wrist to the
fake rosbridge server's model of a ROS joint_trajectory_controller (:mod:`torm.testing.fake_rosbridge`:
goals replace each other, the arm holds a goal's last point). At a cut time the link dies, either
silent (nothing in or out, the socket stays open: a dead network) or dropped (the socket closes: a dead
process); no stop command can reach the controller. Recorded per cut: the time from the cut to
standstill (``end of the last received chunk - cut``), the arm's stated bound (``stop_within_s`` of
that motion) and the worst case of any motion the safety layer accepts
(:func:`torm.hardware.streaming.worst_case_stop_s`), and how far the TCP travelled after the cut.

This measures the adapter's streaming against a model of the controller, not a real Inovo: the
controller's real behaviour on goal replacement and at a goal's end is an assumption (README).

Run: ``python benchmarks/arm_stop.py [--cuts 6]``; about 2 s per cut and mode (30 s here). Writes
``benchmarks/results/arm_stop.json`` and ``.md``; re-running overwrites them (each run is complete).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from _common import RESULTS, context  # noqa: E402

from sim.robots.config import load_robot_config  # noqa: E402
from torm.errors import HardwareError  # noqa: E402
from torm.execution.trajectory import min_jerk_segment  # noqa: E402
from torm.hardware.rosbridge import InovoArm, MujocoKinematics  # noqa: E402
from torm.hardware.streaming import StreamSettings, worst_case_stop_s  # noqa: E402
from torm.testing.fake_rosbridge import FakeRosbridge  # noqa: E402

SPEED_SCALE = 0.25
MOVE_S = 3.0
DELTA_Q = np.array([0.3, -0.25, 0.3, 0.0, 0.2, 0.0])  # rad; within speed_scale x the limits over MOVE_S


def one_cut(rcfg, kin, cut_s: float, mode: str) -> dict:
    joints = tuple(rcfg.arm.joints)
    srv = FakeRosbridge(rcfg.arm.home_q, joints)
    arm = InovoArm("127.0.0.1", srv.port, joints, kin, armed=True, watchdog_s=1.0, connect_timeout_s=5.0,
                   accel_limits=SPEED_SCALE * np.asarray(rcfg.arm.acceleration_limits))
    try:
        q0 = arm.state().q
        times, q = min_jerk_segment(q0, q0 + DELTA_Q, MOVE_S, 0.02)
        cut: dict = {}

        def kill() -> None:
            if mode == "silent":
                cut["t"] = srv.freeze()
            else:
                cut["t"] = time.monotonic()
                srv.drop_connections()

        t0 = time.monotonic()
        threading.Timer(cut_s, kill).start()
        try:
            arm.follow_trajectory(times, q)
            raised = None
        except HardwareError as exc:
            raised = str(exc)[:200]
        if "t" not in cut:  # the motion failed before the cut (e.g. a stalled machine): recorded, not measured
            time.sleep(max(0.0, cut_s - (time.monotonic() - t0)) + 0.05)
            return {"mode": mode, "cut_s": cut_s, "error": raised, "within_bound": None}
        t_rest = srv.controller.end_time()
        q_cut, q_rest = srv.controller.q_at(cut["t"]), srv.controller.q_at(t_rest)
        tcp_after_m = float(np.linalg.norm(kin.tcp(q_rest)[:3, 3] - kin.tcp(q_cut)[:3, 3]))
        return {"mode": mode, "cut_s": round(cut["t"] - t0, 3), "stop_after_cut_s": round(t_rest - cut["t"], 3),
                "stated_bound_s": round(arm.stop_within_s, 3),
                "within_bound": bool(t_rest - cut["t"] <= arm.stop_within_s),
                "tcp_travel_after_cut_m": round(tcp_after_m, 4),
                "stopped_short_of_goal_rad": round(float(np.max(np.abs(q_rest - q[-1]))), 4), "error": raised}
    finally:
        arm.close()
        srv.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cuts", type=int, default=6, help="cut times per mode, spread over 0.4..2.4 s (default 6)")
    ap.add_argument("--results-dir", default=str(RESULTS))
    args = ap.parse_args()
    ctx = context(vars(args))
    rcfg = load_robot_config("inovo_2f85")
    a = rcfg.arm
    kin = MujocoKinematics(rcfg.mjcf, tuple(a.joints), a.tcp_site, a.flange_site)
    rows = [one_cut(rcfg, kin, float(c), mode) for mode in ("silent", "dropped")
            for c in np.linspace(0.4, 2.4, args.cuts)]
    s = StreamSettings()
    worst = worst_case_stop_s(s, a.velocity_limits, a.acceleration_limits)
    done = [r for r in rows if r["within_bound"] is not None]
    summary = {"n": len(rows), "measured": len(done), "all_within_bound": all(r["within_bound"] for r in done),
               "stop_after_cut_s_max": max(r["stop_after_cut_s"] for r in done),
               "stop_after_cut_s_mean": round(float(np.mean([r["stop_after_cut_s"] for r in done])), 3),
               "stated_bound_s": done[0]["stated_bound_s"], "worst_case_any_motion_s": round(worst, 3),
               "tcp_travel_after_cut_m_max": max(r["tcp_travel_after_cut_m"] for r in done)}
    out = {"what": "arm stop after link loss, real adapter vs a joint_trajectory_controller model (not a real Inovo)",
           "robot": "inovo_2f85", "speed_scale": SPEED_SCALE,
           "move": {"duration_s": MOVE_S, "dq_rad": DELTA_Q.tolist()},
           "stream": {"horizon_s": s.horizon_s, "period_s": s.period_s, "lead_s": s.lead_s,
                      "brake_fraction": s.brake_fraction, "tail_dt_s": s.tail_dt_s},
           "summary": summary, "rows": rows, "context": {**ctx, "load_avg_end": list(__import__("os").getloadavg())}}
    res = Path(args.results_dir)
    res.mkdir(parents=True, exist_ok=True)
    (res / "arm_stop.json").write_text(json.dumps(out, indent=2) + "\n")
    lines = ["# Arm stop after link loss (streamed chunks ending at rest)", "",
             f"Real adapter (`InovoArm`, default stream settings) against the fake rosbridge server's "
             f"joint_trajectory_controller model, Inovo preset at speed_scale {SPEED_SCALE}, a {MOVE_S:g} s move; "
             "the link dies at the cut (silent: nothing in or out; dropped: socket closed). Not a real controller.",
             "", f"- stop after the cut: max **{summary['stop_after_cut_s_max']} s**, mean "
             f"{summary['stop_after_cut_s_mean']} s; stated bound of this motion {summary['stated_bound_s']} s "
             f"(all within: {summary['all_within_bound']}); worst case over any accepted motion "
             f"{summary['worst_case_any_motion_s']} s",
             f"- measured {summary['measured']} of {summary['n']} cuts (the rest failed before the cut)",
             f"- TCP travel after the cut: at most {summary['tcp_travel_after_cut_m_max'] * 1000:.1f} mm",
             f"- machine load at start {ctx['load_avg_start'][0]:.1f} (contended: {ctx['contended']})", "",
             "| mode | cut (s) | stop after cut (s) | bound (s) | TCP travel (mm) |", "|---|---|---|---|---|"]
    lines += [f"| {r['mode']} | {r['cut_s']} | {r['stop_after_cut_s']} | {r['stated_bound_s']} | "
              f"{r['tcp_travel_after_cut_m'] * 1000:.1f} |" if r["within_bound"] is not None
              else f"| {r['mode']} | {r['cut_s']} | failed before the cut: {r['error']} | | |" for r in rows]
    (res / "arm_stop.md").write_text("\n".join(lines) + "\n")
    print(json.dumps(summary, indent=2))
    return 0 if summary["all_within_bound"] else 1


if __name__ == "__main__":
    sys.exit(main())
