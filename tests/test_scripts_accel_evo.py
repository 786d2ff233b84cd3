"""accel.py and paired_evo.py end to end, each run a process of its own (tests/script_runs.py): the run
directory of each mode, the step accounting of replay updates (training rollout plus the children's
evaluation rollout), the BC schedule, and a kill-and-resume round trip per script that must end exactly
where an uninterrupted run ends.

The runs are independent, so a module fixture plays them three at a time (one torch thread each: on a
loaded 2-core machine the third process keeps the wall time down) and the tests check their results.
The uninterrupted run of each kill test is the script's default run."""

import concurrent.futures
import csv
import json
import math
import os
import signal
import time

import pytest
import script_runs

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# One torch thread per run: on a loaded 2-core machine, two busy-waiting OpenMP threads per process slow
# these small runs down by an order of magnitude.
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
NUM_ENVS, NUM_STEPS = 4, 32
BATCH = NUM_ENVS * NUM_STEPS
# Validation and level images cost more than the updates here: one run per script validates and draws
# every 3 and 2 updates, the others only at their end.
TINY = ["--env", "maze", "--num-envs", str(NUM_ENVS), "--num-steps", str(NUM_STEPS), "--level-buffer-size", "8",
        "--total-timesteps", "1024", "--eval-episodes", "1", "--checkpoint-interval", "1", "--log-interval", "1"]
AT_END = ["--eval-interval", "100", "--levels-interval", "100"]
OFTEN = ["--eval-interval", "3", "--levels-interval", "2"]
HELD_OUT = ["SixteenRooms", "SixteenRoomsFewerDoors", "Labyrinth", "Labyrinth2", "Maze", "Maze2", "Maze3", "SmallCorridor",
            "LargeCorridor", "PerfectMazeMedium", "FourRooms", "SimpleCrossingS11N5"]
# key: (script, flags, the header line's start, the run's default experiment name)
RUNS = {
    "accel": ("accel.py", AT_END, "ACCEL on maze", "accel"),
    "accel-random": ("accel.py", [*OFTEN, "--generator", "random"], "ACCEL on maze", "accel_random"),
    # (seed 2: at replay rate 0.5, seed 1 replays once in these 6 updates, too few to check the replay rules)
    "evo": ("paired_evo.py", [*AT_END, "--seed", "2"], "PAIRED+Evo on maze", "paired_evo"),
    "evo-flex": ("paired_evo.py", [*OFTEN, "--flexible"], "FlexPAIRED+Evo on maze", "flexpaired_evo"),
    "evo-bibc": ("paired_evo.py", [*AT_END, "--seed", "2", "--bc-coef", "0.1", "--bc-interval", "2", "--bidirectional"],
                 "PAIRED+Evo+BiBC on maze", "paired_evo_bibc"),
}
KILLED = {"accel-killed": ("accel.py", "accel"), "evo-killed": ("paired_evo.py", "evo")}  # script, uninterrupted run


def run(script, args, cwd):
    return script_runs.run([os.path.join(ROOT, script), *args], cwd, ENV)


def only_run_dir(cwd):
    (name,) = os.listdir(os.path.join(cwd, "runs"))
    return os.path.join(cwd, "runs", name)


def read_metrics(run_dir):
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        return list(csv.DictReader(f))


def kill_and_resume(script, args, cwd):
    """Start a run, SIGKILL it once it has written 3 metric rows, resume it. Returns (finished before the
    kill, the resumed run's result)."""
    process = script_runs.start([os.path.join(ROOT, script), *args], cwd, ENV)
    deadline = time.time() + 300
    while time.time() < deadline and process.poll() is None:
        runs = os.path.join(cwd, "runs")
        # (the run directory exists a moment before its metrics.csv)
        if os.path.isdir(runs) and os.listdir(runs) and os.path.isfile(os.path.join(only_run_dir(cwd), "metrics.csv")) \
                and len(read_metrics(only_run_dir(cwd))) >= 3:
            break
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    ended_early = os.path.exists(os.path.join(only_run_dir(cwd), "eval.json"))
    return ended_early, run(script, ["--resume", only_run_dir(cwd)], cwd)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """{key: (result, cwd)} for every run of RUNS and every kill-and-resume of KILLED."""
    cwds = {key: tmp_path_factory.mktemp(key) for key in [*RUNS, *KILLED]}
    with concurrent.futures.ThreadPoolExecutor(3) as pool:
        futures = {key: pool.submit(kill_and_resume, script, [*TINY, *RUNS[straight][1]], cwds[key])
                   for key, (script, straight) in KILLED.items()}
        futures.update({key: pool.submit(run, script, [*TINY, *flags], cwds[key]) for key, (script, flags, _, _) in RUNS.items()})
        return {key: (future.result(), cwds[key]) for key, future in futures.items()}


