"""What the sweep tests share: tiny maze runs, a sweep file written from a dict, and the launcher run as a user
runs it (python -m results.sweep)."""

import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# 6 updates of 4 copies x 32 steps; a checkpoint after each, one held-out episode per maze at the end
TINY = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", "--total-timesteps", "768", "--level-buffer-size", "8",
        "--eval-episodes", "1", "--eval-interval", "1000", "--levels-interval", "4", "--checkpoint-interval", "1"]


def with_budget(steps: int) -> list[str]:
    """TINY with another --total-timesteps."""
    at = TINY.index("--total-timesteps")
    return [*TINY[:at], "--total-timesteps", str(steps), *TINY[at + 2:]]


ONE_UPDATE = with_budget(128)  # for tests of the queue, where what a run does does not matter
LONG = with_budget(10_000_000)  # a run that is still going whenever the test stops it


def sweep_file(path, experiments: dict, seeds=(1,), parallel=1) -> str:
    lines = [f"seeds = {list(seeds)}", f"parallel = {parallel}", "threads = 1", "timeout_hours = 1", "[experiments]"]
    lines += [f"{name} = {json.dumps(command)}" for name, command in experiments.items()]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def sweep(*args, **kwargs):
    return subprocess.run([sys.executable, "-m", "results.sweep", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=600, **kwargs)


def metric_rows(run_dir):
    with open(os.path.join(run_dir, "metrics.csv")) as f:
        return f.read().strip().splitlines()[1:]
