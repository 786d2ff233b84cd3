"""PAIRED's maze teacher on the device (envs/maze/teacher_on_device.py), checked on the CPU: the torch MDP equals
the numpy MDP step for step, its random numbers and the generator it leaves included; a design episode on the
device is the script's teacher_rollout with the same seed (levels, actions, log-probabilities, values); its
acting and MDP step trace as one graph with no break (so no host sync); PAIRED's scripts design through it when
it is chosen, and a run with it is the run without it."""

import csv
import os
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch._dynamo.testing import CompileCounterWithBackend

import paired
from envs.maze.env import CELL_ENCODING, EMPTY, GOAL, WALL, MazeEnv, MazeTeacher, MazeTeacherMDP
from envs.maze.teacher_on_device import MazeTeacherTorchMDP, TeacherDeviceRollout, act

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SETTINGS = {"maze": (60, True), "maze25": (25, False)}  # block budget, uniform budget
WALL_TYPE, EMPTY_TYPE, GOAL_TYPE = (int(CELL_ENCODING[code, 0]) for code in (WALL, EMPTY, GOAL))  # an image cell's first channel


@pytest.fixture(autouse=True)
def fast_paths_on(monkeypatch):
    monkeypatch.delenv("CLEANUED_PLAIN_NETS", raising=False)


def generator(seed: int, half_left: bool) -> np.random.Generator:
    """A PCG64 generator; with `half_left`, an odd number of float32s drawn, so that numpy keeps a 32-bit half
    of a word for its next float32 (the MDP's noise must start with it)."""
    rng = np.random.default_rng(seed)
    if half_left:
        rng.random(3, dtype=np.float32)
    assert rng.bit_generator.state["has_uint32"] == half_left
    return rng


def both_mdps(setting: str, seed: int, half_left: bool, size: int = 15):
    budget, uniform = SETTINGS[setting]
    return (MazeTeacherMDP(budget, uniform, generator(seed, half_left), size),
            MazeTeacherTorchMDP(budget, uniform, generator(seed, half_left), size))


def assert_same_observation(expected: dict, got: dict, where: str):
    assert set(got) == set(expected)
    for key, value in expected.items():
        assert got[key].dtype == torch.from_numpy(value).dtype, f"{key} at {where}"
        np.testing.assert_array_equal(got[key].numpy(), value, err_msg=f"{key} at {where}")


def assert_same_levels(expected, got):
    for field in ("walls", "goal", "agent", "agent_dir"):
        assert getattr(got, field).dtype == getattr(expected, field).dtype, field
        np.testing.assert_array_equal(getattr(got, field), getattr(expected, field), err_msg=field)


def play_both(numpy_mdp, torch_mdp, actions: np.ndarray):
    """Both MDPs through actions [T, n], every observation and done flag compared. -> the levels of both."""
    n = actions.shape[1]
    expected, got = numpy_mdp.reset(n), torch_mdp.reset(n)
    assert_same_observation(expected, got, "reset")
    for step, action in enumerate(actions):
        (expected, expected_done), (got, done) = numpy_mdp.step(action), torch_mdp.step(torch.from_numpy(action))
        assert done == expected_done and isinstance(done, bool)
        assert_same_observation(expected, got, f"step {step}")
    assert done
    return numpy_mdp.levels(), torch_mdp.levels()


