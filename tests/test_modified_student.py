"""A modified student trains, resumes and is evaluated as itself: a run records its student's class in
args.json (module:qualname), and `--resume` and `python -m envs.evaluate RUN` rebuild that class, or stop
with one `error:` line if it cannot be imported. The maze student's sizes are arguments, and its fast
path is derived, and checked, at other sizes too."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import torch
from test_fast_paths import as_torch, assert_fast_step_equals_plain

from envs.evaluate import main
from envs.evaluation import evaluate_all
from envs.maze import MazeEnv, MazeStudent

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = {**os.environ, "PYTHONPATH": ROOT, "OMP_NUM_THREADS": "1"}
# The recipe "change a network" of docs/modifying.md, followed in a copy of plr.py.
SMALL_STUDENT = '''

class SmallStudent(MazeStudent):
    """The maze student at other sizes."""

    FastPath = MazeStudentFastPath  # derived for any sizes, and checked against this net

    def __init__(self):
        super().__init__(hidden_size=32, conv_channels=4)
'''
TINY = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", "--total-timesteps", "256", "--level-buffer-size", "8",
        "--eval-episodes", "1", "--eval-interval", "100", "--levels-interval", "100", "--no-cuda"]


class NarrowStudent(MazeStudent):
    """The maze student with a smaller LSTM, for the evaluation below."""

    def __init__(self):
        super().__init__(hidden_size=24)


def fork_of_plr(folder) -> str:
    """plr.py copied as my_plr.py, training SmallStudent instead of the env's student."""
    with open(os.path.join(ROOT, "plr.py")) as f:
        source = f.read()
    imports = "from envs.training_run import TrainingRun\n"
    source = source.replace(imports, imports + "from envs.maze.fast_paths import MazeStudentFastPath\nfrom envs.maze import MazeStudent\n")
    source = source.replace("\n\n# The defaults written here", SMALL_STUDENT + "\n\n# The defaults written here")
    building = "agent = student_class(env, args.resume)().to(device)"
    assert building in source
    path = os.path.join(folder, "my_plr.py")
    with open(path, "w") as f:
        f.write(source.replace(building, "agent = SmallStudent().to(device)"))
    return path


def run(argv, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *argv], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=600)


def test_a_forked_script_with_another_student_resumes_and_is_evaluated(tmp_path):
    script = fork_of_plr(tmp_path)
    trained = run([script, *TINY], tmp_path)
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert "SmallStudent: fast path (derived from the plain net, checked against it)" in trained.stdout
    (name,) = os.listdir(tmp_path / "runs")
    run_dir = tmp_path / "runs" / name
    saved = json.loads((run_dir / "args.json").read_text())
    assert saved["student"] == "my_plr:SmallStudent"
    resumed = run([script, "--resume", str(run_dir)], tmp_path)  # a finished run: its checkpoint loads, it evaluates again
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    evaluated = run(["-m", "envs.evaluate", str(run_dir), "--no-capture-video"], tmp_path)
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    again, own = (json.loads((run_dir / path).read_text()) for path in ("evaluation/eval.json", "eval.json"))
    assert {name: again[name] for name in own} == own  # the run's own final evaluation, repeated

    (run_dir / "args.json").write_text(json.dumps({**saved, "student": "nowhere:SmallStudent"}))
    for argv in ([script, "--resume", str(run_dir)], ["-m", "envs.evaluate", str(run_dir)]):
        failed = run(argv, tmp_path)
        assert failed.returncode == 2 and len(failed.stderr.splitlines()) == 1, failed.stderr[-3000:]
        assert failed.stderr.startswith("error: cannot import the run's student class nowhere:SmallStudent")


def test_evaluate_rebuilds_the_student_class_a_run_recorded(tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "args.json").write_text(json.dumps({"env": "maze", "seed": 1, "eval_episodes": 1,
                                                   "student": f"{__name__}:NarrowStudent"}))
    student = NarrowStudent()
    torch.save({"agent": student.state_dict()}, run_dir / "checkpoint.pt")
    main([str(run_dir), "--levels", "FourRooms", "--no-capture-video"])
    expected = evaluate_all(student.eval(), "maze", ["FourRooms"], 1, 1, torch.device("cpu"))["FourRooms"]
    assert json.loads((run_dir / "evaluation" / "eval.json").read_text())["FourRooms"] == expected


def test_the_maze_students_fast_path_is_derived_at_other_sizes(monkeypatch, capsys):
    torch.manual_seed(3)
    net = MazeStudent(hidden_size=24, conv_channels=8)
    assert net.lstm.lstm.input_size == 8 * 3 * 3 + 5
    env = MazeEnv("maze", 6, seed=2)
    obs = as_torch(env.reset(env.random_levels(6, np.random.default_rng(2))))
    state = (torch.randn(1, 6, 24), torch.randn(1, 6, 24))
    assert_fast_step_equals_plain(net, obs, state, torch.tensor([0.0, 1, 0, 0, 1, 0]), monkeypatch)
    assert net.fast_path() is not None and net.fast_path_state.checked
    assert "warning" not in capsys.readouterr().out
