"""A run continued to a longer budget (`--resume RUN_DIR --total-timesteps N`) must equal a run given N steps
from the start: metrics.csv row for row in every training column (the validation at the first part's end
may stay), and the same held-out evaluations. Every script on the maze; on CarRacing the two scripts its
long campaign continues (tests/test_continue_run_carracing.py), with the code of the other four's
continuation the same as theirs (the shared envs.runs.resumed_args and record_continuation, and the same
few lines in each loop). Each tiny run costs a process start and its evaluations, hence no more cases. The
uninterrupted run also evaluates at a milestone (`--milestones`), which must leave its training as it is
and give the evaluation that the first part ended with: a milestone's evaluation is the one a run of
that budget ends with.

Each case is a run of budget B continued to 2B, against a run of 2B with a milestone at B. The runs
are independent, so a module fixture plays them two at a time."""

import concurrent.futures
import json
import os

import pytest
from test_scripts_accel_evo import only_run_dir, read_metrics, run

MAZE = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", "--eval-episodes", "1", "--eval-interval", "100",
        "--checkpoint-interval", "1"]
PAIRED_MAZE = ["--teacher-conv-channels", "4"]
CURATOR = ["--level-buffer-size", "4"]
# (script, env flags, the script's flags, B: the first part's budget in env steps; 2 or 3 updates)
CASES = {
    "plr-maze": ("plr.py", MAZE, CURATOR, 256),
    "accel-maze": ("accel.py", MAZE, [*CURATOR, "--gradient-updates", "0"], 384),
    "paired-maze": ("paired.py", MAZE, PAIRED_MAZE, 256),
    "paired_hient-maze": ("paired_hient.py", MAZE, PAIRED_MAZE, 256),
    "paired_bc-maze": ("paired_bc.py", MAZE, [*PAIRED_MAZE, "--bc-interval", "1"], 256),
    "paired_evo-maze": ("paired_evo.py", MAZE, [*CURATOR, "--bc-coef", "0.1", "--bc-interval", "1"], 384),
}
TIMING = ("sps", "time_")


def continued(script, flags, budget, cwd):
    """A run of `budget` steps, then resumed to twice that with a milestone at its new end."""
    first = run(script, [*flags, "--total-timesteps", str(budget)], cwd)
    if first.returncode != 0:
        return first, None
    return first, run(script, ["--resume", only_run_dir(cwd), "--total-timesteps", str(2 * budget), "--milestones", str(2 * budget)], cwd)


def play(cases: dict, tmp_path_factory, extra_flags=()) -> dict:
    """{case: ((first part, continuation), its cwd, uninterrupted run, its cwd)}, two runs at a time."""
    cwds = {(case, kind): tmp_path_factory.mktemp(f"{case}-{kind}") for case in cases for kind in ("continued", "straight")}
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        futures = {}
        for case, (script, env_flags, flags, budget) in cases.items():
            flags = [*env_flags, *extra_flags, *flags]
            futures[case, "continued"] = pool.submit(continued, script, flags, budget, cwds[case, "continued"])
            futures[case, "straight"] = pool.submit(run, script, [*flags, "--total-timesteps", str(2 * budget), "--milestones", str(budget)],
                                                    cwds[case, "straight"])
        return {case: (futures[case, "continued"].result(), cwds[case, "continued"], futures[case, "straight"].result(),
                       cwds[case, "straight"]) for case in cases}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    return play(CASES, tmp_path_factory)


def training_columns(row: dict) -> dict:
    return {k: v for k, v in row.items() if not k.startswith(TIMING) and not k.startswith("val_")}


def read_json(path):
    with open(path) as f:
        return json.load(f)


@pytest.mark.parametrize("case", list(CASES))
def test_a_run_continued_to_a_longer_budget_equals_one_given_it_from_the_start(finished, case):
    """Catches a budget that something besides the loop's end depends on, state lost at the first part's
    end, and a milestone's evaluation that draws from training's random streams or differs from the final
    evaluation of a run of that budget."""
    check_continued(finished[case], CASES[case][3])


def check_continued(played, budget: int) -> None:
    """A case's continued run against its uninterrupted one (`play`'s entry for it)."""
    (first, continuation), cwd, straight, straight_cwd = played
    assert first.returncode == 0, first.stderr[-3000:]
    assert continuation.returncode == 0, continuation.stderr[-3000:]
    assert straight.returncode == 0, straight.stderr[-3000:]
    assert "resuming" in continuation.stdout
    run_dir, straight_dir = only_run_dir(cwd), only_run_dir(straight_cwd)
    rows, straight_rows = read_metrics(run_dir), read_metrics(straight_dir)
    assert int(rows[-1]["env_steps"]) >= 2 * budget > int(rows[-2]["env_steps"])
    assert [training_columns(r) for r in rows] == [training_columns(r) for r in straight_rows]
    # The first part's final evaluation is kept as the milestone of its budget; both runs end alike, and the
    # continuation's new milestone at its end is its final evaluation.
    for name in (f"eval_{budget}.json", "eval.json"):
        assert read_json(os.path.join(run_dir, name)) == read_json(os.path.join(straight_dir, name)), name
    assert read_json(os.path.join(run_dir, "eval.json")) == read_json(os.path.join(run_dir, f"eval_{2 * budget}.json"))
    assert not os.path.exists(os.path.join(straight_dir, f"eval_{2 * budget}.json"))
    saved = read_json(os.path.join(run_dir, "args.json"))
    assert (saved["total_timesteps"], saved["milestones"]) == (2 * budget, [2 * budget])  # a later --resume goes on to them


def test_a_budget_below_what_the_run_has_done_is_refused(finished):
    (_, _), cwd, _, _ = finished["plr-maze"]
    run_dir = only_run_dir(cwd)
    with open(os.path.join(run_dir, "args.json")) as f:
        before = f.read()
    result = run("plr.py", ["--resume", run_dir, "--total-timesteps", "128"], cwd)
    assert result.returncode == 2
    assert result.stderr.strip() == f"error: --total-timesteps 128 is below the 512 env steps the run {run_dir} has done"
    with open(os.path.join(run_dir, "args.json")) as f:
        assert f.read() == before  # nothing written
    assert os.path.isfile(os.path.join(run_dir, "eval.json"))