@pytest.mark.parametrize("half_left", [False, True])
@pytest.mark.parametrize("size", [15, 9])
@pytest.mark.parametrize("setting", ["maze", "maze25"])
def test_torch_mdp_equals_numpy_mdp_step_for_step(setting, size, half_left):
    """Random design episodes of 24 levels (four seeds): every observation (grid image, time, noise) and done flag,
    the levels and the generator's state afterwards are the numpy MDP's. The actions favour 3 cells, so walls
    land on walls, the goal and the agent on walls and the agent on the goal (moved to a random free cell)
    many times; each happened."""
    events = {"wall on a wall": 0, "goal on a wall": 0, "agent on a wall": 0, "agent on the goal": 0}
    for seed in range(4):
        numpy_mdp, torch_mdp = both_mdps(setting, seed, half_left, size)
        rng = np.random.default_rng(100 + seed)
        actions = rng.integers(0, numpy_mdp.num_actions, (numpy_mdp.num_steps, 24))
        favoured = rng.random(actions.shape) < 0.6
        actions[favoured] = rng.integers(0, 3, int(favoured.sum()))
        numpy_mdp.reset(24)
        walls_before, budget = numpy_mdp.walls.copy(), None
        for step, action in enumerate(actions):  # the numpy MDP alone first, to count the events
            numpy_mdp.step(action)
            budget = numpy_mdp.budget
            x, y = action % numpy_mdp.interior + 1, action // numpy_mdp.interior + 1
            on_wall = walls_before[np.arange(24), y, x]
            events["wall on a wall"] += int((on_wall & (step < budget)).sum())
            events["goal on a wall"] += int((on_wall & (step == budget)).sum())
            events["agent on a wall"] += int((on_wall & (step == budget + 1)).sum())
            events["agent on the goal"] += int(((step == budget + 1) & (x == numpy_mdp.goal[:, 0]) & (y == numpy_mdp.goal[:, 1])).sum())
            walls_before = numpy_mdp.walls.copy()
        numpy_mdp, torch_mdp = both_mdps(setting, seed, half_left, size)
        expected, got = play_both(numpy_mdp, torch_mdp, actions)
        assert_same_levels(expected, got)
        assert torch_mdp.rng.bit_generator.state == numpy_mdp.rng.bit_generator.state
    assert all(count > 0 for count in events.values()), events


def test_hand_worked_fixed_budget_wall_on_a_wall_goal_on_a_wall_and_agent_on_the_goal():
    """Budget 3 (5 steps): walls at (1, 1), again at (1, 1) (no wall added) and at (3, 1); the goal at (3, 1)
    clears that wall; the agent at (3, 1), on the goal, moves to a random free cell (not a wall, not the goal):
    the one numpy draws."""
    numpy_mdp, torch_mdp = MazeTeacherMDP(3, False, np.random.default_rng(0)), MazeTeacherTorchMDP(3, False, np.random.default_rng(0))
    obs = torch_mdp.reset(1)
    images = [obs["image"][0, :, :, 0]]
    for action in (0, 0, 2, 2, 2):
        obs, done = torch_mdp.step(torch.tensor([action]))
        images.append(obs["image"][0, :, :, 0])
    assert done
    assert images[0][1:-1, 1:-1].eq(EMPTY_TYPE).all()
    assert images[1][1, 1] == WALL_TYPE and torch.equal(images[2], images[1]) and images[2][1:-1, 1:-1].eq(WALL_TYPE).sum() == 1
    assert images[3][1, 3] == WALL_TYPE and images[3][1:-1, 1:-1].eq(WALL_TYPE).sum() == 2
    assert images[4][1, 3] == GOAL_TYPE and images[4][1:-1, 1:-1].eq(WALL_TYPE).sum() == 1
    assert torch.equal(images[5], images[4])  # the agent is not drawn
    assert (obs["time"] == 4).all()
    levels = torch_mdp.levels()
    assert levels.walls[0, 1, 1] and not levels.walls[0, 1, 3] and levels.walls[0, 1:-1, 1:-1].sum() == 1
    assert tuple(levels.goal[0]) == (3, 1) and tuple(levels.agent[0]) not in {(3, 1), (1, 1)}
    numpy_mdp.reset(1)
    for action in (0, 0, 2, 2, 2):
        numpy_mdp.step([action])
    assert_same_levels(numpy_mdp.levels(), levels)


