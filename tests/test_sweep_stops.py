"""The sweep launcher (results/sweep.py) stopping runs: the timeout bounds each run, not its lane, and a
run stopped by a signal (as stopping the sweep stops it) ends its lane. The queue: test_sweep.py."""

import os
import signal
import subprocess
import sys
import time

from sweep_runs import LONG, ROOT, sweep, sweep_file


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
