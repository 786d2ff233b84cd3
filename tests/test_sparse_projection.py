"""The maze teacher's fast path, its sparse input projection (envs/maze/sparse_projection.py), equals the plain
teacher: outputs and every gradient on teacher trajectories of both maze settings, acting step by step,
generic sequences, a float64 gradcheck, and three updates of paired.py."""

import ast
import concurrent.futures
import csv
import os

import numpy as np
import pytest
import script_runs
import torch
from torch import nn

from envs.maze.env import CELL_ENCODING, MazeTeacher, MazeTeacherMDP
from envs.maze.levels import empty_grid
from envs.maze.sparse_projection import MAX_CHANGED_FRACTION, sparse_gate_inputs
from test_fast_paths import count_calls

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SETTINGS = {"maze": (60, True), "maze25": (25, False)}  # (block budget, uniform budget) of MazeTeacherMDP


@pytest.fixture(autouse=True)
def cheap_init(monkeypatch):
    """The paper's teacher has ~22M LSTM input weights; their orthogonal init takes seconds and is not
    what these tests check. (And the fast paths are on.)"""
    monkeypatch.setattr(nn.init, "orthogonal_", lambda tensor, gain=1.0: nn.init.normal_(tensor, 0.0, 0.05 * gain))
    monkeypatch.delenv("CLEANUED_PLAIN_NETS", raising=False)


def run(plain: bool, function, *args):
    """function(*args) on the plain nets (CLEANUED_PLAIN_NETS=1) or with the fast paths."""
    with pytest.MonkeyPatch.context() as patch:
        if plain:
            patch.setenv("CLEANUED_PLAIN_NETS", "1")
        return function(*args)


def teacher_episode(budget: int, uniform: bool, num_copies: int, seed: int, size: int = 15):
    """One teacher episode per copy (at least 4) by random actions, as the training storage holds it:
    the observations before each step, time-major [T * N]. Copy 0 gets a budget of 0 walls (with the
    uniform budget) and puts its agent on the goal; copy 1 repeats wall cells (no-op steps); copy 2
    puts its goal and copy 3 its agent on a wall. Returns the observations and the MDP after the episode."""
    rng = np.random.default_rng(seed)
    mdp = MazeTeacherMDP(budget, uniform, rng, size)
    obs = mdp.reset(num_copies)
    steps = []
    for t in range(mdp.num_steps):
        steps.append(obs)
        actions = rng.integers(0, mdp.num_actions, num_copies)
        if uniform and t == 0:
            actions[0] = 1  # int(1 / 169 * 60) = 0 walls: this is the goal
            actions[1:4] = mdp.num_actions - 1  # 59 walls
        if uniform and t == 1:
            actions[0] = 1  # the agent on the goal
        if 1 <= t <= 6:
            actions[1] = 7 + t % 2  # two cells, placed again and again
        if t == (40 if uniform else budget - 1):
            actions[2:4] = 11
        if t == mdp.budget[2]:
            actions[2] = 11  # the goal on a wall
        if t == mdp.budget[3] + 1:
            actions[3] = 11  # the agent on a wall
        if not uniform and t >= mdp.budget[0]:
            actions[0] = 3  # the goal, then the agent on it
        obs, _ = mdp.step(actions)
    batch = {k: torch.as_tensor(np.concatenate([step[k] for step in steps])) for k in steps[0]}
    return batch, mdp


def assert_episode_has_the_cases(batch, mdp, setting, num_copies):
    images = batch["image"].view(mdp.num_steps, num_copies, *batch["image"].shape[1:])
    unchanged = (images[1:] == images[:-1]).flatten(2).all(2)  # [T - 1, N]
    assert unchanged[:, 1].any() and not unchanged.all()  # no-op steps, and changes
    if setting == "maze":
        assert mdp.budget[0] == 0 and unchanged[1:, 0].all()
    assert (mdp.agent[0] != mdp.goal[0]).any()  # the agent placed on the goal moved away
    assert not mdp.walls[2, mdp.goal[2, 1], mdp.goal[2, 0]]


