"""Agent steps per second of CarRacing's (or the walker's) env with its copies stepped in worker processes
(envs/workers.py) against stepping them in process, measured side by side in one run.

    python benchmarks/env_workers.py [--env carracing] [--copies 16] [--workers 0 2] [--seconds 5] [--rounds 3]

Each setting is an env of `--copies` copies made by envs.make with that many worker processes (0: in
process), reset on the same random levels (CarRacing: PLR's random sketches; the walker: DR's levels) and
stepped in training mode with the same uniform random actions in the policy's range; episodes restart
their levels. Worker processes start at the reset, before the timing. The settings take turns round by
round, so a machine whose speed drifts slows them alike. A step of N copies counts as N agent steps. The
last line ends with the ratio of the last setting to the first (medians over rounds) as a bare number.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import envs  # noqa: E402


def steps_per_second(name: str, copies: int, workers: int, seconds: float, seed: int) -> float:
    """Agent steps per second of env `name` with `copies` copies in `workers` worker processes."""
    env = envs.make(name, copies, seed, workers=workers)
    rng = np.random.default_rng(seed)
    levels = (env.level_generators["sketch"] if name == "carracing" else env.random_levels)(copies, rng)
    space = env.single_action_space
    actions = rng.uniform(space.low, space.high, (64, copies, *space.shape)).astype(np.float32)
    env.reset(levels)
    for a in actions[:3]:  # warm-up
        env.step(a)
    steps = 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        env.step(actions[steps % len(actions)])
        steps += 1
    rate = steps * copies / (time.perf_counter() - start)
    env.close()
    return rate


parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--env", default="carracing", choices=("carracing", "walker"))
parser.add_argument("--copies", type=int, default=16, help="env copies (the paper's CarRacing and walker runs: 16)")
parser.add_argument("--workers", type=int, nargs="+", default=[0, 2], help="worker processes of each setting (0: in process)")
parser.add_argument("--seconds", type=float, default=5.0, help="stepping time per setting and round")
parser.add_argument("--rounds", type=int, default=3)
parser.add_argument("--seed", type=int, default=0)
options = parser.parse_args()
os.environ.setdefault("CLEANUED_F1_TRACKS", "none")  # no held-out tracks are played here

rates = {workers: [] for workers in options.workers}
for round_number in range(options.rounds):
    for workers in options.workers:
        rates[workers].append(steps_per_second(options.env, options.copies, workers, options.seconds, options.seed))
    print(f"round {round_number + 1}: " + ", ".join(f"{w} workers {r[-1]:,.0f}" for w, r in rates.items()), flush=True)
medians = {workers: float(np.median(r)) for workers, r in rates.items()}
print(f"{options.env}, {options.copies} copies, {os.cpu_count()} CPUs, agent steps/s (medians of {options.rounds} rounds): "
      + ", ".join(f"{w} workers {m:,.0f}" for w, m in medians.items()))
first, last = options.workers[0], options.workers[-1]
print(f"{last} workers / {first} workers: {medians[last] / medians[first]:.2f}")
