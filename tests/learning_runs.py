"""What the maze learning tests share: each runs a script's main loop as a user runs it (a process of its
own, tests/script_runs.py) at a small setting, and evaluates the student it starts from and the one its
run ends with, with the scripts' own evaluation (envs.evaluation.evaluate) on levels drawn from a fixed
evaluation seed. That the first is the script's own starting student is checked by a learning-rate-0 run,
which must end with it."""

import os

import script_runs
import torch

from envs.evaluate import student_state_dict
from envs.evaluation import evaluate
from envs.levels import HeldOutLevel

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEED = 1
# 16 copies x 128 steps on the CPU; no validation or final evaluation (the tests evaluate the checkpoint's
# student themselves), no checkpoint or level image before the last update.
SMALL = ["--env", "maze", "--num-envs", "16", "--num-steps", "128",
         "--eval-episodes", "0", "--checkpoint-interval", "1000", "--levels-interval", "1000", "--no-cuda"]
STEPS_PER_UPDATE = 16 * 128


def run_script(script: str, learning_rate: float, args: list[str], cwd, seed: int = SEED) -> str:
    """Runs `python script` at the small setting with this learning rate, seed and `args` in cwd; its run directory."""
    command = [os.path.join(ROOT, script), *SMALL, "--seed", str(seed), "--learning-rate", str(learning_rate), *args]
    result = script_runs.run(command, cwd)
    assert result.returncode == 0, result.stderr
    (name,) = os.listdir(os.path.join(cwd, "runs"))
    return os.path.join(cwd, "runs", name)


def initial_student(env, seed: int = SEED):
    """The student a script starts from (PAIRED: the protagonist): seeded as the scripts seed it, the first net they build."""
    torch.manual_seed(seed)
    return env.Student()


def trained_student(env, run_dir: str):
    """The student of a run's last checkpoint (PAIRED: the protagonist)."""
    agent = env.Student()
    agent.load_state_dict(student_state_dict(os.path.join(run_dir, "checkpoint.pt")))
    return agent


def same_weights(a, b) -> bool:
    a, b = a.state_dict(), b.state_dict()
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def returns_on(agent, level: HeldOutLevel, episodes: int = 200):
    """The returns of `episodes` first episodes of the agent on a held-out level, from evaluation seed 123."""
    agent.eval()
    return evaluate(agent, "maze", level, episodes, seed=123, device="cpu")


def random_maze_return(agent, env) -> float:
    """The mean return of 200 first episodes on the maze's random levels (0-60 walls, 250 steps each)."""
    return float(returns_on(agent, HeldOutLevel(generate=env.random_levels, max_steps=250)).mean())
