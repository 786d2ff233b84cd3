"""How the committed maze students play away from the held-out mazes: on the levels of the DR generator
they all began from, and in empty rooms with the goal in the middle or by the outer wall. Beside it, from
each run's metrics.csv, how the rollouts it trained on ended over its last tenth of steps.

    python -m results.probe_maze results/maze

reads DIR/<experiment>/1/{agent.pt, metrics.csv} (the 10M campaign) and DIR/long/<experiment>/1/ (the
long runs, agent.pt at their last milestone), and writes DIR/long/probe.md. Each level set is played by
the scripts' evaluation (envs.evaluation: 300 first episodes, 250 steps each, the stochastic policy, from
a fixed evaluation seed), so the same code on the same CPU writes the same file.
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import torch

from envs.evaluation import play_first_episodes
from envs.levels import HeldOutLevel
from envs.maze import MazeEnv
from results.report_common import EXPERIMENTS, fail, load_runs
from results.report_milestones import load_long_runs

EPISODES = 300
SEED = 123
MAX_STEPS = 250


def rooms_with_goal(env: MazeEnv, middle: bool):
    """Empty rooms (ACCEL's empty generator) kept only where the goal lies in the middle 7 x 7 cells of the
    13 x 13 interior, or (middle False) within two cells of the outer wall."""
    def generate(n: int, rng: np.random.Generator):
        levels = env.empty_levels(8 * n, rng)
        goal = levels.goal
        keep = np.all((goal >= 4) & (goal <= 10), axis=1) if middle else np.any((goal <= 2) | (goal >= 12), axis=1)
        return levels[np.flatnonzero(keep)[:n]]
    return generate


def level_sets(env: MazeEnv) -> dict[str, HeldOutLevel]:
    return {"DR levels (0-60 walls)": HeldOutLevel(env.random_levels, MAX_STEPS),
            "empty room, goal in the middle": HeldOutLevel(rooms_with_goal(env, middle=True), MAX_STEPS),
            "empty room, goal by the wall": HeldOutLevel(rooms_with_goal(env, middle=False), MAX_STEPS)}


def training_rollouts(metrics: list[dict]) -> str:
    """Episodes per rollout the student trained on (plr.py's `trained`, accel.py's `replay`), and of them the
    unsolved, over the run's last tenth of env steps; "–" for a script that logs neither."""
    last = int(metrics[-1]["env_steps"])
    rows = [row for row in metrics if int(row["env_steps"]) > 0.9 * last and row.get("trained", row.get("replay")) == "1"]
    if not rows or "episodes" not in rows[0]:
        return "– | –"
    episodes = np.array([float(row["episodes"]) for row in rows])
    unsolved = episodes * (1 - np.array([float(row["solved_rate"]) for row in rows]))
    return f"{episodes.mean():.0f} | {unsolved.mean():.1f}"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("directory", help="the maze's results directory (results/maze)")
    args = parser.parse_args(argv)
    long_directory = os.path.join(args.directory, "long")
    if not os.path.isdir(long_directory):
        fail(f"{args.directory} holds no long/ folder of long runs")
    torch.set_num_threads(1)
    env = MazeEnv("maze", 1, seed=1)
    sets = level_sets(env)
    students = []  # (label, run directory, metrics)
    for directory, runs in ((args.directory, load_runs(args.directory)), (long_directory, load_long_runs(long_directory))):
        for experiment, seeds in runs.items():
            if 1 in seeds and os.path.isfile(os.path.join(directory, experiment, "1", "agent.pt")):
                steps = int(seeds[1]["metrics"][-1]["env_steps"])
                students.append((f"{EXPERIMENTS.get(experiment, experiment)}, {steps / 1e6:.0f}M", os.path.join(directory, experiment, "1"), seeds[1]["metrics"]))
    lines = ["Seed 1 of each run: its student's solved rate on each level set (300 first episodes, 250 steps each), and the",
             "rollouts it trained on over its last tenth of steps (episodes per rollout of 32 copies x 256 steps, and of",
             "them unsolved). Written by `python -m results.probe_maze results/maze`.", "",
             "| student | " + " | ".join(sets) + " | episodes per rollout | unsolved |",
             "|---|" + "---|" * (len(sets) + 2)]
    for name, run, metrics in students:
        agent = env.Student()
        agent.load_state_dict(torch.load(os.path.join(run, "agent.pt"), map_location="cpu"))
        agent.eval()
        returns = play_first_episodes(agent, "maze", list(sets.values()), EPISODES, [SEED] * len(sets), "cpu")
        solved = " | ".join(f"{np.mean(level_returns > 0):.2f}" for level_returns in returns)
        lines.append(f"| {name} | {solved} | {training_rollouts(metrics)} |")
        print(lines[-1], flush=True)
    with open(os.path.join(long_directory, "probe.md"), "w") as f:
        f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
