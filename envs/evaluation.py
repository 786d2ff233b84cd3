"""Zero-shot evaluation on held-out levels, the same for every env and script.

Each of the `episodes` episodes of a held-out level runs to its own end in its own env copy, and only
that first episode counts: long episodes weigh as much as short ones (the paper's "episodes evaluated in
sequence", unlike counting whichever episodes finish first in parallel workers). The policy is the
stochastic one. The copies, and all the levels evaluated, are stepped together only for speed: each level
draws from its own seed (`play_first_episodes`).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np
import torch
from torch.distributions import Categorical, Independent

import envs
from envs.runs import fail


def to_torch(obs: dict, device) -> dict:
    """An env's observation (numpy arrays) as tensors on `device`. For a GPU each array is first copied
    into page-locked (pinned) host memory, from which the copy to the GPU runs without making the host
    wait; torch's caching host allocator reuses those pinned blocks from step to step."""
    if torch.device(device).type == "cuda":
        return {k: torch.from_numpy(np.asarray(v)).pin_memory().to(device, non_blocking=True) for k, v in obs.items()}
    return {k: torch.as_tensor(v, device=device) for k, v in obs.items()}


def evaluate(agent, env_name: str, level, episodes: int, seed: int, device) -> np.ndarray:
    """Returns of `episodes` first episodes of the agent on a HeldOutLevel, its random parts and the
    actions drawn from `seed` (`play_first_episodes`)."""
    return play_first_episodes(agent, env_name, [level], episodes, [seed], device)[0]


@torch.no_grad()
def play_first_episodes(agent, env_name: str, levels, episodes: int, seeds, device) -> np.ndarray:
    """Returns [level, episode] of `episodes` first episodes of the agent on each HeldOutLevel of `levels`.

    Level i draws from seeds[i] alone: its level instances, its env copies' random parts, and the actions
    sampled for them, from torch's generator on `device` seeded with seeds[i] (its state is swapped in
    around that level's draw, inside a fork: evaluating never shifts the random stream of training). The
    agent runs on the copies of all levels still playing at once, as one batch: each step costs one pass
    of the network, not one per level. So a level plays what it would play evaluated on its own, up to the float rounding
    of the network's sums at another batch size (a discrete draw near a boundary, a continuous action's
    last bits)."""
    generator = device_generator(device)
    on_cuda = generator.device.type == "cuda"
    with torch.random.fork_rng(devices=[generator.device] if on_cuda else []):
        generator_states = [generator.manual_seed(seed).get_state() for seed in seeds]
        level_envs, observations = [], []
        for level, seed in zip(levels, seeds):
            env = envs.make(env_name, episodes, seed)
            env.training = False  # no training-only reward shaping
            observations.append(env.reset(level.generate(episodes, np.random.default_rng(seed)), level.max_steps))
            level_envs.append(env)
        finished = np.zeros((len(levels), episodes), dtype=bool)
        returns = np.zeros((len(levels), episodes), dtype=np.float64)
        playing = list(range(len(levels)))  # the levels whose copies the batch holds, in order
        state = agent.initial_state(len(levels) * episodes, device)
        done = torch.ones(len(levels) * episodes, device=device)
        while True:
            obs = {key: np.concatenate([observations[i][key] for i in playing]) for key in observations[0]}
            policy, state = agent.policy_and_state(to_torch(obs, device), state, done)
            actions = []
            for k, i in enumerate(playing):  # level i's actions, from its own generator's state
                generator.set_state(generator_states[i])
                actions.append(agent.sample(distribution_rows(policy, slice(k * episodes, (k + 1) * episodes))))
                generator_states[i] = generator.get_state()
            actions = torch.cat(actions).cpu().numpy()  # one copy from the device per step
            ended = np.zeros((len(playing), episodes), dtype=bool)
            for k, i in enumerate(playing):
                observations[i], reward, terminated, truncated, _ = level_envs[i].step(actions[k * episodes : (k + 1) * episodes])
                returns[i] += np.where(finished[i], 0.0, reward)
                ended[k] = terminated | truncated
                finished[i] |= ended[k]
            still = [k for k, i in enumerate(playing) if not finished[i].all()]
            if not still:
                break
            if len(still) < len(playing):  # a level done: its copies, and their state, leave the batch
                rows = np.concatenate([np.arange(k * episodes, (k + 1) * episodes) for k in still])
                state, ended = state_rows(state, torch.as_tensor(rows, device=device)), ended[still]
                playing = [playing[k] for k in still]
            done = torch.as_tensor(ended.reshape(-1), dtype=torch.float32, device=device)
        for env in level_envs:
            env.close()
    return returns


def state_rows(state, rows: torch.Tensor):
    """Some copies' rows of a net's state: None (a feed-forward net), or the LSTM's (h, c), each [1, N, H]
    (envs/nets.py)."""
    return None if state is None else tuple(part[:, rows] for part in state)


