"""A learning test for the PLR family: plr.py itself, its main loop in its default mode, Robust PLR (train
on replayed levels only), run as a user runs it, must teach the student to find the goal more often in
random mazes. Fails if the agent does not learn: with learning rate 0 the run ends with the student it
started with, and the two evaluations are the same (tests/learning_runs.py).

The setting is small: 16 copies x 128 steps, a 64-level buffer, learning rate 5e-3, 40 updates (about half
of them replays, the others new levels only scored); the rest is the paper's maze Robust PLR. The measure:
200 first episodes on the maze's random levels (0-60 walls), drawn from a fixed evaluation seed, averaged
over three training seeds."""

import csv
import os

from learning_runs import STEPS_PER_UPDATE, initial_student, random_maze_return, run_script, same_weights, trained_student

from envs.maze import MazeEnv

SEEDS = (1, 2, 3)


def test_robust_plr_student_learns_to_reach_the_goal(tmp_path):
    befores, afters = [], []
    for seed in SEEDS:
        env = MazeEnv("maze", 16, seed=1)
        befores.append(random_maze_return(initial_student(env, seed), env))
        cwd = tmp_path / str(seed)
        cwd.mkdir()
        run_dir = run_script("plr.py", 5e-3, ["--level-buffer-size", "64", "--total-timesteps", str(40 * STEPS_PER_UPDATE)], cwd, seed)
        afters.append(random_maze_return(trained_student(env, run_dir), env))
        with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
            rows = list(csv.DictReader(f))
        assert all(row["trained"] == row["replay"] for row in rows) and 12 <= sum(row["trained"] == "1" for row in rows) <= 28
    print("student on random mazes, seeds " + ", ".join(f"{b:.3f} -> {a:.3f}" for b, a in zip(befores, afters)))
    before, after = sum(befores) / len(SEEDS), sum(afters) / len(SEEDS)
    # One seed's gain varies with the machine's floating-point kernels (at 60 updates and learning rate 3e-3,
    # seed 1 ended at 0.199 on one machine, 0.119 and 0.146 on two others), the mean over seeds less so.
    # Measured on an Intel Xeon, before about 0.073 for every seed, after (seeds 1, 2, 3): 0.254 (0.303, 0.201, 0.258);
    # at 60 updates and 3e-3 it was 0.198 to 0.265 on three machines. The bar lies about halfway between the
    # student it starts from and the lowest of these.
    assert after > before + 0.06 and after > 1.8 * before, (befores, afters)


def test_plr_with_learning_rate_0_ends_with_the_student_it_started_with(tmp_path):
    env = MazeEnv("maze", 16, seed=1)
    run_dir = run_script("plr.py", 0.0, ["--level-buffer-size", "64", "--total-timesteps", str(4 * STEPS_PER_UPDATE)], tmp_path)
    assert same_weights(trained_student(env, run_dir), initial_student(env))
