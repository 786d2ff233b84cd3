"""The scripts' results at this checkout against another commit: the guard for a change that must not change
what a run computes (a refactor, a faster path). Each case of benchmarks/against.py (every maze script, the
headline command on CarRacing, accel.py on the walker) runs a few updates at the paper's settings with the
same seed from COMMIT and from this checkout, one torch thread each, and their metrics.csv must agree
column for column, row for row, except the timing columns (sps, time_*), as must their eval.json.

    python benchmarks/same_metrics.py d936cb0                  # every case
    python benchmarks/same_metrics.py d936cb0 --only maze      # the maze scripts only

Same seed, same CPU, same result: run both sides on one machine. Exit status 1 if any case differs, with
its first differing row and column.
"""

from __future__ import annotations

import argparse
import csv
import glob
import json
import os
import subprocess
import sys
import tempfile

from against import BATCH, CASES, QUIET, ROOT, USER_ENVIRONMENT, copy_of_commit

UPDATES = {"maze": 3, "carracing": 2, "walker": 2}  # updates per run of each env's cases
TIMING = ("sps", "time_")


def run_outputs(code: str, env: str, script: str, options: list[str]) -> tuple[list[dict], dict]:
    """metrics.csv's rows and eval.json of a run of `script` from the code in `code`, seed 1, one thread."""
    with tempfile.TemporaryDirectory() as run_in:
        command = [sys.executable, os.path.join(code, script), "--env", env, "--seed", "1",
                   "--total-timesteps", str(UPDATES[env] * BATCH[env]), *QUIET, *options]
        result = subprocess.run(command, cwd=run_in, capture_output=True, text=True,
                                env={**USER_ENVIRONMENT, "OMP_NUM_THREADS": "1", "CLEANUED_F1_TRACKS": "none"})
        if result.returncode != 0:
            last_line = (result.stderr.strip().splitlines() or [f"exit status {result.returncode}"])[-1]
            sys.exit(f"{code}: {script} --env {env} failed: {last_line}")
        (run_dir,) = glob.glob(os.path.join(run_in, "runs", "*"))
        with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
            rows = list(csv.DictReader(f))
        with open(os.path.join(run_dir, "eval.json")) as f:
            return rows, json.load(f)


def first_difference(theirs: list[dict], ours: list[dict]) -> str | None:
    """Where two metrics tables first differ outside the timing columns, in words; None if nowhere."""
    if len(theirs) != len(ours):
        return f"{len(theirs)} rows against {len(ours)}"
    for row, (a, b) in enumerate(zip(theirs, ours), start=1):
        for column in sorted(set(a) | set(b)):
            if not column.startswith(TIMING) and a.get(column) != b.get(column):
                return f"row {row}, {column}: {a.get(column)!r} against {b.get(column)!r}"
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("commit", help="the commit to compare this checkout against (e.g. the last release)")
    parser.add_argument("--only", nargs="*", choices=sorted(BATCH), default=sorted(BATCH), help="the envs whose cases run")
    options = parser.parse_args()
    if subprocess.run(["git", "-C", ROOT, "rev-parse", "--verify", "--quiet", options.commit + "^{commit}"],
                      capture_output=True).returncode != 0:
        print(f"error: {options.commit} is not a commit of this repository", file=sys.stderr)
        sys.exit(2)
    differing = 0
    with tempfile.TemporaryDirectory() as scratch:
        theirs_code = copy_of_commit(options.commit, scratch)
        for label, env, script, extra, _ in (case for case in CASES if case[1] in options.only):
            (theirs, their_eval), (ours, our_eval) = (run_outputs(code, env, script, extra) for code in (theirs_code, ROOT))
            difference = first_difference(theirs, ours) or (None if their_eval == our_eval else "eval.json differs")
            differing += difference is not None
            print(f"{env:9s} {label:40s} {'same' if difference is None else 'DIFFERENT: ' + difference} "
                  f"({len(ours)} updates)", flush=True)
    sys.exit(1 if differing else 0)


if __name__ == "__main__":
    main()
