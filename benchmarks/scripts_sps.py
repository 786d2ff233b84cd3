"""End-to-end steps/s of the algorithm scripts at the paper's settings for an env (maze: 32 envs x 256
steps, 5 epochs; carracing: 16 x 125, 8 epochs; walker: 16 x 2000, 5 epochs).

Each script runs as a user would run it, in a temporary directory, for a few updates; the rate is read
from its metrics.csv over the updates after the first (steps and time both cumulative there, evaluation
excluded). Only the level buffer is shrunk (to 64 levels, 32 for the 16-copy envs) so that replay
updates start after two updates instead of hundreds; a buffer's size does not change the cost of an
update. With a level buffer, the share of replay updates in a short run scatters around the replay
probability p (11 updates at p = 0.5 give 3 to 8 replays), so the rate a long run converges to is
printed too: the mean steps over the mean time of an update with p's mix of this run's replay and
new-level updates. For PAIRED the shares of the update spent in the teacher's rollout, the students' rollouts (env
and inference), their PPO updates and the teacher's update are printed too, and on the maze the paper's teacher's
rate as a multiple of the light teacher's (--teacher-conv-channels 16), both measured in this run.

    python benchmarks/scripts_sps.py [--env maze] [--updates 8] [--only accel.py ...]
    python benchmarks/scripts_sps.py --env carracing --updates 3 --only paired_bc.py
    python benchmarks/scripts_sps.py --env walker --updates 3 --only accel.py
"""

import argparse
import csv
import glob
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
QUIET = ["--eval-interval", "100000", "--eval-episodes", "1", "--levels-interval", "100000", "--checkpoint-interval", "100000"]
BUFFER = ["--level-buffer-size", "64"]
SMALL_BUFFER = ["--level-buffer-size", "32"]
BATCH = {"maze": 32 * 256, "carracing": 16 * 125, "walker": 16 * 2000}
MAZE_CASES = [
    ("plr.py (Robust PLR)", "plr.py", BUFFER, "env steps"),
    ("plr.py --replay-prob 0 (DR)", "plr.py", ["--replay-prob", "0"], "env steps"),
    ("accel.py", "accel.py", BUFFER, "env steps, incl. edit evaluation"),
    ("paired.py (paper's teacher)", "paired.py", [], "protagonist steps"),
    ("paired.py --teacher-conv-channels 16", "paired.py", ["--teacher-conv-channels", "16"], "protagonist steps"),
    ("paired_bc.py --bidirectional", "paired_bc.py", ["--bidirectional"], "protagonist steps"),
    ("paired_evo.py", "paired_evo.py", BUFFER, "student steps, both students"),
]
CONTINUOUS_CASES = [
    ("plr.py (Robust PLR)", "plr.py", SMALL_BUFFER, "env steps"),
    ("accel.py", "accel.py", SMALL_BUFFER, "env steps, incl. edit evaluation"),
    ("paired.py", "paired.py", [], "protagonist steps"),
    ("paired_bc.py --bidirectional", "paired_bc.py", ["--bidirectional"], "protagonist steps"),
    ("paired_evo.py", "paired_evo.py", SMALL_BUFFER, "student steps, both students"),
]

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--env", default="maze", choices=sorted(BATCH), help="the env, at its paper settings")
parser.add_argument("--updates", type=int, default=8, help="updates per script (the first is not timed)")
parser.add_argument("--only", nargs="*", default=None, help="script names to run (default: all)")
options = parser.parse_args()

print(f"{'script (' + options.env + ')':40s} {'steps/s':>9s}  counting")
rates = {}
for label, script, extra, counting in MAZE_CASES if options.env == "maze" else CONTINUOUS_CASES:
    if options.only and script not in options.only:
        continue
    with tempfile.TemporaryDirectory() as tmp:
        # PAIRED's budget counts protagonist steps; the others count every step they simulate.
        steps = options.updates * BATCH[options.env]
        command = [sys.executable, os.path.join(ROOT, script), "--env", options.env, "--total-timesteps", str(steps), *QUIET, *extra]
        result = subprocess.run(command, cwd=tmp, capture_output=True, text=True)
        if result.returncode != 0:
            print(f"{label:40s} failed: {result.stderr.strip().splitlines()[-1]}")
            continue
        run_dir = glob.glob(os.path.join(tmp, "runs", "*"))[0]
        with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
            rows = list(csv.DictReader(f))
        with open(os.path.join(run_dir, "args.json")) as f:
            replay_prob = json.load(f).get("replay_prob")
    step_column = "student_steps" if "student_steps" in rows[0] else "env_steps"
    steps = np.array([float(r[step_column]) for r in rows])
    elapsed = steps / np.array([float(r["sps"]) for r in rows])
    rate = (steps[-1] - steps[0]) / (elapsed[-1] - elapsed[0])
    rates[label] = rate
    line = f"{label:40s} {rate:9.0f}  {counting}"
    if "replay" in rows[0] and replay_prob:
        # Over a few updates the share of replay updates (which train, and in ACCEL also edit) scatters
        # around the replay probability p; a long run's rate is the mean steps over the mean time of an
        # update with p's mix, from this run's average replay and new-level updates.
        replay = np.array([r["replay"] == "1" for r in rows])[1:]
        step_sizes, times = np.diff(steps), np.diff(elapsed)
        if replay.any() and (~replay).any():
            mix = lambda x: replay_prob * x[replay].mean() + (1 - replay_prob) * x[~replay].mean()  # noqa: E731
            line += f" | {replay.sum()}/{len(replay)} replay updates; at p = {replay_prob}: {mix(step_sizes) / mix(times):.0f}"
    if "time_teacher_update" in rows[0]:
        parts = ["time_teacher_rollout", "time_student_rollouts", "time_student_updates", "time_teacher_update"]
        totals = {p: sum(float(r[p]) for r in rows[1:]) for p in parts}
        total = sum(totals.values())
        line += " | " + ", ".join(f"{p[5:]} {totals[p] / total:.0%}" for p in parts)
    print(line, flush=True)
teachers = [label for label, script, extra, _ in MAZE_CASES if script == "paired.py"]
if options.env == "maze" and all(label in rates for label in teachers):
    print(f"paired.py: the paper's teacher at {rates[teachers[0]] / rates[teachers[1]]:.2f}x the light teacher's steps/s")