def device_generator(device) -> torch.Generator:
    """The generator torch's sampling on `device` draws from."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.default_generators[device.index if device.index is not None else torch.cuda.current_device()]
    return torch.default_generator


def distribution_rows(dist, rows: slice):
    """Some rows of a batch of distributions, as a distribution of the same kind: a Categorical of those
    rows' probabilities, an Independent (or a subclass: CarRacing's BetaPolicy) of its base's rows, any other
    kind built from those rows of its parameters. (The batch's parameters were checked as it was built.)"""
    if isinstance(dist, Independent):
        return type(dist)(distribution_rows(dist.base_dist, rows), dist.reinterpreted_batch_ndims, validate_args=False)
    if isinstance(dist, Categorical):  # its probabilities, computed once for the batch
        return Categorical(probs=dist.probs[rows], validate_args=False)
    return type(dist)(**{name: getattr(dist, name)[rows] for name in dist.arg_constraints}, validate_args=False)


def evaluate_all(agent, env_name: str, names, episodes: int, seed: int, device) -> dict[str, dict]:
    """{level name: {"solved_rate", "mean_return"}} over the named held-out levels of the env, level i
    played from seed + 1000 * i."""
    env = envs.make(env_name, 1, seed)
    held_out = env.test_levels()
    env.close()
    returns = play_first_episodes(agent, env_name, [held_out[name] for name in names], episodes,
                                  [seed + 1000 * i for i in range(len(names))], device)
    return {name: {"solved_rate": float(np.mean(level_returns > env.solved_threshold)),
                   "mean_return": float(np.mean(level_returns))} for name, level_returns in zip(names, returns)}


def save_held_out_evaluation(agent, env_name: str, episodes: int, seed: int, device, paths) -> dict:
    """The zero-shot evaluation on every held-out level of the env, with the mean over them: what a run
    writes as eval.json at its end, and as eval_<steps>.json at a milestone (to each of `paths`). It draws
    from its own random streams (`evaluate`), so a run evaluated at milestones trains as one that is not."""
    env = envs.make(env_name, 1, seed)
    names = list(env.test_levels())
    env.close()
    results = evaluate_all(agent, env_name, names, episodes, seed, device)
    results["mean"] = {k: float(np.mean([r[k] for r in results.values()])) for k in ("solved_rate", "mean_return")}
    for path in paths:
        with open(path, "w") as f:
            json.dump(results, f, indent=2)
    return results


def milestones_passed(milestones, steps_before: int, steps_after: int) -> list[int]:
    """The milestones (env steps) an update took the run to or past: those in (steps_before, steps_after].
    A milestone's evaluation is the one a run given that many steps ends with."""
    return [m for m in milestones if steps_before < m <= steps_after]


# ---------------------------------------------------------------------------------------------------
# Aggregating over seeds: mean and standard error per level, IQM and optimality gap with 95%
# stratified-bootstrap percentile intervals (the methods of Agarwal et al. 2021, as in their rliable).
# Scores are [runs, tasks] matrices; the statistics also take a batch of them, [..., runs, tasks].
# ---------------------------------------------------------------------------------------------------
BOOTSTRAP_REPETITIONS = 10_000
METRICS = ("solved_rate", "mean_return")


def interquartile_mean(scores: np.ndarray):
    """Mean of the middle 50% of all runs' and tasks' scores: int(25%) of them cut from each end, as
    scipy.stats.trim_mean(scores, 0.25, axis=None). One value per matrix of the batch."""
    flat = np.sort(scores.reshape(*scores.shape[:-2], -1), axis=-1)
    cut = int(0.25 * flat.shape[-1])
    return flat[..., cut : flat.shape[-1] - cut].mean(axis=-1)


def optimality_gap(scores: np.ndarray, target: float = 1.0):
    """How far scores fall short of the target on average: mean of max(target - score, 0). One value per
    matrix of the batch."""
    return np.maximum(target - scores, 0.0).mean(axis=(-2, -1))


def bootstrap_interval(scores: np.ndarray, statistic, repetitions: int = BOOTSTRAP_REPETITIONS,
                       seed: int = 0) -> tuple[float, float]:
    """95% percentile interval of statistic(scores [runs, tasks]) under the stratified bootstrap: each
    resample draws, for every task independently, as many runs as there are with replacement.
    `statistic` maps resamples [n, runs, tasks] to [n] values; they are drawn in chunks to bound memory."""
    rng = np.random.default_rng(seed)
    runs, tasks = scores.shape
    chunk = max(1, 1_000_000 // scores.size)
    values = []
    for start in range(0, repetitions, chunk):
        picks = rng.integers(0, runs, (min(chunk, repetitions - start), runs, tasks))
        values.append(statistic(scores[picks, np.arange(tasks)]))
    low, high = np.percentile(np.concatenate(values), [2.5, 97.5])
    return float(low), float(high)


def aggregate(results: list[dict], metric: str = "solved_rate", target: float | None = None) -> dict:
    """Summary over runs (seeds) of their eval.json results on the same levels: per level mean and
    standard error, the mean over levels, IQM and optimality gap (shortfall from `target`, which
    defaults to 1.0 only for solved_rate) with 95% bootstrap intervals."""
    if target is None:
        if metric != "solved_rate":
            raise ValueError(f"the optimality gap of {metric} needs a target")
        target = 1.0
    names = [name for name in results[0] if name != "mean"]
    scores = np.array([[r[name][metric] for name in names] for r in results])
    count = len(results)
    stderr = scores.std(axis=0, ddof=1) / np.sqrt(count) if count > 1 else np.zeros(len(names))
    per_run_mean = scores.mean(axis=1)

    def gap(s):
        return optimality_gap(s, target)

    return {
        "runs": count,
        "levels": {name: {"mean": float(m), "stderr": float(s)} for name, m, s in zip(names, scores.mean(axis=0), stderr)},
        "mean": float(per_run_mean.mean()),
        "mean_stderr": float(per_run_mean.std(ddof=1) / np.sqrt(count)) if count > 1 else 0.0,
        "iqm": float(interquartile_mean(scores)),
        "iqm_ci": bootstrap_interval(scores, interquartile_mean),
        "optimality_gap": float(gap(scores)),
        "optimality_gap_ci": bootstrap_interval(scores, gap),
    }


def load_groups(run_dirs: list[str]) -> dict[str, list[dict]]:
    """The runs' eval.json results grouped by "<env> <exp_name>" from their args.json (one group per env
    and method, one run per seed). Fails on a directory that is not a finished run, and on a group whose
    runs were evaluated on different levels."""
    groups: dict[str, list[dict]] = {}
    for run in run_dirs:
        paths = [os.path.join(run, "eval.json"), os.path.join(run, "args.json")]
        if not all(os.path.isfile(p) for p in paths):
            fail(f"{run} is not a finished run (needs eval.json and args.json)")
        with open(paths[1]) as f:
            args = json.load(f)
        with open(paths[0]) as f:
            results = json.load(f)
        if "env" not in args or "exp_name" not in args:
            fail(f"{run}/args.json names no env and exp_name")
        name = f"{args['env']} {args['exp_name']}"
        group = groups.setdefault(name, [])
        if group and set(group[0]) != set(results):
            fail(f"{run} was evaluated on other levels than the other {name} runs")
        group.append(results)
    return groups


def main(argv=None) -> None:
    """python -m envs.evaluation RUN_DIR [RUN_DIR ...] [--metric M] [--target T] [--plot PNG]: the runs'
    eval.json, grouped by env and exp_name (one group per method, one run per seed), summarized as in
    the paper."""

    class Parser(argparse.ArgumentParser):
        def error(self, message):
            fail(message)

    parser = Parser(description=main.__doc__)
    parser.add_argument("runs", nargs="+", help="run directories holding eval.json and args.json")
    parser.add_argument("--metric", default="solved_rate", choices=METRICS, help="the per-level score to aggregate")
    parser.add_argument("--target", type=float, default=None,
                        help="the optimality gap measures how far scores fall short of this: the best score "
                             "that counts (default 1.0 for solved_rate; required for mean_return, whose best "
                             "value depends on the env)")
    parser.add_argument("--plot", default=None, help="save a PNG of IQM and optimality gap per group")
    options = parser.parse_args(argv)
    if options.target is None and options.metric != "solved_rate":
        fail(f"--metric {options.metric} needs --target, the score its optimality gap is measured from")
    target = 1.0 if options.target is None else options.target
    groups = load_groups(options.runs)
    summaries = {name: aggregate(results, options.metric, target) for name, results in groups.items()}
    print(f"{options.metric}; optimality gap below {target:g}; 95% intervals from {BOOTSTRAP_REPETITIONS} "
          f"stratified bootstrap resamples")
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

        fig, axes = plt.subplots(1, 2, figsize=(8, 1.4 + 0.5 * len(summaries)))
        for ax, key in zip(axes, ("iqm", "optimality_gap")):
            for i, s in enumerate(summaries.values()):
                low, high = s[key + "_ci"]
                ax.barh(i, high - low, left=low, height=0.6, alpha=0.6)
                ax.plot([s[key]], [i], "k|", markersize=12)
            ax.set_yticks(range(len(summaries)), list(summaries) if key == "iqm" else [""] * len(summaries))
            ax.set_title("IQM (higher is better)" if key == "iqm" else "optimality gap (lower is better)")
            ax.set_xlabel(options.metric.replace("_", " "))
            if options.metric == "solved_rate":  # both statistics of a rate lie in [0, 1]
                ax.set_xlim(0, 1)
        fig.suptitle(f"95% stratified-bootstrap intervals over {BOOTSTRAP_REPETITIONS} resamples", fontsize=9)
        fig.tight_layout()
        fig.savefig(options.plot, dpi=100)


if __name__ == "__main__":
    main()
