"""Evaluate grasp-selection policies on ``torm/TormGraspSelect-v0`` with plain Gymnasium tooling.

An example of using the env the way an RL comparison does: ``gymnasium.make`` (registered by ``import torm``),
``gymnasium.wrappers.RecordEpisodeStatistics``, seeded resets, and three policies:

- ``random``: a uniformly random *valid* candidate (the action-mask baseline);
- ``planner``: action 0, the planner's best candidate (TORM's own choice);
- ``clearance``: a scripted heuristic that picks the candidate farthest from the other objects, ties broken by
  the planner's score (uses only observation features, like a policy would).

Each episode is one pick (the env's spec has ``max_episode_steps=1``); success = the paper's test (25 cm lift,
20 cm translation, lower, release) judged by physics. Perception: ``oracle`` by default (true meshes, fast; the
policy comparison does not need reconstruction); ``--perception torm`` runs the whole pipeline per episode.

Writes ``benchmarks/results/grasp_select_policies.{json,md}``. About 2 s per episode on 2 cores with oracle
perception (default: 4 scenarios x 5 seeds x 3 policies = 60 episodes, ~2-3 minutes).

Usage: ``python benchmarks/grasp_select_policies.py [--scenarios rw1 rw3 ...] [--seeds 5]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from _common import RESULTS, context, context_md, md_table, setup, write_json  # noqa: E402

import torm  # noqa: E402  (registers the envs)
from torm.bench.stats import format_rate, wilson_interval  # noqa: E402
from torm.env.grasp_select_env import FEATURE_NAMES  # noqa: E402

gym.register_envs(torm)

POLICIES = ("random", "planner", "clearance")


def choose(policy: str, obs: dict[str, np.ndarray], rng: np.random.Generator) -> int:
    """The candidate index ``policy`` picks from observation ``obs``."""
    valid = np.flatnonzero(obs["valid"])
    if len(valid) == 0:
        return 0
    if policy == "random":
        return int(rng.choice(valid))
    if policy == "planner":
        return 0
    feats = obs["candidates"][valid]
    clear = feats[:, FEATURE_NAMES.index("clearance")]
    score = feats[:, FEATURE_NAMES.index("score")]
    return int(valid[np.lexsort((-score, -clear))[0]])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["rw1", "rw3", "rw5", "rw7"])
    ap.add_argument("--seeds", type=int, default=5, help="layout seeds per scenario (0..N-1)")
    ap.add_argument("--perception", default="oracle", choices=("oracle", "torm", "depth"))
    ap.add_argument("--out", default=str(RESULTS / "grasp_select_policies"))
    args = ap.parse_args(argv)
    setup()
    ctx = context(vars(args))
    rows = []
    for scenario in args.scenarios:
        env = gym.wrappers.RecordEpisodeStatistics(
            gym.make("torm/TormGraspSelect-v0", scenario=scenario, perception=args.perception))
        try:
            for policy in POLICIES:
                rng = np.random.default_rng(0)
                for seed in range(args.seeds):
                    obs, info = env.reset(seed=seed)
                    action = choose(policy, obs, rng)
                    _, reward, terminated, truncated, info = env.step(action)
                    rows.append({"scenario": scenario, "seed": seed, "policy": policy, "action": action,
                                 "reward": float(reward), "outcome": info.get("outcome"),
                                 "episode_length": int(info["episode"]["l"]), "terminated": bool(terminated),
                                 "truncated": bool(truncated)})
        finally:
            env.close()
    summary = []
    for policy in POLICIES:
        sel = [r for r in rows if r["policy"] == policy]
        k, n = sum(r["reward"] > 0 for r in sel), len(sel)
        lo, hi = wilson_interval(k, n)
        summary.append({"policy": policy, "successes": k, "episodes": n, "rate": k / n if n else None,
                        "wilson95": [lo, hi]})
    doc = {"context": ctx, "env": "torm/TormGraspSelect-v0", "perception": args.perception,
           "summary": summary, "episodes": rows}
    out = Path(args.out)
    write_json(out.with_suffix(".json"), doc)
    md = ["# Grasp-selection policies on torm/TormGraspSelect-v0\n",
          f"Perception `{args.perception}`, scenarios {', '.join(args.scenarios)}, layout seeds 0..{args.seeds - 1}; "
          "reward 1 = the paper's success test passed (physics). Wilson 95 % intervals.\n",
          md_table(["policy", "success"], [[s["policy"], format_rate(s["successes"], s["episodes"])]
                                           for s in summary]),
          "\n## Run context\n", context_md(ctx)]
    out.with_suffix(".md").write_text("\n".join(md))
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
