"""Cost of the gymnasium envs per step and per reset, per env and ``obs_mode``, on one core.

- ``torm/TormPick-v0`` with ``obs_mode`` ``state``, ``rgb``, ``rgbd``, ``pointcloud`` (96x96 overview camera):
  steps per second of random actions (one env, one thread), reset seconds; and ``gymnasium.make_vec`` with 2
  sync envs (steps per second of the vector, per core used).
- ``TormGraspSelect`` variants: reset seconds (a new layout: world, capture, perception, planning), reset of the
  same seed (cached perception: physics reset only), step seconds (one whole pick in physics).

Every timing records the CPU other processes used meanwhile (``other_processes_cores``), so a contended run is
visible. Writes ``benchmarks/results/env_throughput.{json,md}``.

Usage: ``python benchmarks/env_throughput.py [--pick-steps 300] [--select-layouts 2]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from _common import RESULTS, context, context_md, cpu_busy_s, md_table, own_cpu_s, setup, write_json  # noqa: E402

import torm  # noqa: E402  (registers the envs)
from torm.env import GRASP_SELECT_HARD_ID, GRASP_SELECT_ID, GRASP_SELECT_MEASURED_ID, PICK_ID  # noqa: E402

gym.register_envs(torm)


class Timer:
    """Wall seconds of a block and the cores other processes kept busy meanwhile."""

    def __enter__(self) -> Timer:
        self.busy0, self.own0, self.t0 = cpu_busy_s(), own_cpu_s(children=True), time.perf_counter()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.wall = time.perf_counter() - self.t0
        other = (cpu_busy_s() - self.busy0) - (own_cpu_s(children=True) - self.own0)
        self.other_cores = round(max(0.0, other) / max(self.wall, 1e-9), 2)


def pick_rows(steps: int) -> list[dict[str, Any]]:
    rows = []
    for mode in ("state", "rgb", "rgbd", "pointcloud"):
        env = gym.make(PICK_ID, scenario="rw1", obs_mode=mode)
        env.action_space.seed(0)
        with Timer() as tr:
            env.reset(seed=0)
        with Timer() as ts:
            for _ in range(steps):
                _, _, term, trunc, _ = env.step(env.action_space.sample())
                if term or trunc:
                    env.reset()
        env.close()
        rows.append({"env": PICK_ID, "obs_mode": mode, "reset_s": tr.wall, "steps": steps,
                     "steps_per_s": steps / ts.wall, "other_processes_cores": ts.other_cores})
    venv = gym.make_vec(PICK_ID, num_envs=2, vectorization_mode="sync", scenario="rw1", obs_mode="state")
    venv.action_space.seed(0)
    venv.reset(seed=0)
    with Timer() as tv:
        for _ in range(steps // 2):
            venv.step(venv.action_space.sample())
    venv.close()
    rows.append({"env": PICK_ID, "obs_mode": "state, make_vec sync x2", "reset_s": None, "steps": 2 * (steps // 2),
                 "steps_per_s": 2 * (steps // 2) / tv.wall, "other_processes_cores": tv.other_cores})
    return rows


def select_rows(layouts: int) -> list[dict[str, Any]]:
    rows = []
    for env_id in (GRASP_SELECT_ID, GRASP_SELECT_MEASURED_ID, GRASP_SELECT_HARD_ID):
        env = gym.make(env_id)
        new, same, step, other = [], [], [], []
        for seed in range(layouts):
            with Timer() as t1:
                env.reset(seed=seed)
            with Timer() as t2:
                env.step(0)
            with Timer() as t3:
                env.reset(seed=seed)
            new.append(t1.wall)
            step.append(t2.wall)
            same.append(t3.wall)
            other += [t1.other_cores, t2.other_cores]
        env.close()
        rows.append({"env": env_id, "layouts": layouts, "reset_new_layout_s": float(np.median(new)),
                     "reset_same_seed_s": float(np.median(same)), "step_s": float(np.median(step)),
                     "other_processes_cores": float(np.mean(other))})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pick-steps", type=int, default=300)
    ap.add_argument("--select-layouts", type=int, default=2)
    ap.add_argument("--out", default=str(RESULTS / "env_throughput"))
    args = ap.parse_args(argv)
    setup(threads=1)
    ctx = context(vars(args))
    pick = pick_rows(args.pick_steps)
    select = select_rows(args.select_layouts)
    doc = {"context": ctx, "pick": pick, "grasp_select": select}
    out = Path(args.out)
    write_json(out.with_suffix(".json"), doc)
    md = ["# Env throughput on one core\n",
          "Random actions; one env on one thread unless stated. `other cores` = CPU other processes used while "
          "timing (above ~0.25 the numbers are contended and low).\n",
          md_table(["env", "obs_mode", "reset (s)", "steps/s", "other cores"],
                   [[r["env"], r["obs_mode"], "-" if r["reset_s"] is None else f"{r['reset_s']:.2f}",
                     f"{r['steps_per_s']:.0f}", f"{r['other_processes_cores']:.2f}"] for r in pick]),
          "\n",
          md_table(["env", "reset, new layout (s)", "reset, same seed (s)", "step = one pick (s)", "other cores"],
                   [[r["env"], f"{r['reset_new_layout_s']:.1f}", f"{r['reset_same_seed_s']:.2f}",
                     f"{r['step_s']:.1f}", f"{r['other_processes_cores']:.2f}"] for r in select]),
          f"\nMedians over {args.select_layouts} layouts per grasp-selection variant.\n",
          "## Run context\n", context_md(ctx)]
    out.with_suffix(".md").write_text("\n".join(md))
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
