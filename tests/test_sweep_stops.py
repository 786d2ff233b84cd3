"""The sweep launcher (results/sweep.py) stopping and continuing runs: the timeout bounds each run, not its
lane; a run stopped by a signal (as stopping the sweep stops it) ends its lane; a sweep file that raises a
finished run's budget continues it. The queue: test_sweep.py; resuming a killed sweep: test_sweep_resume.py."""

import json
import os
import signal
import subprocess
import sys
import time

from sweep_runs import LONG, ROOT, metric_rows, sweep, sweep_file, with_budget


def test_the_timeout_applies_to_each_run(tmp_path):
    """timeout_hours bounds each run, not the lane: with a limit of ~2 s, a run that cannot finish in time is
    stopped and reported, and the next run of the same lane still starts (and is stopped in turn)."""
    long = ["plr.py", *LONG]
    path = sweep_file(tmp_path / "sweep.toml", {"first": long, "second": long})
    text = (tmp_path / "sweep.toml").read_text().replace("timeout_hours = 1", "timeout_hours = 0.0006")
    (tmp_path / "sweep.toml").write_text(text)
    result = sweep(path, "--workdir", str(tmp_path))
    assert result.returncode == 1, result.stdout + result.stderr
    assert result.stdout.count("stopped after its timeout") == 2, result.stdout
    assert "ran second seed 1: stopped" in result.stdout and (tmp_path / "logs" / "second_1.log").is_file()


def test_a_run_killed_by_a_signal_ends_its_lane(tmp_path):
    """Stopping a run with SIGTERM (as stopping the sweep does) ends its lane: the next run does not start,
    as it would after a run that failed."""
    long = ["plr.py", *LONG]
    path = sweep_file(tmp_path / "sweep.toml", {"first": long, "second": long})
    process = subprocess.Popen([sys.executable, "-m", "results.sweep", path, "--workdir", str(tmp_path)], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and not list(tmp_path.glob("runs/maze__first__1__*/metrics.csv")):
        time.sleep(0.1)
    run = subprocess.run(["pgrep", "-f", "plr.py .*--exp-name first"], capture_output=True, text=True).stdout.split()
    assert len(run) == 1
    os.kill(int(run[0]), signal.SIGTERM)
    output, _ = process.communicate(timeout=120)
    assert process.returncode == 1 and "stopped by signal 15" in output, output
    assert not (tmp_path / "logs" / "second_1.log").exists()


def test_a_sweep_file_that_raises_the_budget_continues_its_finished_runs(tmp_path):
    """A finished DR run of 512 steps; the same sweep with a budget of 1024 and milestones continues it
    (it is not skipped as finished, nor started anew) to 1024, where its first end's evaluation is kept as
    eval_512.json; a third launch with the old budget skips it. Collecting a run still going copies its
    milestones so far and no eval.json."""
    short = with_budget(512)
    first = sweep_file(tmp_path / "first.toml", {"dr": ["plr.py", *short, "--replay-prob", "0"]})
    assert sweep(first, "--workdir", str(tmp_path)).returncode == 0
    (run,) = (tmp_path / "runs").glob("maze__dr__1__*")
    longer = sweep_file(tmp_path / "longer.toml", {"dr": ["plr.py", *short[:short.index("--total-timesteps")], "--total-timesteps", "1024",
                                                          "--milestones", "512", "1024", "--replay-prob", "0"]})
    result = sweep(longer, "--workdir", str(tmp_path))
    assert result.returncode == 0 and f"resumed {run}" in result.stdout, result.stdout + result.stderr
    assert [int(row.split(",")[0]) for row in metric_rows(run)] == list(range(1, 9))  # 1024 / 128 updates, once each
    assert {"eval.json", "eval_512.json", "eval_1024.json"} <= set(os.listdir(run))
    assert json.loads((run / "args.json").read_text())["total_timesteps"] == 1024
    again = sweep(first, "--workdir", str(tmp_path))
    assert again.returncode == 0 and "finished earlier" in again.stdout

    (run / "eval.json").unlink()  # as a run continued further would be, until its new end
    collected = tmp_path / "results"
    assert sweep(longer, "--workdir", str(tmp_path), "--collect", str(collected)).returncode == 0
    assert sorted(os.listdir(collected / "dr" / "1")) == ["args.json", "eval_1024.json", "eval_512.json", "levels.png", "metrics.csv"]