def test_hand_worked_uniform_budget_zero_walls_and_agent_on_a_wall():
    """Uniform budget: a first action below 169 / 60 sets 0 walls and is the goal, the next the agent, the rest
    no-ops. Budget 1 from a first action of 3 (3 * 60 // 169 = 1): a wall, then the goal, then the agent on
    the wall, which clears it."""
    mdp = MazeTeacherTorchMDP(60, True, np.random.default_rng(1))
    mdp.reset(2)
    first = [(0, 3), (5, 16), (7, 3), (30, 40)]  # level 0: goal (1, 1), agent (6, 1); level 1: wall (4, 1), goal (4, 2), agent (4, 1)
    for step in range(mdp.num_steps):
        action = first[step] if step < len(first) else (step % 169, (step * 7) % 169)
        obs, done = mdp.step(torch.tensor(action))
    assert done and mdp.t == 62
    levels = mdp.levels()
    assert levels.walls[:, 1:-1, 1:-1].sum() == 0  # level 1's only wall was cleared by its agent
    assert levels.goal.tolist() == [[1, 1], [4, 2]] and levels.agent.tolist() == [[6, 1], [4, 1]]
    assert obs["image"][1, 2, 4, 0] == GOAL_TYPE and obs["image"][1, 1, 4, 0] == EMPTY_TYPE


def test_the_torch_mdp_needs_a_pcg64_generator_and_ends_with_its_episode():
    with pytest.raises(TypeError, match="PCG64"):
        MazeTeacherTorchMDP(25, False, np.random.Generator(np.random.MT19937(0)))
    mdp = MazeTeacherTorchMDP(25, False, np.random.default_rng(0))
    mdp.reset(2)
    for _ in range(mdp.num_steps):
        mdp.step(torch.zeros(2, dtype=torch.long))
    with pytest.raises(ValueError, match="ended after 27 steps"):
        mdp.step(torch.zeros(2, dtype=torch.long))


def test_act_draws_torch_multinomial_s_action():
    """`act`'s draw (the largest probability over an exponential draw) is torch.multinomial's from the same
    random stream, and its log-probability, value and state are the plain net's Categorical and heads'."""
    torch.manual_seed(3)
    mdp = MazeTeacherTorchMDP(60, True, np.random.default_rng(0))
    teacher = MazeTeacher(mdp.num_steps, conv_channels=4)
    obs = mdp.reset(64)
    state, start = teacher.initial_state(64), torch.ones(64)
    with torch.no_grad():
        hidden, plain_state = teacher.lstm(teacher.features(obs), state, start)
        dist = torch.distributions.Categorical(logits=teacher.actor(hidden))
        torch.manual_seed(4)
        expected = torch.multinomial(dist.probs, 1, True).squeeze(1)
        torch.manual_seed(4)
        action, logprob, value, new_state = act(teacher, obs, state, start)
    assert torch.equal(action, expected) and len(set(action.tolist())) > 10
    assert torch.equal(logprob, dist.log_prob(action)) and torch.equal(value, teacher.critic(hidden).squeeze(-1))
    assert all(torch.equal(a, b) for a, b in zip(new_state, plain_state))


def concentrated_teacher(num_steps: int, seed: int) -> MazeTeacher:
    """A small teacher whose policy favours 3 cells, so its walls, goal and agent often collide."""
    torch.manual_seed(seed)
    teacher = MazeTeacher(num_steps, conv_channels=4)
    with torch.no_grad():
        teacher.actor[2].bias[[0, 1, 14]] += 4.0
    return teacher


def plain_and_device(setting: str, n: int, seed: int, teacher, device=torch.device("cpu"), graph: bool = False):
    """The same env twice (the same generator): its MDP and a teacher storage for the script's teacher_rollout,
    and a device player of the teacher with a storage of its own. -> both envs, the MDP, both storages, the player."""
    made = []
    for _ in range(2):
        env = MazeEnv(setting, n, seed=seed)
        mdp = env.teacher()
        made.append((env, mdp, paired.Rollout(mdp.reset(n), mdp.action_space, mdp.num_steps, n, device)))
    (plain_env, mdp, plain_storage), (device_env, device_mdp, device_storage) = made
    player = TeacherDeviceRollout(device_mdp, teacher, device_storage, device, graph=graph)
    return plain_env, device_env, mdp, plain_storage, device_storage, player


