"""Steps per second of the walker env (envs/walker/env.py, 16 copies) against one gymnasium BipedalWalker-v3.

    python benchmarks/walker_env.py [--seconds 10] [--rounds 10] [--copies 16] [--levels v3|random]

They run in the same run, in alternating rounds (so both see the same load from whatever else runs
on the machine), with uniform random actions in [-1, 1]^4 made before timing. A step of N walker env
copies counts as N env steps; ended episodes restart inside the env. gymnasium's walker
(BipedalWalker-v3, hardcore off) is stepped in a plain loop, reset after every ended episode and at
1600 steps (its TimeLimit). The walker env plays the held-out "BipedalWalker-v3" course (gymnasium's
own terrain generator; --levels random: the DR levels of training instead) with the same limit. The
last line ends with the ratio walker env / gymnasium as a bare number.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import gymnasium  # noqa: E402
from gymnasium.envs.box2d.bipedal_walker import BipedalWalker  # noqa: E402

from envs.walker import WalkerEnv  # noqa: E402

ACTION_BLOCK = 4096  # pre-generated action rows, cycled
MAX_STEPS = 1600  # BipedalWalker-v3's TimeLimit


class WalkerEnvRunner:
    """A WalkerEnv with 16 (or --copies) copies on its levels, stepped with random actions in rounds."""

    def __init__(self, copies: int, levels: str, seed: int):
        rng = np.random.default_rng(seed)
        self.env = WalkerEnv(copies, seed)
        batch = self.env.random_levels(copies, rng) if levels == "random" else self.env.test_levels()["BipedalWalker-v3"].generate(copies, rng)
        self.env.reset(batch, max_steps=MAX_STEPS)
        self.actions = rng.uniform(-1, 1, (ACTION_BLOCK, copies, 4)).astype(np.float32)
        self.calls = 0
        for _ in range(20):  # warm-up
            self.step()

    def step(self) -> int:
        self.env.step(self.actions[self.calls % ACTION_BLOCK])
        self.calls += 1
        return self.env.num_envs


class GymnasiumRunner:
    """One gymnasium BipedalWalker-v3, reset after each ended episode (and at its 1600-step limit)."""

    def __init__(self, seed: int):
        rng = np.random.default_rng(seed)
        self.env = BipedalWalker()
        self.env.reset(seed=seed)
        self.actions = rng.uniform(-1, 1, (ACTION_BLOCK, 4)).astype(np.float32)
        self.steps = self.episode_steps = 0
        for _ in range(20):  # warm-up
            self.step()

    def step(self) -> int:
        _, _, terminated, _, _ = self.env.step(self.actions[self.steps % ACTION_BLOCK])
        self.steps += 1
        self.episode_steps += 1
        if terminated or self.episode_steps >= MAX_STEPS:
            self.env.reset()
            self.episode_steps = 0
        return 1


def run_for(runner, seconds: float) -> tuple[int, float]:
    """Step a runner for about `seconds`; -> (env steps, elapsed seconds)."""
    steps = 0
    start = time.perf_counter()
    while True:
        for _ in range(8):  # check the clock every 8 calls
            steps += runner.step()
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return steps, elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="timed seconds per env, over all rounds")
    parser.add_argument("--copies", type=int, default=16, help="walker env copies")
    parser.add_argument("--levels", choices=("v3", "random"), default="v3", help="the walker env's levels")
    parser.add_argument("--rounds", type=int, default=10, help="alternating rounds the seconds are split into")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    print(f"python {platform.python_version()}, numpy {np.__version__}, gymnasium {gymnasium.__version__}, "
          f"{os.cpu_count()} CPUs, {args.seconds:g} s per env in {args.rounds} rounds")
    print(f"{'env':<36}{'copies':>8}{'steps timed':>14}{'steps/s':>12}")
    runners = {
        "gymnasium BipedalWalker-v3 (loop)": GymnasiumRunner(args.seed),
        f"WalkerEnv {args.levels}": WalkerEnvRunner(args.copies, args.levels, args.seed),
    }
    totals = {name: [0, 0.0] for name in runners}
    # Alternate short rounds, so every runner sees the same load from whatever else runs on the machine.
    for _ in range(args.rounds):
        for name, runner in runners.items():
            steps, elapsed = run_for(runner, args.seconds / args.rounds)
            totals[name][0] += steps
            totals[name][1] += elapsed
    sps = {name: steps / elapsed for name, (steps, elapsed) in totals.items()}
    for name, runner in runners.items():
        copies = args.copies if isinstance(runner, WalkerEnvRunner) else 1
        print(f"{name:<36}{copies:>8}{totals[name][0]:>14,}{sps[name]:>12,.0f}")
    ratio = sps[f"WalkerEnv {args.levels}"] / sps["gymnasium BipedalWalker-v3 (loop)"]
    print(f"ratio WalkerEnv({args.copies})/gymnasium: {ratio:.2f}")


if __name__ == "__main__":
    main()