def losses_and_grads(net, batch, num_copies, done, weights):
    """The training path's logits and values, and every gradient (parameters and the noise input) of a
    random linear function of them."""
    net.zero_grad()
    obs = {**batch, "noise": batch["noise"].clone().requires_grad_()}
    dist, value = net.dist_and_value(obs, net.initial_state(num_copies), done)
    loss = (dist.logits * weights[0]).sum() + (value * weights[1]).sum()
    loss.backward()
    grads = {name: p.grad.clone() for name, p in net.named_parameters()}
    return dist.logits.detach(), value.detach(), {**grads, "noise": obs["noise"].grad}


def assert_matches_dense(net, batch, num_copies, sparse: bool, done=None):
    """The fast path's outputs and gradients equal the plain net's, which computes the dense features;
    the fast path projects the batch sparsely if `sparse`, else hands it over to the dense path. `done`
    marks episode starts (by default: the first step of every copy)."""
    if done is None:
        done = torch.zeros(len(batch["time"]))
        done[:num_copies] = 1.0
    torch.manual_seed(5)
    weights = (torch.randn(len(batch["time"]), net.actor[-1].out_features), torch.randn(len(batch["time"])))
    with pytest.MonkeyPatch.context() as patch:
        projections = count_calls(patch, "sparse_gate_inputs")  # per call: whether it projected (or handed over)
        fast = run(False, losses_and_grads, net, batch, num_copies, done, weights)
    assert projections == [sparse]
    dense = run(True, losses_and_grads, net, batch, num_copies, done, weights)
    for got, expected in zip(fast[:2], dense[:2]):
        assert torch.allclose(got, expected, rtol=1e-4, atol=1e-5)
    assert fast[2].keys() == dense[2].keys()
    for name, expected in dense[2].items():
        scale = expected.abs().max()
        assert scale > 0, name
        assert torch.allclose(fast[2][name], expected, rtol=1e-3, atol=1e-4 * scale), name


@pytest.mark.parametrize("setting", ["maze", "maze25"])
@pytest.mark.parametrize("channels", [3, 128])
def test_training_path_equals_dense_on_teacher_episodes(setting, channels):
    torch.manual_seed(0)
    num_copies = 6
    batch, mdp = teacher_episode(*SETTINGS[setting], num_copies, seed=channels)
    assert_episode_has_the_cases(batch, mdp, setting, num_copies)
    net = MazeTeacher(mdp.num_steps, conv_channels=channels)
    assert_matches_dense(net, batch, num_copies, sparse=True)


def test_training_path_equals_dense_on_generic_sequences():
    """Sequences no teacher makes: cells anywhere (the outer ring too) change, several per step, an episode
    restarts mid-sequence, the first image is not the empty grid; and random images, where too many cells
    change for the sparse path, which hands over to the dense one."""
    torch.manual_seed(1)
    rng = np.random.default_rng(1)
    steps, num_copies, size = 12, 3, 15
    codes = empty_grid(num_copies, size).astype(np.int64)
    images = []
    for t in range(steps):
        for n in range(num_copies):
            if t == 0 or rng.random() < 0.6:
                for _ in range(rng.integers(1, 3)):
                    codes[n, rng.integers(0, size), rng.integers(0, size)] = rng.integers(0, 3)
        images.append(CELL_ENCODING[codes])
    batch = {"image": torch.as_tensor(np.concatenate(images)), "time": torch.as_tensor(rng.integers(0, 27, steps * num_copies)),
             "noise": torch.rand(steps * num_copies, 50)}
    net = MazeTeacher(27, conv_channels=5)
    done = torch.zeros(steps * num_copies)
    done[[0, 1, 2, 5 * num_copies + 1]] = 1.0
    assert_matches_dense(net, batch, num_copies, sparse=True, done=done)

    random_images = {**batch, "image": torch.randint(0, 10, batch["image"].shape, dtype=torch.uint8)}
    assert MAX_CHANGED_FRACTION < 1
    assert_matches_dense(net, random_images, num_copies, sparse=False)