@pytest.mark.parametrize("plain_nets", [False, True])
@pytest.mark.parametrize("setting", ["maze", "maze25"])
def test_a_design_episode_on_the_device_is_the_scripts_teacher_rollout(setting, plain_nets, monkeypatch):
    """Three design episodes of 16 levels, each by paired.teacher_rollout (numpy MDP, the teacher's own acting
    step) and by the device player, from the same seeds, the second after an Adam step of the teacher: the
    same levels, stored observations, episode starts and actions, and the env's generator left in the same
    state; the same log-probabilities and values, bit for bit where the net runs plainly (the player runs the
    plain net), within float rounding of the teacher's fast path otherwise. Agents landed on the goal."""
    if plain_nets:
        monkeypatch.setenv("CLEANUED_PLAIN_NETS", "1")
    teacher = concentrated_teacher(SETTINGS[setting][0] + 2, seed=6)
    plain_env, device_env, mdp, plain_storage, device_storage, player = plain_and_device(setting, 16, 5, teacher)
    optimizer = torch.optim.Adam(teacher.parameters(), lr=1e-3)
    relocated = 0
    for episode in range(3):
        torch.manual_seed(10 + episode)
        expected = paired.teacher_rollout(teacher, mdp, plain_storage, SimpleNamespace(num_envs=16), torch.device("cpu"))
        torch.manual_seed(10 + episode)
        got = player()
        assert player.episodes == episode + 1  # the device path played it
        assert_same_levels(expected, got)
        assert device_env.rng.bit_generator.state == plain_env.rng.bit_generator.state
        for key in plain_storage.obs:
            assert torch.equal(device_storage.obs[key], plain_storage.obs[key]), key
        assert torch.equal(device_storage.episode_starts, plain_storage.episode_starts)
        assert torch.equal(device_storage.actions, plain_storage.actions)
        for name in ("logprobs", "values"):
            if plain_nets:
                assert torch.equal(getattr(device_storage, name), getattr(plain_storage, name)), name
            else:
                torch.testing.assert_close(getattr(device_storage, name), getattr(plain_storage, name), atol=1e-5, rtol=0)
        goal_steps = torch.as_tensor(mdp.budget)
        agent_actions = plain_storage.actions[goal_steps + 1, torch.arange(16)]
        relocated += int((agent_actions == plain_storage.actions[goal_steps, torch.arange(16)]).sum())
        if episode == 0:
            teacher.train()
            loss = -teacher.get_action_and_value({k: v.flatten(0, 1) for k, v in plain_storage.obs.items()}, teacher.initial_state(16),
                                                 plain_storage.episode_starts.flatten(), plain_storage.actions.flatten())[1].mean()
            loss.backward()
            optimizer.step()
            teacher.eval()
    assert relocated > 0


def test_the_acting_and_mdp_step_trace_as_one_graph():
    """torch.compile(fullgraph=True) traces the teacher's acting step with the MDP's step as one graph: no graph
    break, so no host sync (a read of a value, a branch on one, a shape that depends on data), which a CUDA
    graph could not hold. The steps differ only in the step count (a constant of each step's graph): the first
    three, which run every branch of the MDP's code, are traced, and every output equals the eager step's. The
    backend is aot_eager, as in tests/test_maze_on_device.py."""
    teacher = concentrated_teacher(62, seed=1)

    def design_step(mdp, obs, state, episode_start):
        action, logprob, value, state = act(teacher, obs, state, episode_start)
        obs, _ = mdp.step(action)
        return action, logprob, value, obs, state

    counter = CompileCounterWithBackend("aot_eager")
    compiled = torch.compile(design_step, fullgraph=True, dynamic=False, backend=counter)
    mdps = [MazeTeacherTorchMDP(60, True, np.random.default_rng(2)) for _ in range(2)]
    obs = [mdp.reset(4) for mdp in mdps]
    state = [teacher.initial_state(4)] * 2
    start = torch.ones(4)
    with torch.no_grad(), torch._dynamo.config.patch(allow_rnn=True):  # the LSTM's weights are read from its nn.LSTM
        for step in range(3):
            torch.manual_seed(step)
            got = compiled(mdps[0], obs[0], state[0], start)
            torch.manual_seed(step)
            expected = design_step(mdps[1], obs[1], state[1], start)
            for name, have, want in zip(("action", "logprob", "value"), got[:3], expected[:3]):
                torch.testing.assert_close(have, want, atol=1e-6, rtol=0, msg=f"{name} at step {step}")
            for key in expected[3]:
                assert torch.equal(got[3][key], expected[3][key]), key
            obs, state, start = [got[3], expected[3]], [got[4], expected[4]], torch.zeros(4)
    assert counter.frame_count == 3
    assert_same_levels(mdps[1].levels(), mdps[0].levels())