@pytest.mark.parametrize("key", list(RUNS))
def test_script_writes_a_complete_run(finished, key):
    script, flags, header, name = RUNS[key]
    result, cwd = finished[key]
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(header), result.stdout[:200]
    run_dir = only_run_dir(cwd)
    seed = flags[flags.index("--seed") + 1] if "--seed" in flags else "1"
    assert os.path.basename(run_dir).startswith(f"maze__{name}__{seed}__")
    rows = read_metrics(run_dir)
    last = len(rows)
    for name in ("args.json", "metrics.csv", "checkpoint.pt", f"levels_{last}.png", "eval.json", "curves.png"):
        assert os.path.isfile(os.path.join(run_dir, name)), name
    often = "--eval-interval" in flags and flags[flags.index("--eval-interval") + 1] == "3"
    pngs = sorted(int(name[7:-4]) for name in os.listdir(run_dir) if name.startswith("levels_") and name.endswith(".png"))
    assert pngs == sorted({*range(2, last + 1, 2), last} if often else {last})

    saved = json.load(open(os.path.join(run_dir, "args.json")))
    assert (saved["num_envs"], saved["num_steps"], saved["level_buffer_size"]) == (NUM_ENVS, NUM_STEPS, 8)
    assert saved["generator"] == ("random" if "--generator" in flags else "empty")  # the maze's default: empty rooms
    assert saved["staleness_coef"] == 0.3
    assert saved["replay_prob"] == {"accel": 0.8, "accel-random": 0.8, "evo": 0.5, "evo-flex": 0.9, "evo-bibc": 0.5}[key]

    evaluation = json.load(open(os.path.join(run_dir, "eval.json")))
    assert list(evaluation) == HELD_OUT + ["mean"]
    for k in ("solved_rate", "mean_return"):
        assert evaluation["mean"][k] == pytest.approx(sum(evaluation[n][k] for n in HELD_OUT) / 12)

    assert [int(r["update"]) for r in rows] == list(range(1, last + 1))
    assert int(rows[-2]["env_steps"]) < 1024 <= int(rows[-1]["env_steps"])  # stops once the budget is spent
    interval = 3 if often else 100
    assert all((r["val_solved_rate"] != "") == (int(r["update"]) % interval == 0 or r is rows[-1]) for r in rows)
    assert rows[0]["replay"] == "0"  # an empty buffer cannot be replayed
    assert all(int(r["buffer_size"]) == min(8, 4 * int(r["update"])) for r in rows[:2])
    assert all(r["buffer_size"] == "8" for r in rows[1:])


def replay_rows(rows):
    return [r for r in rows if r["replay"] == "1"]


@pytest.mark.parametrize("key", list(RUNS))
def test_replay_updates_edit_and_count_two_rollouts(finished, key):
    """A replay update plays two rollouts (training, then the children's evaluation) and logs the
    children; a new-level update plays one and has no children."""
    rows = read_metrics(only_run_dir(finished[key][1]))
    assert len(replay_rows(rows)) >= 2, "too few replay updates to check anything"
    previous = 0
    for r in rows:
        steps = int(r["env_steps"])
        if r["replay"] == "1":
            assert steps - previous == 2 * BATCH, r
            assert 0 <= int(r["children_entered"]) <= NUM_ENVS
            assert all(r[k] != "" for k in ("child_score", "child_walls_change", "child_path_length_change"))
        else:
            assert r["replay"] == "0" and steps - previous == BATCH, r
            assert r["children_entered"] == "" and r["child_score"] == ""
        previous = steps
    if key.startswith("accel"):  # (the students of PAIRED+Evo rarely finish an episode here: regret 0 everywhere)
        assert any(int(r["children_entered"]) > 0 for r in replay_rows(rows)), "no child ever entered the buffer"


