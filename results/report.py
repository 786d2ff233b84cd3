"""The reproductions' numbers and figures, regenerated from the committed run outputs alone.

    python -m results.report results/maze
    python -m results.report results/carracing    # or results/walker: see results/report_continuous.py

The entry point of the reports: it reads the runs in DIR with results/report_common.py and hands them to
the report of their env, the runs' own (their args.json): the maze's is results/report_maze.py,
CarRacing's and the walker's results/report_continuous.py. A long/ folder in DIR, of runs evaluated at
milestones (DIR/long/<experiment>/<seed>/eval_<steps>.json), is reported into itself by
results/report_milestones.py. A campaign's folder under results/ also rewrites results/summary.md, the table of
every campaign's numbers beside the paper's (results/report_summary.py).
No report module imports this one.
"""

from __future__ import annotations

import argparse
import os

from results import report_continuous, report_maze, report_milestones, report_summary
from results.report_common import env_of, fail, load_runs


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Regenerate a reproduction's summary, table and figures (maze, "
                                                 "carracing or walker: the runs' env, from their args.json).")
    parser.add_argument("directory", help="the results directory, e.g. results/maze or results/carracing")
    parser.error = lambda message: fail(message)
    args = parser.parse_args(argv)
    if not os.path.isdir(args.directory):
        fail(f"no directory {args.directory}")
    runs = load_runs(args.directory)
    env = env_of(runs)
    if env in ("carracing", "walker"):
        report_continuous.write_report(args.directory, runs, env)
    else:
        report_maze.write_report(args.directory, runs, env)
    long_runs = os.path.join(args.directory, "long")
    if os.path.isdir(long_runs):
        report_milestones.write_report(long_runs, runs, env)
    if os.path.realpath(os.path.dirname(os.path.abspath(args.directory))) == os.path.realpath(report_summary.RESULTS):
        report_summary.write_summary()


if __name__ == "__main__":
    main()
