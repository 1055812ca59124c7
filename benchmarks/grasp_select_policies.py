"""Rank grasp-selection policies on a ``TormGraspSelect`` variant: random, the planner, a heuristic, a trained PPO.

Three phases, each resumable (``runs/grasp_select_<tag>/``):

1. **sweep**: record every candidate's outcome on training layouts (seeds ``0..train-1``) and held-out layouts
   (seeds ``100000..``) with :func:`torm.env.outcome_table.record_layout` (one physics pick per candidate; the
   env is deterministic per (seed, action), so the table is exactly what the live env returns; a few rows are
   re-checked live with :func:`~torm.env.outcome_table.replay_matches_live`). Worker processes split the layouts.
2. **train**: Stable-Baselines3 PPO (``MultiInputPolicy``) on :class:`~torm.env.outcome_table.OutcomeTableEnv`
   over the *training* rows; every ``--eval-every`` steps the deterministic policy is scored on the *held-out*
   rows (the learning curve). The trained policy is saved (``benchmarks/results/policies/``).
3. **evaluate**: on the held-out rows: ``random`` (a uniformly random valid candidate, seeded; its expectation
   too), ``planner`` (action 0, TORM's choice), ``clearance`` (the candidate farthest from other objects, ties by
   score), ``ppo`` (the trained policy, deterministic) and ``best_of_k`` (hindsight: any candidate succeeds; an
   upper bound no policy can beat). Wilson 95 % intervals; planner - random and ppo - planner with Newcombe
   intervals.

Writes ``benchmarks/results/grasp_select_policies.{json,md,png}``. Usage::

    python benchmarks/grasp_select_policies.py --env-id torm/TormGraspSelectHard-v0 --train 120 --eval 80

Cost: the sweep dominates (K picks + one perception per layout; see the md for the measured time).
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing as mp
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from _common import RESULTS, context, context_md, md_table, setup, write_json  # noqa: E402

import torm  # noqa: E402  (registers the envs)
from torm.bench.stats import difference_interval, format_rate, wilson_interval  # noqa: E402
from torm.config import parse_yaml, to_dict  # noqa: E402
from torm.env.outcome_table import record_layout, replay_matches_live  # noqa: E402
from torm.env.policy_io import load_policy, save_policy  # noqa: E402
from torm.env.selection_policies import POLICIES, PPO_HYPERPARAMETERS, choices, successes, train_ppo  # noqa: E402

gym.register_envs(torm)
log = logging.getLogger("grasp_select_policies")

EVAL_OFFSET = 100_000

RUNS = Path(__file__).resolve().parents[1] / "runs"

_ENV: gym.Env | None = None


def _worker_init(env_id: str, kwargs: dict[str, Any]) -> None:
    global _ENV
    import os

    import torch

    os.environ["TORM_THREADS"] = "1"  # one core per worker (reconstruct() reads it)
    torch.set_num_threads(1)
    logging.getLogger().setLevel(logging.WARNING)
    _ENV = gym.make(env_id, **kwargs).unwrapped


def _record(seed: int) -> dict[str, Any]:
    t = time.perf_counter()
    row = record_layout(_ENV, seed)
    row["wall_s"] = time.perf_counter() - t
    return row


def _read_rows(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    rows = []
    for line in path.read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:  # a line cut by an interruption: dropped, its layout is redone
            log.warning("%s: dropping an unreadable line", path)
    return rows


def sweep(env_id: str, kwargs: dict[str, Any], seeds: list[int], path: Path, workers: int) -> list[dict[str, Any]]:
    """Record the rows of ``seeds`` into ``path`` (JSONL, appended as they finish; done seeds are skipped)."""
    from tqdm import tqdm

    done = {r["seed"]: r for r in _read_rows(path)}
    todo = [s for s in seeds if s not in done]
    log.info("%s: %d layouts, %d recorded, %d to record on %d workers", path.name, len(seeds), len(done), len(todo),
             workers)
    if todo:
        with mp.get_context("spawn").Pool(workers, _worker_init, (env_id, kwargs)) as pool, path.open("a") as f:
            for row in tqdm(pool.imap_unordered(_record, todo), total=len(todo), desc=path.stem, unit="layout"):
                f.write(json.dumps(row) + "\n")
                f.flush()
                done[row["seed"]] = row
    return [done[s] for s in seeds]


def plot(curve: list[dict[str, Any]], summary: dict[str, Any], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    steps = [c["steps"] for c in curve]
    ax.plot(steps, [c["heldout_successes"] / c["heldout_n"] for c in curve], "o-", label="PPO, held-out layouts")
    ax.plot(steps, [c["train_successes"] / c["train_n"] for c in curve], ".--", alpha=0.6,
            label="PPO, training layouts")
    for name, style in (("planner", "k-"), ("random", "r:"), ("clearance", "g-."), ("best_of_k", "b--")):
        s = summary[name]
        ax.axhline(s["rate"], ls=style[1:], color=style[0], lw=1, label=f"{name} (held-out) {s['rate']:.2f}")
    ax.set_xlabel("PPO steps (one pick each)")
    ax.set_ylabel("success rate")
    ax.set_ylim(0, 1.02)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env-id", default="torm/TormGraspSelectHard-v0")
    ap.add_argument("--set", dest="env_options", action="append", default=[], metavar="KEY=VALUE",
                    help="env keyword argument (value read as YAML), e.g. --set top_k=8")
    ap.add_argument("--train", type=int, default=120, help="training layouts (seeds 0..N-1)")
    ap.add_argument("--eval", type=int, default=80, help=f"held-out layouts (seeds {EVAL_OFFSET}..)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--timesteps", type=int, default=20000, help="PPO steps on the training table")
    ap.add_argument("--eval-every", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0, help="PPO and random-policy seed")
    ap.add_argument("--live-check", type=int, default=3, help="held-out rows re-run live against the table")
    ap.add_argument("--threads", type=int, default=2, help="torch threads of this process (PPO, live re-check)")
    ap.add_argument("--phases", nargs="+", default=["sweep", "train", "evaluate"],
                    choices=("sweep", "train", "evaluate"))
    ap.add_argument("--tag", default=None, help="run folder name (default: from the env id)")
    ap.add_argument("--algorithm", default="MaskablePPO", choices=("MaskablePPO", "PPO"),
                    help="the trained policy: sb3-contrib's MaskablePPO (reads the action mask) or plain PPO")
    ap.add_argument("--random-seeds", type=int, default=20,
                    help="the random policy is scored with this many generators (mean and range reported)")
    ap.add_argument("--runs-dir", default=str(RUNS))
    ap.add_argument("--out", default=str(RESULTS / "grasp_select_policies"))
    args = ap.parse_args(argv)
    setup(threads=args.threads)
    kwargs = {}
    for text in args.env_options:
        k, _, v = text.partition("=")
        kwargs[k.strip()] = parse_yaml(v)
    tag = args.tag or args.env_id.split("/")[-1].replace("-", "_").lower()
    run = Path(args.runs_dir) / f"grasp_select_{tag}"
    run.mkdir(parents=True, exist_ok=True)
    probe = gym.make(args.env_id, **kwargs)
    spaces, spec_kwargs = (probe.observation_space, probe.action_space), dict(probe.spec.kwargs)
    settings = to_dict(probe.unwrapped.config)
    probe.close()
    train_seeds = list(range(args.train))
    eval_seeds = list(range(EVAL_OFFSET, EVAL_OFFSET + args.eval))
    t0 = time.perf_counter()
    if "sweep" in args.phases:
        train_rows = sweep(args.env_id, kwargs, train_seeds, run / "train.jsonl", args.workers)
        eval_rows = sweep(args.env_id, kwargs, eval_seeds, run / "heldout.jsonl", args.workers)
    else:  # what is recorded so far among the requested seeds
        train_rows = [r for r in _read_rows(run / "train.jsonl") if r["seed"] in set(train_seeds)]
        eval_rows = [r for r in _read_rows(run / "heldout.jsonl") if r["seed"] in set(eval_seeds)]
        log.info("recorded so far: %d training and %d held-out layouts", len(train_rows), len(eval_rows))
    sweep_s = time.perf_counter() - t0
    if args.phases == ["sweep"]:
        return 0
    check = []
    if eval_rows and args.live_check > 0:  # the table is what the live env returns: re-run a few episodes live
        live = gym.make(args.env_id, **kwargs).unwrapped
        try:
            for r in eval_rows[: args.live_check]:
                check += replay_matches_live(live, r, [0, int(np.argmin(r["rewards"]))])
        finally:
            live.close()
        if check:
            raise SystemExit("the outcome table differs from the live env: " + "; ".join(check))
    model_path = RESULTS / "policies" / f"grasp_select_ppo_{tag}.zip"
    curve_path = run / "curve.json"
    if "train" in args.phases:
        model, curve, train_s = train_ppo(train_rows, eval_rows, spaces, args.timesteps, args.eval_every,
                                          args.seed, algorithm=args.algorithm)
        save_policy(model, model_path, args.env_id, *spaces, trained_on={
            "algorithm": args.algorithm, "timesteps": args.timesteps, "seed": args.seed,
            "train_layouts": [int(r["seed"]) for r in train_rows], "hyperparameters": dict(PPO_HYPERPARAMETERS),
            "script": "benchmarks/grasp_select_policies.py"})
        curve_path.write_text(json.dumps({"curve": curve, "train_s": train_s}))
    else:
        model = load_policy(model_path, env_id=args.env_id, observation_space=spaces[0]).model
        saved = json.loads(curve_path.read_text())
        curve, train_s = saved["curve"], saved["train_s"]
    rng = np.random.default_rng(args.seed)
    summary: dict[str, Any] = {}
    for policy in POLICIES:
        acts = choices(policy, eval_rows, model, rng)
        k, n = successes(eval_rows, acts), len(eval_rows)
        summary[policy] = {"successes": k, "episodes": n, "rate": k / n, "wilson95": list(wilson_interval(k, n))}
    # the random policy's result depends on its draw: its mean and range over --random-seeds generators
    draws = [successes(eval_rows, choices("random", eval_rows, None, np.random.default_rng([args.seed, i])))
             for i in range(args.random_seeds)]
    summary["random"].update(seeds=args.random_seeds, mean_successes=float(np.mean(draws)), min_successes=min(draws),
                             max_successes=max(draws))
    expected_random = float(np.mean([np.mean([r["rewards"][a] for a in np.flatnonzero(r["obs"]["valid"])])
                                     if np.any(r["obs"]["valid"]) else 0.0 for r in eval_rows]))
    summary["random"]["expected_rate"] = expected_random
    diffs = {}
    for a, b in (("planner", "random"), ("ppo", "planner"), ("ppo", "random"), ("clearance", "planner")):
        d, lo, hi = difference_interval(summary[a]["successes"], summary[a]["episodes"], summary[b]["successes"],
                                        summary[b]["episodes"])
        diffs[f"{a}-{b}"] = {"difference": d, "newcombe95": [lo, hi]}
    outcome_counts: dict[str, int] = {}
    for r in eval_rows:
        for o in r["outcomes"]:
            outcome_counts[o] = outcome_counts.get(o, 0) + 1
    K = spaces[1].n
    by_rank = []  # does the planner's order carry information? success of the candidate at each rank
    for a in range(K):
        execd = [r["rewards"][a] for r in train_rows + eval_rows if r["obs"]["valid"][a]]
        by_rank.append({"rank": a, "executed": len(execd), "successes": int(sum(v > 0 for v in execd))})
    per_layout_s = float(np.mean([r.get("wall_s", np.nan) for r in train_rows + eval_rows]))
    ctx = context({**vars(args), "env_kwargs": kwargs})
    doc = {"context": ctx, "env": args.env_id, "spec_kwargs": spec_kwargs, "env_settings": settings,
           "train_layouts": len(train_rows), "heldout_layouts": len(eval_rows), "summary": summary,
           "differences": diffs, "heldout_candidate_outcomes": outcome_counts, "success_by_rank": by_rank,
           "learning_curve": curve,
           "ppo": {"algorithm": args.algorithm, "timesteps": args.timesteps, "train_s": train_s,
                   "model": str(model_path.relative_to(RESULTS.parent.parent)),
                   "hyperparameters": {"policy": "MultiInputPolicy", **PPO_HYPERPARAMETERS}},
           "cost": {"sweep_s_this_session": sweep_s, "mean_layout_s_one_worker": per_layout_s},
           "live_recheck": (f"{min(args.live_check, len(eval_rows))} held-out rows, 2 actions each: identical"
                            if args.live_check > 0 and eval_rows else "none in this run")}
    out = Path(args.out)
    write_json(out.with_suffix(".json"), doc)
    title = f"{args.env_id}: {len(train_rows)} training / {len(eval_rows)} held-out layouts"
    plot(curve, summary, out.with_suffix(".png"), title)
    md = [f"# Grasp-selection policies on `{args.env_id}`\n",
          f"Settings: {', '.join(f'{k}={v}' for k, v in spec_kwargs.items())}" + (f"; options {kwargs}" if kwargs
                                                                                 else "") + ".",
          f"K = {K} candidates per layout; training layouts = seeds 0..{args.train - 1}, held-out layouts = seeds "
          f"{EVAL_OFFSET}..{EVAL_OFFSET + args.eval - 1} (scenario drawn per seed). Every candidate of every layout "
          "was executed in physics once and judged by the paper's test (25 cm lift, 20 cm move, lower, release); "
          "the policies are scored on that table ("
          + (f"re-checked live on {min(args.live_check, len(eval_rows))} held-out layouts, 2 candidates each: "
             "identical). " if args.live_check > 0 and eval_rows else "not re-checked live in this run). ")
          +
          "Wilson 95 % intervals.\n",
          md_table(["policy (held-out)", "success"], [[p, format_rate(summary[p]["successes"],
                                                                       summary[p]["episodes"])] for p in POLICIES]),
          f"\nRandom's expected rate over all its choices: {expected_random:.3f}; over {args.random_seeds} "
          f"generators it scores {summary['random']['mean_successes']:.1f}/{len(eval_rows)} on average (range "
          f"{summary['random']['min_successes']}-{summary['random']['max_successes']}). `best_of_k` = any candidate "
          "succeeds (hindsight upper bound). Every policy but `best_of_k` chooses among the valid candidates (the "
          "action mask).\n",
          md_table(["difference", "pp", "Newcombe 95 %"],
                   [[k, f"{100 * v['difference']:+.1f}", f"[{100 * v['newcombe95'][0]:+.1f}, "
                                                         f"{100 * v['newcombe95'][1]:+.1f}]"]
                    for k, v in diffs.items()]),
          "\nSuccess of the candidate at each planner rank (all recorded layouts): "
          + ", ".join(f"{b['rank']}: {b['successes']}/{b['executed']}" for b in by_rank if b["executed"]) + ".\n",
          "\nOutcomes of all held-out candidates: " + ", ".join(f"{k} {v}" for k, v in sorted(outcome_counts.items()))
          + ".\n",
          f"PPO ({args.algorithm}, `MultiInputPolicy`, gamma 0: a contextual bandit): {args.timesteps} steps on the "
          f"training table in {train_s:.0f} s on this machine; the model is `{doc['ppo']['model']}` with its card "
          "(`torm.env.policy_io.load_policy` checks the env id and observation layout). Learning curve: "
          f"`{out.with_suffix('.png').name}`. Recording the table: "
          f"{per_layout_s:.0f} s per layout on one worker (K picks + one perception).\n",
          md_table(["PPO steps", "held-out", "training"],
                   [[c["steps"], f"{c['heldout_successes']}/{c['heldout_n']}", f"{c['train_successes']}/{c['train_n']}"]
                    for c in curve[:: max(1, len(curve) // 10)]]),
          "\n## Run context\n", context_md(ctx)]
    out.with_suffix(".md").write_text("\n".join(md))
    print(out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
