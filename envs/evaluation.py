"""Zero-shot evaluation on held-out levels (SPEC section 5), the same for every env and script.

Each of the `episodes` episodes of a held-out level runs to its own end in its own env copy, and only
that first episode counts: long episodes weigh as much as short ones (the paper's "episodes evaluated in
sequence", unlike counting whichever episodes finish first in parallel workers). The copies are stepped
together only for speed. The policy is the stochastic one.
"""

from __future__ import annotations

import numpy as np
import torch

import envs


def to_torch(obs: dict, device) -> dict:
    return {k: torch.as_tensor(v, device=device) for k, v in obs.items()}


@torch.no_grad()
def evaluate(agent, env_name: str, level, episodes: int, seed: int, device) -> np.ndarray:
    """Returns of `episodes` first episodes of the agent on a HeldOutLevel (fresh draws of its random
    parts, from `seed`). Actions are sampled from torch's generator forked and seeded here, so evaluating
    never shifts the random stream of training."""
    on_cuda = torch.device(device).type == "cuda"
    with torch.random.fork_rng(devices=[torch.device(device)] if on_cuda else []):
        torch.manual_seed(seed)
        return _play_first_episodes(agent, env_name, level, episodes, seed, device)


def _play_first_episodes(agent, env_name: str, level, episodes: int, seed: int, device) -> np.ndarray:
    env = envs.make(env_name, episodes, seed)
    env.training = False  # no training-only reward shaping (SPEC 2)
    obs = env.reset(level.generate(episodes, np.random.default_rng(seed)), level.max_steps)
    state = agent.initial_state(episodes, device)
    done = torch.ones(episodes, device=device)
    finished = np.zeros(episodes, dtype=bool)
    returns = np.zeros(episodes, dtype=np.float64)
    while not finished.all():
        action, _, _, _, state = agent.get_action_and_value(to_torch(obs, device), state, done)
        obs, reward, terminated, truncated, _ = env.step(action.cpu().numpy())
        returns += np.where(finished, 0.0, reward)
        ended = terminated | truncated
        finished |= ended
        done = torch.as_tensor(ended, dtype=torch.float32, device=device)
    env.close()
    return returns


def evaluate_all(agent, env_name: str, names, episodes: int, seed: int, device) -> dict[str, dict]:
    """{level name: {"solved_rate", "mean_return"}} over the named held-out levels of the env."""
    env = envs.make(env_name, 1, seed)
    held_out = env.test_levels()
    env.close()
    results = {}
    for i, name in enumerate(names):
        returns = evaluate(agent, env_name, held_out[name], episodes, seed + 1000 * i, device)
        results[name] = {
            "solved_rate": float(np.mean(returns > env.solved_threshold)),
            "mean_return": float(np.mean(returns)),
        }
    return results


# ---------------------------------------------------------------------------------------------------
# Aggregating over seeds (SPEC 5): mean and standard error per level, IQM and optimality gap with
# stratified-bootstrap confidence intervals (the method of Agarwal et al. 2021, "rliable").
# ---------------------------------------------------------------------------------------------------
def interquartile_mean(scores: np.ndarray) -> float:
    """Mean of the middle 50% of all scores [runs, tasks] (25% cut from each end, as scipy's trim_mean)."""
    flat = np.sort(scores.reshape(-1))
    cut = int(0.25 * len(flat))
    return float(flat[cut : len(flat) - cut].mean())


def optimality_gap(scores: np.ndarray, target: float = 1.0) -> float:
    """How far scores fall short of the target on average: mean of max(target - score, 0)."""
    return float(np.maximum(target - scores, 0.0).mean())