def run_paired(script: str, tmp_path, device_teacher: bool) -> tuple[list[dict], dict]:
    """Two tiny updates of a PAIRED script on the CPU in this process; with `device_teacher`, its designs played
    by the device player (forced on: a GPU would choose it; here it plays eagerly). -> metrics.csv's rows and
    the script's global names."""
    sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
    from gpu_check import run_script

    players = []

    def instrument(namespace):
        def forced(mdp, teacher, storage, args, device):
            players.append(TeacherDeviceRollout(mdp, teacher, storage, device, graph=False))
            return players[-1]

        if device_teacher:
            namespace["teacher_rollout_on_device"] = forced

    run_dir = tmp_path / ("device" if device_teacher else "plain")
    run_dir.mkdir()
    cwd = os.getcwd()
    os.chdir(run_dir)
    try:
        namespace = run_script(os.path.join(ROOT, script), ["--env", "maze", "--num-envs", "4", "--num-steps", "16", "--total-timesteps", "128",
                                                            "--eval-episodes", "1", "--eval-interval", "1000", "--teacher-conv-channels", "4",
                                                            "--no-cuda"], instrument)
    finally:
        os.chdir(cwd)
    if device_teacher:
        assert len(players) == 1 and players[0].episodes == 2  # it designed both updates' levels
    (metrics,) = [os.path.join(d, "metrics.csv") for d, _, files in os.walk(run_dir) if "metrics.csv" in files]
    with open(metrics) as f:
        return list(csv.DictReader(f)), namespace


@pytest.mark.parametrize("script", ["paired.py", "paired_hient.py", "paired_bc.py"])
def test_a_paired_run_with_the_device_teacher_is_the_run_without_it(script, tmp_path, monkeypatch, restore_torch_settings):
    """The same seed run with its designs by the device player and by teacher_rollout (the nets plain, so the
    player's log-probabilities are the script's to the bit): every logged number but the times is the same, and
    so is the trained teacher."""
    monkeypatch.setenv("CLEANUED_PLAIN_NETS", "1")
    with_device, device_names = run_paired(script, tmp_path, device_teacher=True)
    without, plain_names = run_paired(script, tmp_path, device_teacher=False)
    assert len(with_device) == len(without) == 2
    for got, expected in zip(with_device, without):
        assert {k: v for k, v in got.items() if not k.startswith("time_") and k != "sps"} == \
            {k: v for k, v in expected.items() if not k.startswith("time_") and k != "sps"}
    for (name, got), expected in zip(device_names["teacher"].state_dict().items(), plain_names["teacher"].state_dict().values()):
        assert torch.equal(got, expected), name