def acting_step(net, obs, state, fast: bool = False):
    """An acting step from seed 9; asserted to run on the fast path if `fast`."""
    torch.manual_seed(9)
    with pytest.MonkeyPatch.context() as patch:
        fast_acts = count_calls(patch, "act_from_gate_inputs")
        with torch.no_grad():
            result = net.get_action_and_value(obs, state, torch.zeros(len(obs["time"])))
    assert not fast or fast_acts == [True]
    return result


@pytest.mark.parametrize("setting", ["maze", "maze25"])
def test_acting_path_equals_dense(setting):
    """Acting step by step (the running W f(I) per copy) gives the plain teacher's action, log-probability,
    value and new state from the same given state, over two episodes in a row, a step with new random
    images (the dense fallback), a smaller batch, and after a weight change."""
    torch.manual_seed(2)
    num_copies = 5
    net = MazeTeacher(SETTINGS[setting][0] + 2, conv_channels=128)
    episodes = [teacher_episode(*SETTINGS[setting], num_copies, seed)[0] for seed in (3, 4)]
    random_images = {**episodes[0], "image": torch.randint(0, 10, episodes[0]["image"].shape, dtype=torch.uint8)}

    def split(episode, copies):
        return [{k: v[t * num_copies : t * num_copies + copies] for k, v in episode.items()} for t in range(len(episode["time"]) // num_copies)]

    steps = split(episodes[0], num_copies) + split(episodes[1], num_copies) + split(random_images, num_copies) + split(episodes[1], 2)
    hidden = net.lstm.hidden_size
    states = {n: (torch.randn(1, n, hidden), torch.randn(1, n, hidden)) for n in (2, num_copies)}

    def check(steps):
        for step in steps:
            state = states[len(step["time"])]
            fast, plain = run(False, acting_step, net, step, state, True), run(True, acting_step, net, step, state)
            assert torch.equal(fast[0], plain[0])
            for got, expected in zip((*fast[1:4], *fast[4]), (*plain[1:4], *plain[4])):
                assert torch.allclose(got, expected, rtol=1e-4, atol=1e-5)

    check(steps)
    # An episode's first image is the empty grid, the reference: its copies restart exactly from
    # W f(I_ref), rounding from the earlier episodes gone.
    for step in split(episodes[1], num_copies)[:20] + split(episodes[0], num_copies)[:1]:
        acting_step(net, step, states[num_copies], True)
    running = net.fast_path_state.weights["running_conv_gates"]
    assert torch.equal(running.gates, running.start_gates.expand(num_copies, -1))
    with torch.no_grad():
        net.lstm.lstm.weight_ih_l0.mul_(1.5)
    check(steps[: len(steps) // 3])


class SparseGates(nn.Module):
    """sparse_gate_inputs on this module's conv: torch.func.functional_call then swaps in the conv's
    weights as gradcheck's inputs."""

    def __init__(self, conv):
        super().__init__()
        self.conv = conv

    def forward(self, reference, images, dense_inputs, weight_ih, bias, num_copies):
        return sparse_gate_inputs(self.conv, 10.0, reference, images, dense_inputs, weight_ih, bias, num_copies, max_changed_fraction=1.0)


def test_gradcheck_float64_small_grid():
    """float64 gradcheck of every input of the sparse projection (conv weight and bias, W_ih, bias, the dense
    inputs) on a 7x7 grid with 2 channels, and its value equal to the dense projection. (A changed cell
    there touches up to 9 of 25 windows: the sparse path is forced.)"""
    torch.manual_seed(3)
    num_copies = 4
    batch, mdp = teacher_episode(6, False, num_copies, seed=3, size=7)
    images = batch["image"]
    reference = torch.as_tensor(CELL_ENCODING[empty_grid(1, 7)[0].astype(np.uint8)])
    conv = nn.Conv2d(3, 2, 3).double()
    gates = SparseGates(conv)
    features = 2 * 5 * 5 + 4
    inputs = (conv.weight.detach().clone(), conv.bias.detach().clone(), torch.randn(12, features, dtype=torch.float64),
              torch.randn(12, dtype=torch.float64), torch.randn(len(images), 4, dtype=torch.float64))
    inputs = tuple(x.requires_grad_() for x in inputs)

    def projection(conv_weight, conv_bias, weight_ih, bias, dense_inputs):
        out = torch.func.functional_call(gates, {"conv.weight": conv_weight, "conv.bias": conv_bias},
                                         (reference, images, dense_inputs, weight_ih, bias, num_copies))
        assert out is not None
        return out

    assert torch.autograd.gradcheck(projection, inputs)
    with torch.no_grad():
        dense_features = torch.relu(conv(images.permute(0, 3, 1, 2).double() / 10.0)).flatten(1)
        dense = torch.addmm(inputs[3], torch.cat([dense_features, inputs[4]], 1), inputs[2].t())
        assert torch.allclose(projection(*inputs), dense, atol=1e-10)


# Runs a script as `python SCRIPT ARGS` would, counting the calls of the fast paths' acting steps and of
# the teacher's sparse projection, by whether each ran (returned a result) or handed over to the plain
# path: "fast path calls: {...}" at exit.
COUNTING_FAST_PATHS = """
import atexit, collections, runpy, sys
from envs.maze import fast_paths
calls = collections.Counter()
def counted(name, function):
    def call(*args, **kwargs):
        result = function(*args, **kwargs)
        calls[name + (" ran" if result is not None else " handed over")] += 1
        return result
    return call
fast_paths.sparse_gate_inputs = counted("sparse projection", fast_paths.sparse_gate_inputs)
for fast_path in (fast_paths.MazeStudentFastPath, fast_paths.MazeTeacherFastPath):
    fast_path.act = counted(fast_path.__name__ + ".act", fast_path.act)
atexit.register(lambda: print("fast path calls:", dict(calls)))
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def test_paired_updates_equal_plain_nets(tmp_path):
    """Two updates of paired.py with the paper's teacher log the same metrics with the fast paths (all
    three nets act on theirs, the second time with the weights the first update trained, and the teacher
    trains on its sparse projection) as with CLEANUED_PLAIN_NETS=1 (timings aside)."""
    args = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", "--total-timesteps", "256", "--eval-interval", "1000",
            "--eval-episodes", "1", "--levels-interval", "1000", "--checkpoint-interval", "1000"]

    def run_script(mode):
        cwd = tmp_path / mode
        cwd.mkdir()
        env = {**os.environ, "OMP_NUM_THREADS": "1", "CLEANUED_PLAIN_NETS": "1" if mode == "plain" else "0", "PYTHONPATH": ROOT}
        result = script_runs.run(["-c", COUNTING_FAST_PATHS, os.path.join(ROOT, "paired.py"), *args], cwd, env)
        assert result.returncode == 0, result.stderr
        lines = result.stdout.splitlines()
        announced = sorted(line for line in lines if line.startswith(("MazeStudent: ", "MazeTeacher: ", "warning: ")))
        (calls,) = [ast.literal_eval(line.removeprefix("fast path calls: ")) for line in lines if line.startswith("fast path calls: ")]
        (run_dir,) = (cwd / "runs").iterdir()
        with open(run_dir / "metrics.csv", newline="") as f:
            return list(csv.DictReader(f)), announced, calls

    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        (fast, fast_announced, fast_calls), (plain, plain_announced, plain_calls) = pool.map(run_script, ["fast", "plain"])
    checked = "fast path (derived from the plain net, checked against it)"
    assert fast_announced == [f"MazeStudent: {checked}"] * 2 + [f"MazeTeacher: {checked}"]
    assert sorted(fast_calls) == ["MazeStudentFastPath.act ran", "MazeTeacherFastPath.act ran", "sparse projection ran"]
    assert plain_announced == ["MazeStudent: plain path (CLEANUED_PLAIN_NETS=1)"] * 2 + ["MazeTeacher: plain path (CLEANUED_PLAIN_NETS=1)"]
    assert plain_calls == {}
    assert len(fast) == len(plain) == 2
    for got, expected in zip(fast, plain):
        for column, value in expected.items():
            if column == "sps" or column.startswith("time_"):
                continue
            if value in ("", "nan"):
                assert got[column] == value, column
            else:
                assert float(got[column]) == pytest.approx(float(value), rel=1e-4, abs=1e-6), column
