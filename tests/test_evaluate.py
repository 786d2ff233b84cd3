"""`python -m envs.evaluate` on tiny checkpoints made here: eval.json, the bar chart and one GIF per level;
one `error:` line and exit status 2 for bad input, before anything is written; a finished run's own
evaluation repeated. And the GIFs of envs/video.py on every env."""

import glob
import json
import os

import imageio.v3 as iio
import numpy as np
import pytest
import script_runs
import torch

import envs
import envs.evaluate
from envs.evaluate import main
from envs.evaluation import evaluate_all
from envs.runs import import_class
from envs.video import MAX_FRAMES, capture_videos

LEVELS = ["FourRooms", "SimpleCrossingS11N5"]  # the maze's two quickest held-out levels


def fresh_student(env_name: str, seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    env = envs.make(env_name, 1, 0)
    student = env.Student()
    env.close()
    return student


def gif_frames(path: str) -> np.ndarray:
    return iio.imread(path, index=None)


def test_a_state_dict_gets_eval_json_a_chart_and_a_gif_per_level(tmp_path):
    weights = tmp_path / "agent.pt"
    torch.save(fresh_student("maze").state_dict(), weights)
    out = tmp_path / "out"
    main([str(weights), "--env", "maze", "--levels", *LEVELS, "--episodes", "1", "--out", str(out)])
    results = json.loads((out / "eval.json").read_text())
    assert list(results) == [*LEVELS, "mean"]
    for r in results.values():
        assert 0.0 <= r["solved_rate"] <= 1.0
    assert results["mean"]["solved_rate"] == pytest.approx(np.mean([results[n]["solved_rate"] for n in LEVELS]))
    assert (out / "eval.png").stat().st_size > 0
    assert sorted(os.listdir(out / "videos")) == sorted(f"{name}.gif" for name in LEVELS)
    for name in LEVELS:
        frames = gif_frames(out / "videos" / f"{name}.gif")
        assert 1 <= len(frames) <= MAX_FRAMES and min(frames.shape[1:3]) >= 192


def test_a_run_directory_gives_its_env_and_the_paired_protagonist(tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    run.mkdir()
    (run / "args.json").write_text(json.dumps({"env": "maze", "seed": 3, "eval_episodes": 1}))
    protagonist = fresh_student("maze", seed=1)
    torch.save({"protagonist": protagonist.state_dict(), "antagonist": fresh_student("maze", seed=2).state_dict(),
                "update": 5}, run / "checkpoint.pt")
    evaluated = []  # the students evaluate_all was given, and the env and seed
    monkeypatch.setattr(envs.evaluate, "evaluate_all",
                        lambda student, env, *rest: evaluated.append((student, env, rest[2])) or evaluate_all(student, env, *rest))
    main([str(run), "--levels", "FourRooms", "--no-capture-video"])
    [(student, env_name, seed)] = evaluated
    assert (env_name, seed) == ("maze", 3)
    weights = student.state_dict()
    assert all(torch.equal(weights[k].cpu(), v) for k, v in protagonist.state_dict().items())  # not the antagonist
    out = run / "evaluation"
    assert sorted(os.listdir(out)) == ["eval.json", "eval.png"]
    assert list(json.loads((out / "eval.json").read_text())) == ["FourRooms", "mean"]
    assert "FourRooms" in capsys.readouterr().out


def test_the_student_class_committed_runs_record_still_imports():
    """The committed maze runs record their student as "envs.maze:MazeStudent" (args.json's "student"), which
    `python -m envs.evaluate` and --resume import through envs.runs.import_class: it is the maze's student,
    and the runs' agent.pt load into the class each records."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    recorded = set()
    for path in glob.glob(os.path.join(root, "results", "**", "args.json"), recursive=True):
        with open(path) as f:
            student = json.load(f).get("student")
        weights = os.path.join(os.path.dirname(path), "agent.pt")
        if student is not None:
            recorded.add(student)
            if os.path.exists(weights):
                import_class(student)().load_state_dict(torch.load(weights, map_location="cpu"))
    assert "envs.maze:MazeStudent" in recorded
    assert import_class("envs.maze:MazeStudent") is fresh_student("maze").__class__


def bad_input(tmp_path, capsys, argv) -> str:
    """The one error line of a rejected command; checks exit status 2 and that nothing was written."""
    out = tmp_path / "never"
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--out", str(out)])
    assert exit_info.value.code == 2
    stderr = capsys.readouterr().err.strip().splitlines()
    assert len(stderr) == 1 and stderr[0].startswith("error: ")
    assert not out.exists()
    return stderr[0]


def test_bad_input_is_one_error_line(tmp_path, capsys):
    maze_weights = tmp_path / "maze.pt"
    torch.save(fresh_student("maze").state_dict(), maze_weights)
    walker_weights = tmp_path / "walker.pt"
    torch.save(fresh_student("walker").state_dict(), walker_weights)
    not_torch = tmp_path / "notes.pt"
    not_torch.write_text("not a checkpoint")
    empty_run = tmp_path / "empty_run"
    empty_run.mkdir()
    assert "no run directory or file" in bad_input(tmp_path, capsys, [str(tmp_path / "missing")])
    assert "holds no checkpoint.pt or agent.pt" in bad_input(tmp_path, capsys, [str(empty_run)])
    assert "--env" in bad_input(tmp_path, capsys, [str(maze_weights)])  # no args.json to name the env
    assert "invalid choice" in bad_input(tmp_path, capsys, [str(maze_weights), "--env", "atari"])
    assert "unknown maze level 'Nowhere'" in bad_input(tmp_path, capsys, [str(maze_weights), "--env", "maze", "--levels", "Nowhere"])
    assert "does not hold a maze student" in bad_input(tmp_path, capsys, [str(walker_weights), "--env", "maze"])
    assert "does not hold a walker student" in bad_input(tmp_path, capsys, [str(maze_weights), "--env", "walker"])
    assert "not a PyTorch checkpoint" in bad_input(tmp_path, capsys, [str(not_torch), "--env", "maze"])
    assert "--episodes must be positive" in bad_input(tmp_path, capsys, [str(maze_weights), "--env", "maze", "--episodes", "0"])


@pytest.mark.parametrize("env_name, level", [("walker", "Stump"), ("carracing", "vanilla")])
def test_gifs_of_the_walker_and_carracing(tmp_path, env_name, level):
    paths = capture_videos(fresh_student(env_name), env_name, [level], 1, "cpu", str(tmp_path))
    frames = gif_frames(paths[level])
    assert 1 <= len(frames) <= MAX_FRAMES
    assert os.path.getsize(paths[level]) < 500_000


def test_capturing_videos_leaves_the_callers_random_stream_alone(tmp_path):
    student = fresh_student("maze")
    torch.manual_seed(7)
    capture_videos(student, "maze", ["FourRooms"], 1, "cpu", str(tmp_path))
    after_videos = torch.rand(3)
    torch.manual_seed(7)
    assert torch.equal(after_videos, torch.rand(3))


def test_a_finished_runs_checkpoint_gives_its_eval_json_again(tmp_path):
    """The defaults are the run's own: env, seed and episodes from args.json, the student of checkpoint.pt."""
    script = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "plr.py")
    tiny = ["--env", "maze", "--seed", "4", "--total-timesteps", "256", "--num-envs", "4", "--num-steps", "32",
            "--level-buffer-size", "8", "--eval-episodes", "2"]
    result = script_runs.run([script, *tiny], tmp_path, timeout=300)
    assert result.returncode == 0, result.stderr
    (name,) = os.listdir(tmp_path / "runs")
    run = tmp_path / "runs" / name
    main([str(run), "--no-capture-video"])
    assert json.loads((run / "evaluation" / "eval.json").read_text()) == json.loads((run / "eval.json").read_text())
