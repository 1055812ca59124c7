"""Robot fit benchmark: does each shipped robot.yaml give a robot that reaches, squeezes and picks as configured?

Per robot (``inovo_2f85``: pre-combined MJCF at the origin; ``mini6_lg90``: arm + linkage gripper composed from
two files, base moved by ``base_pose``):

* reach: the start-up reach check's share of the workspace box (``sim/robots/reach.py``);
* grip force: requested vs produced pad force on fixed blocks (``measure_gripper.check_force``: MuJoCo contact
  forces, requests 20-235 N at widths between the force map's grid points);
* TCP offset: how far the pads move along the approach between the widest and the narrowest gap;
* arm sag: the TCP error at home after 0.6 s with ``gravcomp`` on and off;
* picks: closed-loop oracle trials (true meshes, so only the robot is under test) on the rw suite, seed 0, with
  the robot's own gravcomp setting and, for robots whose MJCF has no gravity compensation, with it off too:
  outcome per object, largest TCP tracking error, and the grip force requested / applied / measured.

Writes ``benchmarks/results/robot_fit.json`` and ``robot_fit.md``. Resumable: finished rows are kept in
``runs/robot_fit/rows.jsonl`` and skipped on a re-run (``--fresh`` starts over). About 3-5 minutes here
(2 cores): ``MUJOCO_GL=egl python benchmarks/robot_fit.py [--robots inovo_2f85 mini6_lg90] [--scenarios rw1 rw2]``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import RESULTS, ROOT, context, context_md, md_table, setup, write_json  # noqa: E402

log = logging.getLogger("bench.robot_fit")
ROWS = ROOT / "runs" / "robot_fit" / "rows.jsonl"
SCENARIOS = tuple(f"rw{i}" for i in range(1, 9))
CHECK_WIDTHS = (0.018, 0.036, 0.058, 0.077)
CHECK_FORCES = (20.0, 60.0, 130.0, 235.0)


def _done() -> dict[str, dict[str, Any]]:
    if not ROWS.exists():
        return {}
    out = {}
    for line in ROWS.read_text().splitlines():
        if line.strip():
            row = json.loads(line)
            out[row["key"]] = row
    return out


def _append(row: dict[str, Any]) -> None:
    ROWS.parent.mkdir(parents=True, exist_ok=True)
    with ROWS.open("a") as f:
        f.write(json.dumps(row) + "\n")


def robot_static(name: str) -> dict[str, Any]:
    """Reach, force check, TCP offset range, sag on/off for one robot."""
    import numpy as np

    from sim.backend import SimBackend
    from sim.robots.config import load_robot_config
    from sim.robots.measure_gripper import check_force
    from sim.robots.reach import reach_report
    from sim.world import WORKSPACE_BOUNDS, build_world

    cfg = load_robot_config(name)
    t = time.perf_counter()
    rep = reach_report(cfg, WORKSPACE_BOUNDS)
    reach_s = time.perf_counter() - t
    force = check_force(cfg, CHECK_FORCES, CHECK_WIDTHS)
    offs = [o for _, o in cfg.gripper.tcp_offset] or [0.0]
    sag = {}
    for on in (True, False):
        rc = load_robot_config(name, [f"gravcomp={str(on).lower()}"])
        b = SimBackend(build_world("rw1", seed=0, robot=rc))
        b.clock.sleep(0.6)
        st = b.arm.state()
        sag[str(on).lower()] = float(np.linalg.norm(
            st.T_world_tcp[:3, 3] - b.arm.forward_kinematics(b.arm.inner.target())[:3, 3]))
        b.close()
    return {"key": f"static/{name}", "robot": name, "composed": cfg.composed,
            "base_pose": [list(cfg.base_pose.position), list(cfg.base_pose.orientation)],
            "gravcomp": cfg.gravcomp, "reach_share": rep.share, "reach_points": len(rep.reached),
            "reach_s": reach_s, "force_check": force,
            "force_max_abs_rel_error": max(abs(r["rel_error"]) for r in force),
            "tcp_offset_span_m": max(offs) - min(offs), "sag_m": sag}


def trial(name: str, scenario: str, gravcomp: str) -> dict[str, Any]:
    """One oracle trial of ``name`` on ``scenario`` seed 0 (``gravcomp``: "yaml", "true" or "false")."""
    from torm import config
    from torm.pipeline import TrialConfig, run_trial

    robot = name
    if gravcomp != "yaml":  # override the robot.yaml: a copy with absolute paths under runs/robot_fit/
        import yaml

        from sim.robots.config import robot_yaml_path

        src = robot_yaml_path(name)
        data = yaml.safe_load(src.read_text())
        data["gravcomp"] = gravcomp == "true"
        for sect, key in ((None, "mjcf"), (None, "scene"), ("arm", "mjcf"), ("gripper", "mjcf")):
            d = data if sect is None else data.get(sect, {})
            if d.get(key):
                d[key] = str((src.parent / d[key]).resolve())
        tmp = ROWS.parent / f"{name}_gravcomp_{gravcomp}.yaml"
        tmp.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(yaml.safe_dump(data))
        robot = str(tmp)
    cfg = config.from_dict(TrialConfig, {"scenario": scenario, "seed": 0, "method": "oracle", "robot": robot},
                           overrides=["capture.n_views=6", "capture.scale=0.25"])
    t = time.perf_counter()
    rec = run_trial(cfg)
    objs = []
    for o in rec["objects"]:
        p = o.get("pick") or {}
        g = p.get("grip_force") or {}
        objs.append({"name": o["name"], "outcome": o["outcome"], "tcp_error_max_m": p.get("tcp_error_max_m"),
                     "requested_n": g.get("requested_n"), "applied_n": g.get("applied_n"),
                     "measured_n": g.get("measured_n"), "message": o.get("message", "")})
    return {"key": f"trial/{name}/{scenario}/{gravcomp}", "robot": name, "scenario": scenario, "gravcomp": gravcomp,
            "objects": objs, "wall_s": time.perf_counter() - t, "context": rec.get("context")}


def _markdown(ctx: dict[str, Any], static: list[dict], trials: list[dict]) -> str:
    out = ["# Robot fit: reach, grip force, sag and picks per robot.yaml\n",
           "Produced by `benchmarks/robot_fit.py` (oracle method: true object meshes, GT segmentation, so only the "
           "robot is under test; MuJoCo renderer, ideal depth, realism profile none).\n", context_md(ctx)]
    rows = [[s["robot"], "arm + gripper files" if s["composed"] else "one MJCF", str(s["base_pose"][0]),
             str(s["gravcomp"]), f"{s['reach_share'] * 100:.0f} % of {s['reach_points']}", s["reach_s"],
             s["force_max_abs_rel_error"] * 100, s["tcp_offset_span_m"] * 1e3, s["sag_m"]["true"] * 1e3,
             s["sag_m"]["false"] * 1e3] for s in static]
    out.append("\n## Per robot\n")
    out.append(md_table(["robot", "form", "base position (m)", "gravcomp (yaml)", "reach", "reach check s",
                         "pad force max abs error %", "pads move along approach (mm)", "sag, gravcomp on (mm)",
                         "sag, gravcomp off (mm)"], rows, nd=2))
    out.append("\n## Pad force on fixed blocks (requested -> applied by the map -> measured by MuJoCo contacts)\n")
    frows = [[s["robot"], r["width_m"] * 1e3, r["requested_n"], r["applied_n"], r["measured_n"], r["rel_error"] * 100]
             for s in static for r in s["force_check"]]
    out.append(md_table(["robot", "block mm", "requested N", "applied N", "measured N", "error %"], frows, nd=1))
    out.append("\n## Oracle picks, seed 0\n")
    trows = []
    for t in trials:
        n = len(t["objects"])
        ok = sum(o["outcome"] == "success" for o in t["objects"])
        outcomes = ", ".join(f"{o['name']}: {o['outcome']}" for o in t["objects"] if o["outcome"] != "success")
        tcp = max((o["tcp_error_max_m"] or 0.0) for o in t["objects"]) if n else None
        meas = [o["measured_n"] / o["applied_n"] - 1 for o in t["objects"] if o["measured_n"] and o["applied_n"]]
        trows.append([t["robot"], t["scenario"], t["gravcomp"], f"{ok}/{n}", outcomes or "-",
                      None if tcp is None else tcp * 1e3, max(map(abs, meas)) * 100 if meas else None, t["wall_s"]])
    out.append(md_table(["robot", "scenario", "gravcomp", "success", "other outcomes", "max TCP error mm",
                         "max abs grip force error %", "wall s"], trows, nd=1))
    tot = {}
    for t in trials:
        k = (t["robot"], t["gravcomp"])
        a, b = tot.get(k, (0, 0))
        tot[k] = (a + sum(o["outcome"] == "success" for o in t["objects"]), b + len(t["objects"]))
    out.append("\nTotals: " + "; ".join(f"{r} (gravcomp {g}): {a}/{b}" for (r, g), (a, b) in tot.items()) + "\n")
    return "".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", nargs="+", default=["inovo_2f85", "mini6_lg90"])
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--fresh", action="store_true", help="forget finished rows")
    args = parser.parse_args()
    setup(verbose=False)
    if args.fresh and ROWS.exists():
        ROWS.unlink()
    ctx = context(vars(args))
    done = _done()
    static, trials = [], []
    for name in args.robots:
        key = f"static/{name}"
        if key not in done:
            done[key] = robot_static(name)
            _append(done[key])
        static.append(done[key])
        from sim.robots.config import load_robot_config

        modes = ["yaml"] + (["false"] if load_robot_config(name).gravcomp else [])
        for mode in modes:
            for sc in args.scenarios:
                key = f"trial/{name}/{sc}/{mode}"
                if key not in done:
                    done[key] = trial(name, sc, mode)
                    _append(done[key])
                    log.warning("%s %s gravcomp=%s: %s", name, sc, mode,
                                [o["outcome"] for o in done[key]["objects"]])
                trials.append(done[key])
    doc = {"context": ctx, "robots": static, "trials": trials}
    write_json(RESULTS / "robot_fit.json", doc)
    (RESULTS / "robot_fit.md").write_text(_markdown(ctx, static, trials))


if __name__ == "__main__":
    main()
