"""The scripts' speed at this checkout against another commit, side by side in one run: the regression check
for any change to threads, environment variables, allocation or the hot loops.

Each case runs as a user types it (the scripts' defaults: torch's own thread count, no OpenMP variables;
any OMP_NUM_THREADS, MKL_NUM_THREADS or OMP_WAIT_POLICY in this shell is removed for the runs), in a
temporary directory, for a few updates, alternating COMMIT and this checkout round by round so that a
machine whose speed drifts slows both alike. A run's rate is read from its metrics.csv over the updates
after the first (steps and time both cumulative there; validation, level images and checkpoints pushed
beyond the run, the final evaluation not counted). Only the level buffers are shrunk (so that replay
starts within the run) and CarRacing's held-out F1 tracks left out; both sides get the same options.

    python benchmarks/against.py 15e73fc                 # every case, 2 rounds
    python benchmarks/against.py a26ba50 --only maze     # the maze cases only
    python benchmarks/against.py 15e73fc --rounds 3 --only carracing walker
    python benchmarks/against.py d936cb0 --only maze --case paired_evo --rounds 7   # one case, more rounds

Measure on an idle machine: a figure taken beside other work is no speed claim. The last lines give
each case's median rate on both sides and the ratio this checkout / COMMIT.
"""

from __future__ import annotations

import argparse
import csv
import glob
import os
import subprocess
import sys
import tarfile
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
QUIET = ["--eval-interval", "100000", "--eval-episodes", "1", "--levels-interval", "100000", "--checkpoint-interval", "100000"]
BATCH = {"maze": 32 * 256, "carracing": 16 * 125, "walker": 16 * 2000}  # steps per update at the paper's settings
# (label, env, script, options beyond --env, updates per run; the first update is not timed)
CASES = [
    ("plr.py Robust PLR", "maze", "plr.py", ["--level-buffer-size", "64"], 8),
    ("plr.py DR (--replay-prob 0)", "maze", "plr.py", ["--replay-prob", "0"], 8),
    ("accel.py", "maze", "accel.py", ["--level-buffer-size", "64"], 8),
    ("paired.py", "maze", "paired.py", [], 6),
    ("paired_hient.py", "maze", "paired_hient.py", [], 6),
    ("paired_bc.py", "maze", "paired_bc.py", [], 6),
    ("paired_evo.py", "maze", "paired_evo.py", ["--level-buffer-size", "64"], 8),
    ("paired_bc.py --bidirectional (headline)", "carracing", "paired_bc.py", ["--bidirectional"], 2),
    ("accel.py", "walker", "accel.py", ["--level-buffer-size", "32"], 2),
]
USER_ENVIRONMENT = {k: v for k, v in os.environ.items()
                    if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OMP_WAIT_POLICY", "CLEANUED_PLAIN_NETS")}


def copy_of_commit(commit: str, directory: str) -> str:
    """The files of `commit` of this checkout's repository, unpacked into `directory`."""
    archive = os.path.join(directory, "commit.tar")
    subprocess.run(["git", "-C", ROOT, "archive", "-o", archive, commit], check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(os.path.join(directory, "commit"), filter="data")
    return os.path.join(directory, "commit")


def rate(code: str, env: str, script: str, options: list[str], updates: int) -> float:
    """Steps/s of one run of `script` from the code in `code` over its updates after the first: protagonist
    steps for PAIRED, both students' steps for PAIRED+Evo, every env step for the curators."""
    with tempfile.TemporaryDirectory() as run_in:
        command = [sys.executable, os.path.join(code, script), "--env", env, "--total-timesteps",
                   str(updates * BATCH[env]), *QUIET, *options]
        result = subprocess.run(command, cwd=run_in, capture_output=True, text=True,
                                env={**USER_ENVIRONMENT, "CLEANUED_F1_TRACKS": "none"})
        if result.returncode != 0:
            last_line = (result.stderr.strip().splitlines() or [f"exit status {result.returncode}"])[-1]
            sys.exit(f"{code}: {script} --env {env} failed: {last_line}")
        with open(glob.glob(os.path.join(run_in, "runs", "*", "metrics.csv"))[0], newline="") as f:
            rows = list(csv.DictReader(f))
    step_column = "student_steps" if "student_steps" in rows[0] else "env_steps"
    steps = np.array([float(row[step_column]) for row in rows])
    elapsed = steps / np.array([float(row["sps"]) for row in rows])
    return float((steps[-1] - steps[0]) / (elapsed[-1] - elapsed[0]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("commit", help="the commit to compare this checkout against (e.g. the last release)")
    parser.add_argument("--rounds", type=int, default=2, help="COMMIT-then-this-checkout rounds (medians over them)")
    parser.add_argument("--only", nargs="*", choices=sorted(BATCH), default=sorted(BATCH), help="the envs whose cases run")
    parser.add_argument("--case", default="", help="only the cases whose label contains this text (e.g. paired_evo)")
    options = parser.parse_args()
    if options.rounds < 1:
        print("error: --rounds must be at least 1", file=sys.stderr)
        sys.exit(2)
    cases = [case for case in CASES if case[1] in options.only and options.case in case[0]]
    if not cases:
        print(f"error: no case of {' '.join(options.only)} has {options.case!r} in its label", file=sys.stderr)
        sys.exit(2)
    if subprocess.run(["git", "-C", ROOT, "rev-parse", "--verify", "--quiet", options.commit + "^{commit}"],
                      capture_output=True).returncode != 0:
        print(f"error: {options.commit} is not a commit of this repository", file=sys.stderr)
        sys.exit(2)
    import torch  # only to report the thread count the runs get

    head = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", ROOT, "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True).stdout
    print(f"this checkout: {head}{' with uncommitted changes' if dirty else ''}; against {options.commit}; "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads (torch's default), {os.cpu_count()} cores")
    rates = {(label, env): {"commit": [], "head": []} for label, env, *_ in cases}
    with tempfile.TemporaryDirectory() as scratch:
        sides = {"commit": copy_of_commit(options.commit, scratch), "head": ROOT}
        for round_ in range(options.rounds):
            for label, env, script, extra, updates in cases:
                for side, code in sides.items():
                    rates[label, env][side].append(rate(code, env, script, extra, updates))
                measured = rates[label, env]
                print(f"round {round_ + 1}: {env:9s} {label:40s} {options.commit} {measured['commit'][-1]:8.1f}  "
                      f"this checkout {measured['head'][-1]:8.1f} steps/s", flush=True)
    print(f"\n{'env':9s} {'case':40s} {options.commit:>10s} {'this':>10s}  ratio (medians over {options.rounds} rounds)")
    for (label, env), measured in rates.items():
        commit, head_rate = float(np.median(measured["commit"])), float(np.median(measured["head"]))
        print(f"{env:9s} {label:40s} {commit:10.1f} {head_rate:10.1f}  {head_rate / commit:.2f}x")


if __name__ == "__main__":
    main()