def bootstrap_interval(scores: np.ndarray, statistic, repetitions: int = 2000, seed: int = 0) -> tuple[float, float]:
    """95% interval of statistic(scores [runs, tasks]), resampling runs with replacement per task."""
    rng = np.random.default_rng(seed)
    runs, tasks = scores.shape
    draws = rng.integers(0, runs, (repetitions, runs, tasks))
    values = [statistic(scores[d, np.arange(tasks)]) for d in draws]
    return float(np.percentile(values, 2.5)), float(np.percentile(values, 97.5))


def aggregate(results: list[dict], metric: str = "solved_rate") -> dict:
    """Summary over runs (seeds) of their eval.json results: per level mean and standard error, the mean
    over levels, IQM and optimality gap with 95% bootstrap intervals."""
    names = [name for name in results[0] if name != "mean"]
    scores = np.array([[r[name][metric] for name in names] for r in results])
    count = len(results)
    stderr = scores.std(axis=0, ddof=1) / np.sqrt(count) if count > 1 else np.zeros(len(names))
    per_run_mean = scores.mean(axis=1)
    return {
        "runs": count,
        "levels": {name: {"mean": float(m), "stderr": float(s)} for name, m, s in zip(names, scores.mean(axis=0), stderr)},
        "mean": float(per_run_mean.mean()),
        "mean_stderr": float(per_run_mean.std(ddof=1) / np.sqrt(count)) if count > 1 else 0.0,
        "iqm": interquartile_mean(scores),
        "iqm_ci": bootstrap_interval(scores, interquartile_mean),
        "optimality_gap": optimality_gap(scores),
        "optimality_gap_ci": bootstrap_interval(scores, optimality_gap),
    }


def main(argv=None) -> None:
    """python -m envs.evaluation RUN_DIR [RUN_DIR ...] [--plot PNG]: the runs' eval.json, grouped by their
    exp_name (one group per method, one run per seed), summarized as in the paper."""
    import argparse
    import json
    import os
    import sys

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("runs", nargs="+", help="run directories holding eval.json and args.json")
    parser.add_argument("--metric", default="solved_rate", help="solved_rate or mean_return")
    parser.add_argument("--plot", default=None, help="save a PNG of IQM and optimality gap per method")
    options = parser.parse_args(argv)
    groups: dict[str, list] = {}
    for run in options.runs:
        paths = [os.path.join(run, "eval.json"), os.path.join(run, "args.json")]
        if not all(os.path.isfile(p) for p in paths):
            print(f"error: {run} is not a finished run (needs eval.json and args.json)", file=sys.stderr)
            sys.exit(2)
        with open(paths[1]) as f:
            name = json.load(f)["exp_name"]
        with open(paths[0]) as f:
            groups.setdefault(name, []).append(json.load(f))
    summaries = {name: aggregate(results, options.metric) for name, results in groups.items()}
    for name, s in summaries.items():
        print(f"{name} ({s['runs']} runs): mean {s['mean']:.3f} +- {s['mean_stderr']:.3f}, IQM {s['iqm']:.3f} "
              f"[{s['iqm_ci'][0]:.3f}, {s['iqm_ci'][1]:.3f}], optimality gap {s['optimality_gap']:.3f} "
              f"[{s['optimality_gap_ci'][0]:.3f}, {s['optimality_gap_ci'][1]:.3f}]")
        for level, v in s["levels"].items():
            print(f"  {level:24s} {v['mean']:.3f} +- {v['stderr']:.3f}")
    if options.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(8, 0.5 + 0.5 * len(summaries)))
        for ax, key in zip(axes, ("iqm", "optimality_gap")):
            for i, s in enumerate(summaries.values()):
                low, high = s[key + "_ci"]
                ax.barh(i, high - low, left=low, height=0.6, alpha=0.6)
                ax.plot([s[key]], [i], "k|", markersize=12)
            ax.set_yticks(range(len(summaries)), list(summaries) if key == "iqm" else [""] * len(summaries))
            ax.set_title(key.replace("_", " "))
        fig.tight_layout()
        fig.savefig(options.plot, dpi=100)


if __name__ == "__main__":
    main()
