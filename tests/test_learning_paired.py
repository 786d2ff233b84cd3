"""A learning test for PAIRED: paired.py itself, its main loop (the paper's Algorithm 1) run as a user runs
it (a process of its own, tests/script_runs.py), must make the protagonist better on random mazes. Fails if
the students do not learn: with learning rate 0 the run ends with the protagonist it started with, and the
two evaluations are the same.

The setting is small: 16 copies x 128 steps, learning rate 3e-3, 30 updates; a light teacher (4 conv
channels, one PPO epoch: its LSTM update is a Python loop that would otherwise take half the time, and it
plays no part in how the students learn); the rest is the paper's maze PAIRED. A teacher this young places
its walls almost at random, so the protagonist's gain shows on the maze's random levels (0-60 walls). The
evaluation is the scripts' own code (envs.evaluation.evaluate) on levels drawn from a fixed evaluation
seed, the same before and after."""

import os

import script_runs
import torch

from envs.evaluate import student_state_dict
from envs.evaluation import evaluate
from envs.levels import HeldOutLevel
from envs.maze import MazeEnv

SCRIPT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "paired.py")
SEED = 1
SMALL = ["--env", "maze", "--seed", str(SEED), "--num-envs", "16", "--num-steps", "128", "--teacher-conv-channels", "4",
         "--teacher-update-epochs", "1", "--eval-episodes", "1", "--eval-interval", "1000", "--checkpoint-interval", "1000",
         "--levels-interval", "1000", "--no-cuda"]
STEPS_PER_UPDATE = 16 * 128


def run_paired(cwd, learning_rate: float, updates: int) -> str:
    """Runs paired.py at the small setting; its run directory."""
    result = script_runs.run([SCRIPT, *SMALL, "--learning-rate", str(learning_rate), "--total-timesteps", str(updates * STEPS_PER_UPDATE)], cwd)
    assert result.returncode == 0, result.stderr
    (name,) = os.listdir(os.path.join(cwd, "runs"))
    return os.path.join(cwd, "runs", name)


def initial_protagonist(env):
    """The protagonist paired.py starts from: seeded as the script seeds it, the first net it builds."""
    torch.manual_seed(SEED)
    return env.Student()


def trained_protagonist(env, run_dir):
    agent = env.Student()
    agent.load_state_dict(student_state_dict(os.path.join(run_dir, "checkpoint.pt")))  # the checkpoint's "protagonist"
    return agent


def random_maze_return(agent, env) -> float:
    """The mean return of 200 first episodes on the maze's random levels (250 steps each)."""
    random_mazes = HeldOutLevel(generate=env.random_levels, max_steps=250)
    agent.eval()
    return float(evaluate(agent, "maze", random_mazes, 200, seed=123, device="cpu").mean())


def test_paired_protagonist_improves(tmp_path):
    env = MazeEnv("maze", 16, seed=SEED)
    before = random_maze_return(initial_protagonist(env), env)
    after = random_maze_return(trained_protagonist(env, run_paired(tmp_path, 3e-3, 30)), env)
    print(f"protagonist on random mazes: {before:.3f} -> {after:.3f}")
    # measured: 0.074 -> 0.238 (seeds 2 and 3: 0.073 -> 0.209 and 0.271); 20 updates: 0.074 -> 0.137
    assert after > before + 0.08 and after > 2 * before, (before, after)


def test_paired_with_learning_rate_0_ends_with_the_protagonist_it_started_with(tmp_path):
    """What makes the learning test's `before` honest: the script's first protagonist is `initial_protagonist`."""
    env = MazeEnv("maze", 16, seed=SEED)
    start = initial_protagonist(env).state_dict()
    end = trained_protagonist(env, run_paired(tmp_path, 0.0, 1)).state_dict()
    assert all(torch.equal(start[k], end[k]) for k in start)
