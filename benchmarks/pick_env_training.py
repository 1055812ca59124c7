"""A short PPO run on an easy ``torm/TormPick-v0`` variant: does the dense reward teach anything in bounded CPU?

Easy variant: rw1 (one glass cylinder), trained on layout 0, ``obs_mode="state"`` with ``privileged_state`` (the
object's true pose), ``reward_shaping=True`` (reach + grasp + lift terms, see the env docs; the reach term on
ManiSkill's PickCube scale, ``reach_scale=5``), episodes of
``--episode-steps`` steps. Stable-Baselines3 PPO (``MultiInputPolicy``) on ``--envs`` sync vector envs for
``--timesteps`` steps; every ``--eval-every`` steps the deterministic policy runs ``--eval-episodes`` episodes on
held-out layouts 1000.. (mean return, mean final TCP-object distance, successes), beside a uniformly random
policy's. "Learning" means the PPO policy's return rises above the random policy's; a pick within this budget is
not expected.

Writes ``benchmarks/results/pick_env_training.{json,md,png}``.

Usage: ``python benchmarks/pick_env_training.py [--timesteps 30000]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from _common import RESULTS, context, context_md, md_table, setup, write_json  # noqa: E402

import torm  # noqa: E402  (registers the envs)
from torm.env import PICK_ID  # noqa: E402

gym.register_envs(torm)

EASY = {"scenario": "rw1", "layout_seed": 0, "obs_mode": "state", "privileged_state": True, "reward_shaping": True,
        "reach_scale": 5.0}


def evaluate(policy: Any, episodes: int, episode_steps: int, seed: int) -> dict[str, float]:
    """Mean return, final TCP-object distance (m) and successes of ``policy(obs) -> action`` on the easy variant."""
    env = gym.make(PICK_ID, max_episode_steps=episode_steps, **EASY)
    returns, dists, wins = [], [], 0
    try:
        for e in range(episodes):
            obs, _ = env.reset(seed=seed + e)
            total, done, info = 0.0, False, {}
            while not done:
                obs, r, term, trunc, info = env.step(policy(obs))
                total += float(r)
                done = term or trunc
            returns.append(total)
            dists.append(float(info.get("tcp_object_distance_m", np.nan)))
            wins += bool(info.get("is_success", False))
    finally:
        env.close()
    return {"mean_return": float(np.mean(returns)), "std_return": float(np.std(returns)),
            "final_distance_m": float(np.nanmean(dists)), "successes": wins, "episodes": episodes}


def main(argv: list[str] | None = None) -> int:
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--timesteps", type=int, default=30000)
    ap.add_argument("--envs", type=int, default=2)
    ap.add_argument("--episode-steps", type=int, default=50)
    ap.add_argument("--eval-every", type=int, default=6000)
    ap.add_argument("--eval-episodes", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(RESULTS / "pick_env_training"))
    ap.add_argument("--report-only", action="store_true", help="rewrite the md and png from the existing json")
    args = ap.parse_args(argv)
    if args.report_only:
        out = Path(args.out)
        report(json.loads(out.with_suffix(".json").read_text()), out)
        return 0
    setup(threads=1)
    ctx = context(vars(args))
    from stable_baselines3.common.env_util import make_vec_env

    sb3_env = make_vec_env(PICK_ID, n_envs=args.envs, seed=args.seed,
                           env_kwargs={"max_episode_steps": args.episode_steps, **EASY})
    rng = np.random.default_rng(args.seed)
    space = sb3_env.action_space
    random_eval = evaluate(lambda _o: rng.uniform(space.low, space.high).astype(np.float32), args.eval_episodes,
                           args.episode_steps, 1000)
    curve: list[dict[str, Any]] = []

    class Curve(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.next = 0

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next:
                self.next += args.eval_every
                ev = evaluate(lambda o: self.model.predict(o, deterministic=True)[0], args.eval_episodes,
                              args.episode_steps, 1000)
                curve.append({"steps": int(self.num_timesteps), **ev})
            return True

    model = PPO("MultiInputPolicy", sb3_env, n_steps=512, batch_size=128, learning_rate=3e-4, gamma=0.98,
                seed=args.seed, verbose=0, device="cpu")
    t = time.perf_counter()
    model.learn(total_timesteps=args.timesteps, callback=Curve())
    train_s = time.perf_counter() - t
    final = evaluate(lambda o: model.predict(o, deterministic=True)[0], args.eval_episodes, args.episode_steps, 1000)
    if not curve or curve[-1]["steps"] != int(model.num_timesteps):
        curve.append({"steps": int(model.num_timesteps), **final})
    sb3_env.close()
    doc = {"context": ctx, "env": PICK_ID, "variant": EASY, "episode_steps": args.episode_steps,
           "random_policy": random_eval, "curve": curve, "train_s": train_s,
           "steps_per_s_training": args.timesteps / train_s,
           "ppo": {"policy": "MultiInputPolicy", "n_steps": 512, "batch_size": 128, "learning_rate": 3e-4,
                   "gamma": 0.98, "envs": args.envs}}
    out = Path(args.out)
    write_json(out.with_suffix(".json"), doc)
    report(doc, out)
    return 0


def report(doc: dict[str, Any], out: Path) -> None:
    """Write the plot and the Markdown table of a run's JSON ``doc`` next to ``out`` (``--report-only`` redoes it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args, curve, random_eval = doc["context"]["args"], doc["curve"], doc["random_policy"]
    fig, ax = plt.subplots(figsize=(6.0, 3.6))
    ax.errorbar([c["steps"] for c in curve], [c["mean_return"] for c in curve],
                yerr=[c["std_return"] for c in curve], fmt="o-", label="PPO (deterministic)")
    ax.axhline(random_eval["mean_return"], color="r", ls=":", label="random actions")
    ax.set_xlabel("training steps")
    ax.set_ylabel(f"mean return ({doc['episode_steps']}-step episodes)")
    ax.set_title(f"{PICK_ID}, easy variant (rw1, state + privileged, dense reward)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=120)
    plt.close(fig)
    n_eval = args["eval_episodes"]
    md = [f"# PPO on an easy `{PICK_ID}` variant\n",
          f"Variant: {doc['variant']}, {doc['episode_steps']}-step episodes; Stable-Baselines3 PPO, {args['envs']} "
          f"sync vector envs (SB3 seeds their first reset with 0..{args['envs'] - 1}; every later reset is layout 0), "
          f"{args['timesteps']} steps in {doc['train_s']:.0f} s on this machine ({doc['steps_per_s_training']:.0f} "
          "steps/s including PPO updates and the evaluations). Evaluation: the deterministic policy on "
          f"{n_eval} held-out layouts (seeds 1000..{1000 + n_eval - 1}: the same cylinder elsewhere on the table; "
          "the privileged observation gives its pose), the same layouts for every point and for random actions.\n",
          md_table(["policy", "steps", "mean return", "final TCP-object distance (m)", "successes"],
                   [["random", "-", f"{random_eval['mean_return']:.2f}", f"{random_eval['final_distance_m']:.3f}",
                     f"{random_eval['successes']}/{random_eval['episodes']}"]]
                   + [["PPO", c["steps"], f"{c['mean_return']:.2f} +- {c['std_return']:.2f}",
                       f"{c['final_distance_m']:.3f}", f"{c['successes']}/{c['episodes']}"] for c in curve]),
          "\nPlot: `pick_env_training.png`.\n", "## Run context\n", context_md(doc["context"])]
    out.with_suffix(".md").write_text("\n".join(md))
    print(out.with_suffix(".md").read_text())


if __name__ == "__main__":
    sys.exit(main())
