"""Protagonist steps/s of the headline command, `python paired_bc.py --bidirectional --env carracing`,
against an older commit of cleanued (default a26ba50, the commit before the CarRacing speed work),
measured side by side in one run.

Both run the command as a user would (the paper's settings: 16 copies x 125 steps, 8 epochs of 4
minibatches per student), in temporary directories, for a few updates, alternating baseline and current
checkout round by round, so that a machine whose speed drifts slows both alike. A run's rate is read
from its metrics.csv over the updates after the first (steps and time both cumulative there;
validation, level images and checkpoints pushed beyond the run, the final evaluation not counted). Only
the held-out F1 tracks are left out (the current checkout's `--f1-tracks none`; the baseline had none).

    python benchmarks/carracing_headline.py [--baseline a26ba50] [--updates 3] [--rounds 1]
    OMP_NUM_THREADS=1 python benchmarks/carracing_headline.py   # both sides on one thread

The last line ends with the ratio current / baseline (of the medians over rounds) as a bare number.
"""

from __future__ import annotations

import argparse
import csv
import glob
import os
import subprocess
import sys
import tempfile

import numpy as np

from against import copy_of_commit  # benchmarks/against.py, beside this script

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BATCH = 16 * 125  # protagonist steps per update at the paper's CarRacing settings
QUIET = ["--eval-interval", "100000", "--eval-episodes", "1", "--levels-interval", "100000", "--checkpoint-interval", "100000"]


def protagonist_rate(code: str, extra: list[str], updates: int) -> tuple[float, float, float]:
    """Protagonist steps/s of the headline command from the code in `code`, over updates 2..updates, and
    the seconds per update (mean over the same updates) of both students' rollouts and PPO updates."""
    with tempfile.TemporaryDirectory() as run_in:
        command = [sys.executable, os.path.join(code, "paired_bc.py"), "--env", "carracing", "--bidirectional",
                   "--total-timesteps", str(updates * BATCH), *QUIET, *extra]
        environment = {k: v for k, v in os.environ.items() if k != "CLEANUED_F1_TRACKS"}
        result = subprocess.run(command, cwd=run_in, capture_output=True, text=True, env=environment)
        if result.returncode != 0:
            sys.exit(f"{code}: paired_bc.py failed: {result.stderr.strip().splitlines()[-1]}")
        with open(glob.glob(os.path.join(run_in, "runs", "*", "metrics.csv"))[0], newline="") as f:
            rows = list(csv.DictReader(f))
    steps = np.array([float(r["env_steps"]) for r in rows])
    elapsed = steps / np.array([float(r["sps"]) for r in rows])
    rollouts, ppo = (np.mean([float(r[column]) for r in rows[1:]]) for column in ("time_student_rollouts", "time_student_updates"))
    return (steps[-1] - steps[0]) / (elapsed[-1] - elapsed[0]), rollouts, ppo


parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--baseline", default="a26ba50", help="the commit to compare against")
parser.add_argument("--updates", type=int, default=3, help="updates per run (the first is not timed)")
parser.add_argument("--rounds", type=int, default=1, help="baseline-then-current rounds")
options = parser.parse_args()
if options.updates < 2 or options.rounds < 1:
    print("error: --updates must be at least 2 and --rounds at least 1", file=sys.stderr)
    sys.exit(2)

import torch  # noqa: E402 (only for the thread count the runs will use)

threads = os.environ.get("OMP_NUM_THREADS", f"{torch.get_num_threads()} (torch's default)")
print(f"paired_bc.py --bidirectional --env carracing, {options.updates} updates per run, threads: {threads}")
rates: dict[str, list[float]] = {"baseline": [], "current": []}
with tempfile.TemporaryDirectory() as scratch:
    sides = {"baseline": (copy_of_commit(options.baseline, scratch), []), "current": (ROOT, ["--f1-tracks", "none"])}
    for round_ in range(options.rounds):
        for side, (code, extra) in sides.items():
            rate, rollouts, ppo = protagonist_rate(code, extra, options.updates)
            rates[side].append(rate)
            print(f"round {round_ + 1} {side + ':':9s} {rate:6.1f} protagonist steps/s; per update: students' rollouts {rollouts:5.1f} s, "
                  f"their PPO updates {ppo:5.1f} s", flush=True)
baseline, current = (float(np.median(rates[side])) for side in ("baseline", "current"))
print(f"baseline {options.baseline} {baseline:.1f}, current {current:.1f} protagonist steps/s (medians); current / baseline: {current / baseline:.2f}")