def test_the_device_teacher_is_the_registry_s_and_chosen_on_a_gpu_only(monkeypatch):
    """The maze's REGISTRY entries name TeacherDeviceRollout; on a CPU, with --no-device-rollouts or for an env
    without one the scripts keep teacher_rollout (teacher_rollout_on_device gives None); on a GPU otherwise it
    is built, as a CUDA graph (the class stood in for here: building it needs a GPU)."""
    import importlib

    import envs
    import envs.maze.teacher_on_device
    from envs.runs import teacher_rollout_on_device

    for setting in ("maze", "maze25"):
        module, name = envs.REGISTRY[setting].device_teacher_rollout.split(":")
        assert getattr(importlib.import_module(module), name) is TeacherDeviceRollout
    assert envs.REGISTRY["carracing"].device_teacher_rollout is None
    mdp = MazeEnv("maze", 2, seed=0).teacher()
    args = SimpleNamespace(env="maze", device_rollouts=True)
    gpu = torch.device("cuda")
    assert teacher_rollout_on_device(mdp, None, None, args, torch.device("cpu")) is None
    assert teacher_rollout_on_device(mdp, None, None, SimpleNamespace(env="maze", device_rollouts=False), gpu) is None
    assert teacher_rollout_on_device(mdp, None, None, SimpleNamespace(env="carracing", device_rollouts=True), gpu) is None
    built = []
    monkeypatch.setattr(envs.maze.teacher_on_device, "TeacherDeviceRollout", lambda *given, **options: built.append((given, options)) or "player")
    assert teacher_rollout_on_device(mdp, "teacher", "storage", args, gpu) == "player"
    assert built == [((mdp, "teacher", "storage", gpu), {"graph": True})]


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def gpu_pair(setting: str, seed: int, n: int = 32):
    """The paper's teacher on the GPU, for the script's teacher_rollout and the device player with its CUDA graph."""
    torch.manual_seed(seed)
    teacher = MazeTeacher(SETTINGS[setting][0] + 2).cuda()
    return teacher, *plain_and_device(setting, n, seed, teacher, torch.device("cuda"), graph=True)


@cuda
@pytest.mark.parametrize("setting", ["maze", "maze25"])
def test_on_a_gpu_the_design_episode_is_one_cuda_graph_that_designs_what_teacher_rollout_designs(setting):
    """Three episodes, an Adam step of the teacher after the first: replayed from one capture (the teacher's
    fast path moves its input weights once, at its first step: the capture follows), the same levels,
    actions and generator state as teacher_rollout's on the GPU, and log-probabilities and values within
    float rounding."""
    teacher, plain_env, device_env, mdp, plain_storage, device_storage, player = gpu_pair(setting, seed=3)
    optimizer = torch.optim.Adam(teacher.parameters(), lr=1e-4)
    for episode in range(3):
        torch.manual_seed(20 + episode)
        expected = paired.teacher_rollout(teacher, mdp, plain_storage, SimpleNamespace(num_envs=32), torch.device("cuda"))
        torch.manual_seed(20 + episode)
        got = player()
        assert_same_levels(expected, got)
        assert device_env.rng.bit_generator.state == plain_env.rng.bit_generator.state
        assert torch.equal(device_storage.actions, plain_storage.actions)
        for key in plain_storage.obs:
            assert torch.equal(device_storage.obs[key], plain_storage.obs[key]), key
        torch.testing.assert_close(device_storage.logprobs, plain_storage.logprobs, atol=1e-4, rtol=0)
        torch.testing.assert_close(device_storage.values, plain_storage.values, atol=1e-4, rtol=0)
        if episode == 0:
            graph = player.cuda_graph
            teacher.train()
            loss = -teacher.get_action_and_value({k: v.flatten(0, 1) for k, v in plain_storage.obs.items()}, teacher.initial_state(32, "cuda"),
                                                 plain_storage.episode_starts.flatten(), plain_storage.actions.flatten())[1].mean()
            loss.backward()
            optimizer.step()
            teacher.eval()
    assert player.graph_replays == 3 and player.cuda_graph is graph


@cuda
def test_on_a_gpu_a_design_episode_never_waits_for_the_device():
    """torch.cuda.set_sync_debug_mode("error") stays silent over a whole design episode, played eagerly and replayed."""
    *_, player = gpu_pair("maze", seed=4)
    player()  # the capture
    player.mdp.draw_words(32)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        player.play()
        player.replay_graph()
    finally:
        torch.cuda.set_sync_debug_mode("default")
