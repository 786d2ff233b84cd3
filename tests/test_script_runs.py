"""The tests' way of running a script (tests/script_runs.py) gives what `python ARGV` gives: the same status,
output, argv, working directory and environment, on a fork of the test process that keeps none of the run's
changes."""

import os
import signal
import subprocess
import sys
import time

import pytest
import script_runs
import torch

# What a run sees and does: its argv, directory and environment, both output streams and its exit status.
SHOWS_ITSELF = """
import os, sys
print("argv", sys.argv, "cwd", os.getcwd(), "X", os.environ.get("X"), "HOME" in os.environ)
print("to stderr", file=sys.stderr)
sys.exit(int(sys.argv[1]))
"""


def fresh(argv, cwd, env):
    return subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("status", ["0", "3"])
def test_a_run_gives_what_a_fresh_interpreter_gives(tmp_path, status):
    env = {"X": "y", "PATH": os.environ.get("PATH", "")}
    argv = ["-c", SHOWS_ITSELF, status, "more"]
    forked, expected = script_runs.run(argv, tmp_path, env), fresh(argv, tmp_path, env)
    assert (forked.returncode, forked.stdout, forked.stderr) == (expected.returncode, expected.stdout, expected.stderr)
    assert forked.returncode == int(status) and f"argv ['-c', '{status}', 'more'] cwd {tmp_path} X y False" in forked.stdout


def test_a_script_file_runs_as_main_and_a_failure_is_a_traceback_and_status_1(tmp_path):
    script = tmp_path / "fails.py"
    script.write_text("import sys\nprint(__name__, sys.argv[1:])\nraise ValueError('planted')\n")
    forked, expected = script_runs.run([str(script), "a"], tmp_path), fresh([str(script), "a"], tmp_path, None)
    assert (forked.returncode, forked.stdout) == (expected.returncode, expected.stdout) == (1, "__main__ ['a']\n")
    assert forked.stderr.startswith("Traceback") and forked.stderr.endswith("ValueError: planted\n")
    assert expected.stderr.endswith("ValueError: planted\n")


def test_runs_are_forks_that_keep_none_of_their_changes(tmp_path):
    """On Linux without a GPU the run is a fork of this process (it starts with torch's compiler front end
    imported, which a fresh interpreter has not), and what the script changes stays in the fork."""
    assert script_runs.forking() == (sys.platform == "linux" and not torch.cuda.is_available())
    code = ("import sys, torch; print('torch._dynamo' in sys.modules); torch.set_num_threads(3); "
            "import script_runs; script_runs.PRELOADED = ()")
    result = script_runs.run(["-c", code], tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"{script_runs.forking()}\n"
    assert torch.get_num_threads() == 1 and script_runs.PRELOADED  # as tests/conftest.py set them


def test_a_started_run_can_be_killed(tmp_path):
    process = script_runs.start(["-c", "import time; open('started', 'w').close(); time.sleep(60)"], tmp_path)
    deadline = time.time() + 30
    while not (tmp_path / "started").exists() and time.time() < deadline:
        time.sleep(0.01)
    assert process.poll() is None
    process.send_signal(signal.SIGKILL)
    assert process.wait(timeout=10) == -signal.SIGKILL
    with pytest.raises(subprocess.TimeoutExpired):
        script_runs.run(["-c", "import time; time.sleep(60)"], tmp_path, timeout=0.5)
