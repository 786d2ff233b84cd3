"""The held-out evaluation's time at this checkout against another commit, side by side in one run: the check
for a change to envs/evaluation.py or to the nets' acting step.

Each case evaluates a committed student of results/ as a user does (`python -m envs.evaluate SOURCE
--no-capture-video`: the run's seed and episodes per level, torch's own thread count), from COMMIT and from
this checkout, alternating round by round so that a machine whose speed drifts slows both alike. Only
the evaluation itself is timed (envs.evaluate's call of evaluate_all), not the imports or the loading. The
last lines give each case's median time on both sides, the ratio COMMIT / this checkout (above 1: this
checkout is faster) and whether both sides wrote the same eval.json.

    python benchmarks/evaluation_speed.py 7df0a6a
    python benchmarks/evaluation_speed.py 7df0a6a --rounds 3 --episodes 10

Measure on an idle machine: a figure taken beside other work is no speed claim.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

from against import ROOT, USER_ENVIRONMENT, copy_of_commit

# (label, a committed run directory of results/ holding agent.pt and args.json)
CASES = [
    ("maze, ACCEL seed 1 at 10M steps", "results/maze/accel_random/1"),
    ("maze, DR seed 1 at 10M steps", "results/maze/dr/1"),
]
# envs.evaluate's main, with its call of evaluate_all timed (printed as "evaluation seconds: S")
TIMED_MAIN = """
import sys, time
import envs.evaluate as evaluate
untimed = evaluate.evaluate_all
def timed(*args, **kwargs):
    start = time.perf_counter()
    results = untimed(*args, **kwargs)
    print(f"evaluation seconds: {time.perf_counter() - start}")
    return results
evaluate.evaluate_all = timed
evaluate.main(sys.argv[1:])
"""


def timed_evaluation(code: str, source: str, extra: list[str]) -> tuple[float, dict]:
    """(seconds, eval.json) of `python -m envs.evaluate SOURCE` run from the code in `code`."""
    with tempfile.TemporaryDirectory() as out:
        result = subprocess.run([sys.executable, "-c", TIMED_MAIN, os.path.join(ROOT, source), "--no-capture-video",
                                 "--out", out, *extra], cwd=code, capture_output=True, text=True, env=USER_ENVIRONMENT)
        if result.returncode != 0:
            last_line = (result.stderr.strip().splitlines() or [f"exit status {result.returncode}"])[-1]
            sys.exit(f"{code}: evaluating {source} failed: {last_line}")
        seconds = float(next(line for line in result.stdout.splitlines() if line.startswith("evaluation seconds:")).split()[-1])
        with open(os.path.join(out, "eval.json")) as f:
            return seconds, json.load(f)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("commit", help="the commit to compare against (any git revision)")
    parser.add_argument("--rounds", type=int, default=2, help="runs of each case on each side")
    parser.add_argument("--episodes", type=int, default=None, help="episodes per level (default: the run's)")
    options = parser.parse_args()
    if options.rounds < 1:
        sys.exit("error: --rounds must be at least 1")
    extra = [] if options.episodes is None else ["--episodes", str(options.episodes)]
    with tempfile.TemporaryDirectory() as work:
        sides = {options.commit: copy_of_commit(options.commit, work), "this checkout": ROOT}
        times = {(label, side): [] for label, _ in CASES for side in sides}
        results = {}
        for round_index in range(options.rounds):
            order = list(sides) if round_index % 2 == 0 else list(sides)[::-1]
            for label, source in CASES:
                for side in order:
                    seconds, results[label, side] = timed_evaluation(sides[side], source, extra)
                    times[label, side].append(seconds)
                    print(f"round {round_index + 1}, {label}, {side}: {seconds:.1f} s", flush=True)
    print(f"\nmedian seconds of the evaluation ({options.rounds} rounds)")
    for label, _ in CASES:
        before, after = (float(np.median(times[label, side])) for side in sides)
        same = results[label, options.commit] == results[label, "this checkout"]
        print(f"{label}: {options.commit} {before:.1f} s, this checkout {after:.1f} s, {before / after:.2f}x; "
              f"eval.json {'the same' if same else 'differs'}")


if __name__ == "__main__":
    main()
