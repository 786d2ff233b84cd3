"""Every run directory holds TensorBoard events beside metrics.csv: the same numbers, per update, and the
curriculum's level images."""

import csv
import os

import pytest
import script_runs
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# (--eval-episodes 0: no evaluation, which these tests do not read)
TINY = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", "--total-timesteps", "384", "--eval-episodes", "0",
        "--levels-interval", "2", "--checkpoint-interval", "1000"]


@pytest.mark.parametrize("script, extra, scalar", [
    ("plr.py", ["--replay-prob", "0"], "charts/walls"),  # DR: trains at every update
    ("paired.py", ["--teacher-conv-channels", "4"], "charts/regret"),
])
def test_runs_write_tensorboard_events(tmp_path, script, extra, scalar):
    result = script_runs.run([os.path.join(ROOT, script), *TINY, *extra], tmp_path, {**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    events = EventAccumulator(str(run_dir), size_guidance={"images": 0})
    events.Reload()
    with open(run_dir / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    logged = events.Scalars(scalar)
    column = scalar.split("/")[1]
    assert [e.step for e in logged] == [int(r["env_steps"]) for r in rows]
    assert [e.value for e in logged] == pytest.approx([float(r[column]) for r in rows], rel=1e-5)
    assert "losses/value_loss" in events.Tags()["scalars"] or "losses/protagonist_value_loss" in events.Tags()["scalars"]
    assert len(events.Images("curriculum/levels")) == 2  # updates 2 and 3 (the last)