@pytest.mark.parametrize("key", ["evo", "evo-flex", "evo-bibc"])
def test_paired_evo_counts_both_students_steps(finished, key):
    """Catches student steps miscounted: both students play a training rollout and the children's
    evaluation rollout on a replay update, one scoring rollout each on new levels."""
    rows = read_metrics(only_run_dir(finished[key][1]))
    student_steps = 0
    for r in rows:
        student_steps += (4 if r["replay"] == "1" else 2) * BATCH
        assert int(r["student_steps"]) == student_steps, r
        for name in ("protagonist", "antagonist"):
            for value in (float(r[f"{name}_return"]), float(r[f"{name}_solved"])):  # nan: no episode finished
                assert math.isnan(value) or 0 <= value <= 1
            assert (r[f"{name}_entropy"] != "") == (r["replay"] == "1")  # students train on replay only
    if key == "evo-flex":  # the flexible regret is never negative
        assert all(float(r["regret"]) >= 0 and float(r["buffer_mean_score"]) >= 0 for r in rows)


def test_accel_trains_on_replay_updates_only(finished):
    rows = read_metrics(only_run_dir(finished["accel"][1]))
    for r in rows:
        assert (r["policy_loss"] != "" and r["entropy"] != "") == (r["replay"] == "1")


def test_the_default_generator_starts_from_empty_rooms(finished):
    """ACCEL's and PAIRED+Evo's maze default plays empty rooms on its first new-level update, as the
    reference's ACCEL does; --generator random still plays the DR generator's levels."""
    empty = read_metrics(only_run_dir(finished["accel"][1]))
    random = read_metrics(only_run_dir(finished["accel-random"][1]))
    evo = read_metrics(only_run_dir(finished["evo"][1]))
    assert float(evo[0]["walls"]) == 0 and evo[0]["replay"] == "0"
    assert float(empty[0]["walls"]) == 0 and float(empty[0]["path_length"]) >= 1 and empty[0]["passable"] == "1"
    assert all(float(r["walls"]) == 0 for r in empty if r["replay"] == "0")
    # replayed levels grow from empty rooms by at most 5 edits per generation
    assert all(float(r["walls"]) <= 5 * int(r["update"]) for r in empty)
    assert float(random[0]["walls"]) > 0


def test_bidirectional_cloning_on_every_second_gradient_update(finished):
    rows = read_metrics(only_run_dir(finished["evo-bibc"][1]))
    gradient_updates = 0
    for r in rows:
        if r["replay"] == "1":
            gradient_updates += 1
        cloning = r["replay"] == "1" and gradient_updates % 2 == 0
        assert (r["kl_protagonist"] != "") == cloning, r
        assert (r["kl_antagonist"] != "") == cloning, r
        if cloning:
            assert float(r["kl_protagonist"]) > 0 and float(r["kl_antagonist"]) > 0
    assert gradient_updates >= 2, "no cloning update happened"
    plain = read_metrics(only_run_dir(finished["evo"][1]))
    assert all(r["kl_protagonist"] == "" and r["kl_antagonist"] == "" for r in plain)


@pytest.mark.parametrize("killed, straight", [("accel-killed", "accel"), ("evo-killed", "evo")])
def test_killed_run_resumes_to_the_same_result(finished, killed, straight):
    (ended_early, resumed), cwd = finished[killed]
    assert not ended_early, "the run ended before it could be killed"
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming" in resumed.stdout
    run_dir, straight_dir = only_run_dir(cwd), only_run_dir(finished[straight][1])
    expected, got = read_metrics(straight_dir), read_metrics(run_dir)
    assert len(expected) >= 5
    drop = lambda rows: [{k: v for k, v in r.items() if k != "sps"} for r in rows]  # noqa: E731
    assert drop(got) == drop(expected)
    assert json.load(open(os.path.join(run_dir, "eval.json"))) == json.load(open(os.path.join(straight_dir, "eval.json")))


def test_accel_budget_in_gradient_updates(tmp_path):
    """The paper trains ACCEL for 20k gradient updates: the maze default is that budget, without a step
    limit, and a run given --gradient-updates stops after exactly that many replay updates."""
    import accel

    args = accel.resolve_args(accel.paper_args(env="maze"))
    assert (args.gradient_updates, args.total_timesteps) == (20_000, 0)
    result = run("accel.py", [*TINY, *AT_END, "--total-timesteps", "0", "--gradient-updates", "3"], tmp_path)
    assert result.returncode == 0, result.stderr
    rows = read_metrics(only_run_dir(tmp_path))
    assert [int(r["gradient_updates"]) for r in rows][-1] == 3
    assert len(replay_rows(rows)) == 3 and rows[-1]["replay"] == "1"
    assert int(rows[-1]["env_steps"]) == BATCH * (len(rows) + 3)  # every replay update also plays the children
