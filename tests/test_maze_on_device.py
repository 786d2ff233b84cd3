"""The maze's device path (envs/maze/on_device.py), checked on the CPU: the torch env equals the numpy env
step for step; a device rollout is what the numpy env and the plain net would have played with its
actions; its acting and env step compile as one graph with no break (so no host sync) and no recompile;
its derived weights are refreshed in place after an update."""

import copy
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch._dynamo.testing import CompileCounterWithBackend

import plr
from envs.maze.env import FORWARD, LEFT, RIGHT, MazeEnv, MazeStudent
from envs.maze.levels import MazeLevels, empty_grid
from envs.maze.on_device import DeviceRollout, MazeTorchEnv, act, observe, rollout_step
from envs.normalize import ReturnNormalizer
from test_fast_paths import FIXED_POLICY, student_with_a_fixed_policy


@pytest.fixture(autouse=True)
def fast_paths_on(monkeypatch):
    monkeypatch.delenv("CLEANUED_PLAIN_NETS", raising=False)


def levels_with_a_goal_ahead(env: MazeEnv, n: int, seed: int) -> MazeLevels:
    """n DR levels, the first replaced by an empty room whose agent starts facing east with the goal
    on the next cell east."""
    levels = env.random_levels(n, np.random.default_rng(seed))
    walls, goal, agent, agent_dir = levels.walls.copy(), levels.goal.copy(), levels.agent.copy(), levels.agent_dir.copy()
    walls[0] = empty_grid(1, walls.shape[1])[0]
    agent[0], goal[0], agent_dir[0] = (5, 5), (6, 5), 0
    return MazeLevels(walls, goal, agent, agent_dir)


@pytest.mark.parametrize("max_steps", [3, 40])
def test_torch_env_equals_numpy_env_step_for_step(max_steps):
    """Over 120 steps of random actions on DR levels: every observation, reward, termination and
    truncation is the numpy env's, across episode ends and timeouts. Copy 0 turns left, right, then steps
    onto the goal ahead: with max_steps 3 it reaches the goal on the episode's last step, which
    terminates (reward 0.1) and does not truncate; the random copies time out there."""
    numpy_env, torch_env = MazeEnv("maze", 16, seed=7), MazeTorchEnv(MazeEnv("maze", 16, seed=7), torch.device("cpu"))
    levels = levels_with_a_goal_ahead(numpy_env, 16, seed=1)
    expected, got = numpy_env.reset(levels, max_steps), torch_env.reset(levels, max_steps)
    rng = np.random.default_rng(2)
    schedule = [LEFT, RIGHT, FORWARD]
    ends = {"terminated": 0, "truncated": 0, "goal_on_last_step": 0}
    for step in range(120):
        actions = rng.integers(0, 7, 16)
        actions[0] = schedule[step % 3]
        for key in ("image", "direction"):
            np.testing.assert_array_equal(got[key].numpy(), expected[key], err_msg=f"{key} at step {step}")
        expected_step = numpy_env.step(actions)
        got_step = torch_env.step(torch.from_numpy(actions))
        expected, got = expected_step[0], got_step[0]
        for name, want, have in zip(("reward", "terminated", "truncated"), expected_step[1:4], got_step[1:4]):
            np.testing.assert_array_equal(have.numpy(), want, err_msg=f"{name} at step {step}")
        ends["terminated"] += int(expected_step[2].sum())
        ends["truncated"] += int(expected_step[3].sum())
        ends["goal_on_last_step"] += int(expected_step[2][0] and step % 3 == 2 and max_steps == 3)
    assert ends["terminated"] > 0 and ends["truncated"] > 0
    if max_steps == 3:
        assert ends["goal_on_last_step"] == 40 and np.isclose(expected_step[1][0], 0.1)


def replay_on_numpy_env_and_plain_net(agent, levels, storage, numpy_env: MazeEnv, advantages, episode_returns, gamma, gae_lambda):
    """The rollout in `storage`, played again: its actions through `numpy_env` (whose generator is where the
    device env's was, so the start directions agree) and its observations through the plain net (both on
    the CPU)."""
    agent = copy.deepcopy(agent).cpu()
    storage = SimpleNamespace(**{k: ({key: v.cpu() for key, v in value.items()} if k == "obs" else value.cpu())
                                 for k, value in vars(storage).items()})
    advantages = advantages.cpu()
    obs = numpy_env.reset(levels)
    running, returns = np.zeros(len(levels)), [[] for _ in range(len(levels))]
    ended = np.ones(len(levels), dtype=bool)
    for step, action in enumerate(storage.actions.numpy()):
        np.testing.assert_array_equal(storage.obs["image"][step].numpy(), obs["image"])
        np.testing.assert_array_equal(storage.obs["direction"][step].numpy(), obs["direction"])
        np.testing.assert_array_equal(storage.episode_starts[step].numpy(), ended)
        obs, reward, terminated, truncated, _ = numpy_env.step(action)
        ended = terminated | truncated
        np.testing.assert_array_equal(storage.rewards[step].numpy(), reward)
        running += reward
        for i in np.nonzero(ended)[0]:
            returns[i].append(running[i])
        running[ended] = 0.0
    np.testing.assert_array_equal(storage.last_step_ended.numpy(), ended)
    assert episode_returns == returns
    state = agent.initial_state(len(levels))
    with torch.no_grad():  # the plain net, step by step: with the action given, no fast path runs
        for step in range(len(storage.actions)):
            step_obs = {k: v[step] for k, v in storage.obs.items()}
            _, logprob, _, value, state = agent.get_action_and_value(step_obs, state, storage.episode_starts[step], storage.actions[step])
            torch.testing.assert_close(storage.logprobs[step], logprob, atol=1e-4, rtol=0)
            torch.testing.assert_close(storage.values[step], value, atol=1e-4, rtol=0)
        next_value = agent.get_value({k: torch.as_tensor(v) for k, v in obs.items()}, state, torch.as_tensor(ended).float())
    # GAE as the scripts compute it, on the host.
    values, rewards, starts = storage.values.numpy(), storage.rewards.numpy(), storage.episode_starts.numpy()
    next_nonterminal = 1.0 - np.concatenate([starts[1:], ended[None]]).astype(np.float32)
    delta = rewards + gamma * np.concatenate([values[1:], next_value.numpy()[None]]) * next_nonterminal - values
    expected, last = np.empty_like(rewards), np.zeros(len(levels), np.float32)
    for t in reversed(range(len(rewards))):
        last = delta[t] + gamma * gae_lambda * next_nonterminal[t] * last
        expected[t] = last
    np.testing.assert_allclose(advantages.numpy(), expected, atol=1e-4)


def device_rollout(agent, env, num_steps: int):
    storage = plr.Rollout(env, num_steps, env.num_envs, torch.device("cpu"))
    return DeviceRollout(env, agent, storage, 0.995, 0.95, torch.device("cpu"), graph=False), storage


def test_a_device_rollout_is_what_the_numpy_env_and_the_plain_net_play():
    """Two rollouts of 64 steps on the CPU (the second after an Adam step): the stored observations,
    episode starts, rewards and episode returns are the numpy env's under the stored actions; the
    log-probabilities and values the plain net's; the advantages the scripts' GAE. The fast path ran, and
    its derived weights were refreshed in place, equal to the ones derived anew."""
    torch.manual_seed(0)
    env, agent = MazeEnv("maze", 8, seed=11), MazeStudent()
    rollout, storage = device_rollout(agent, env, 64)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-2)
    for round in range(2):
        levels = levels_with_a_goal_ahead(env, 8, seed=round)
        seed_state = env.rng.bit_generator.state
        advantages, returns, episode_returns = rollout(levels)
        assert rollout.source_weights is agent.fast_path_state.weights  # acted on the fast path's weights
        replay_env = MazeEnv("maze", 8, seed=0)
        replay_env.rng.bit_generator.state = seed_state
        replay_on_numpy_env_and_plain_net(agent, levels, storage, replay_env, advantages, episode_returns, 0.995, 0.95)
        torch.testing.assert_close(returns, advantages + storage.values)
        if round == 0:
            addresses = {k: v.data_ptr() for k, v in rollout.weights.items() if k != "heads"}
            agent.train()
            loss = -agent.get_action_and_value({k: v.flatten(0, 1) for k, v in storage.obs.items()}, agent.initial_state(8),
                                               storage.episode_starts.flatten(), storage.actions.flatten())[1].mean()
            loss.backward()
            optimizer.step()
            agent.eval()
    assert {k: v.data_ptr() for k, v in rollout.weights.items() if k != "heads"} == addresses
    for key, derived in agent.fast_path_state.weights.items():
        for buffer, value in zip(rollout.weights[key] if key == "heads" else (rollout.weights[key],), derived if key == "heads" else (derived,)):
            assert torch.equal(buffer, value), key


class NarrowerStudent(MazeStudent):
    """A modified student (a subclass runs the plain path): an LSTM of 32."""

    def __init__(self):
        super().__init__(hidden_size=32)


def test_a_modified_student_plays_plain_on_the_device_env():
    torch.manual_seed(1)
    env, agent = MazeEnv("maze", 4, seed=3), NarrowerStudent()
    rollout, storage = device_rollout(agent, env, 40)
    levels = levels_with_a_goal_ahead(env, 4, seed=5)
    seed_state = env.rng.bit_generator.state
    advantages, _, episode_returns = rollout(levels)
    assert rollout.weights is None  # no derived weights: its own acting step ran
    replay_env = MazeEnv("maze", 4, seed=0)
    replay_env.rng.bit_generator.state = seed_state
    replay_on_numpy_env_and_plain_net(agent, levels, storage, replay_env, advantages, episode_returns, 0.995, 0.95)


def test_inverse_cdf_sampling_follows_the_policy():
    """`act`'s draws at uniform numbers are distributed as the policy, never an action of probability 0,
    and a uniform next to 1 still gives a valid action."""
    torch.manual_seed(5)
    probs, net = FIXED_POLICY, student_with_a_fixed_policy()
    n = 100_000
    obs = {"image": torch.zeros(n, 5, 5, 3, dtype=torch.uint8), "direction": torch.zeros(n, dtype=torch.long)}
    weights = net.FastPath.derive(net, obs)
    h = torch.zeros(n, 8)
    uniforms = torch.rand(n)
    uniforms[0] = 1.0 - 2**-24  # the largest float32 below 1
    action, logprob, _, _, _ = act(weights, obs, h, h.clone(), torch.ones(n, dtype=torch.bool), uniforms)
    counts = torch.bincount(action, minlength=7).float()
    assert counts[[1, 4, 5, 6]].sum() == 0 and action[0] == 3
    tolerance = 4 * torch.sqrt(probs * (1 - probs) / n)  # 4 standard errors
    assert torch.all((counts / n - probs).abs() <= tolerance + 1e-9)
    assert torch.allclose(logprob, torch.log(probs.clamp(min=1e-12))[action], atol=1e-5)


def test_the_acting_and_env_step_compile_as_one_graph_without_recompiling():
    """torch.compile(rollout_step, fullgraph=True, dynamic=False) traces the acting step with the env step
    as one graph: no graph break, so no host sync (a read of a value, a branch on one, a shape that
    depends on data), which a CUDA graph could not hold. Over three rollouts on new levels it compiles
    once, and every output equals the eager step's. The backend is aot_eager: the trace and the
    functionalized graph are what prove it, and the GPU path runs the eager ops in a CUDA graph, not
    inductor's kernels (whose C++ build would cost minutes here)."""
    torch.manual_seed(2)
    env, agent = MazeEnv("maze", 8, seed=4), MazeStudent()
    rollout, _ = device_rollout(agent, env, 4)
    counter = CompileCounterWithBackend("aot_eager")
    compiled = torch.compile(rollout_step, fullgraph=True, dynamic=False, backend=counter)
    for round in range(3):
        rollout(env.random_levels(8, np.random.default_rng(round)))  # refreshes the fixed input buffers
        layout = rollout.layout
        carry = {"pos": layout["start"].clone(), "direction": layout["start_dir"].clone(), "t": torch.zeros_like(layout["start"])}
        obs = observe(layout, carry["pos"], carry["direction"])
        h = torch.zeros(8, 256)
        eager = compiled_state = (obs, carry, h, h.clone(), torch.ones(8, dtype=torch.bool))
        for step in range(6):
            uniforms = torch.rand(8)
            got = compiled(rollout.weights, layout, 250, *compiled_state, uniforms)
            expected = rollout_step(rollout.weights, layout, 250, *eager, uniforms)
            for name, have, want in zip(("action", "logprob", "value", "reward"), got[:4], expected[:4]):
                torch.testing.assert_close(have, want, atol=1e-5, rtol=0, msg=f"{name} at step {step}")
            for key in ("image", "direction"):
                assert torch.equal(got[4][key], expected[4][key])
            compiled_state, eager = got[4:], expected[4:]
    assert counter.frame_count == 1


@pytest.mark.parametrize("script", ["plr.py", "paired.py"])
def test_the_scripts_play_their_maze_rollouts_through_the_device_player(script, tmp_path, monkeypatch, restore_torch_settings):
    """A curator and a PAIRED script (the two forms of the rollout function), 2 tiny updates on the CPU with the device player forced on (a GPU would choose
    it; here it runs its eager rollout): every student rollout is the device player's, and the run
    finishes with finite losses."""
    import csv
    import os
    import sys

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks"))
    from gpu_check import run_script

    played = []

    def instrument(namespace):
        def forced(env, agent, storage, args, device, normalizer=None):
            player = DeviceRollout(env, agent, storage, args.gamma, args.gae_lambda, device, graph=False)

            def counted(levels):
                played.append(len(levels))
                return player(levels)

            return counted

        namespace["rollouts_on_device"] = forced

    monkeypatch.chdir(tmp_path)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    flags = ["--level-buffer-size", "8"] if script == "plr.py" else ["--teacher-conv-channels", "4"]
    run_script(os.path.join(root, script), ["--env", "maze", "--num-envs", "4", "--num-steps", "16", "--total-timesteps", "128",
                                            "--eval-episodes", "0", "--no-cuda", *flags], instrument)
    assert len(played) >= 2 and set(played) == {4}
    (metrics,) = [os.path.join(d, "metrics.csv") for d, _, files in os.walk(tmp_path) if "metrics.csv" in files]
    with open(metrics) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2
    assert all(np.isfinite(float(value)) for row in rows for key, value in row.items() if value not in ("", None) and key.endswith("loss"))


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def gpu_rollout(seed: int, num_envs: int = 32, num_steps: int = 256):
    torch.manual_seed(seed)
    env, agent = MazeEnv("maze", num_envs, seed=seed), MazeStudent().cuda()
    storage = plr.Rollout(env, num_steps, num_envs, torch.device("cuda"))
    return env, agent, storage, DeviceRollout(env, agent, storage, 0.995, 0.95, torch.device("cuda"), graph=True)


@cuda
def test_on_a_gpu_the_rollout_is_one_cuda_graph_that_plays_the_numpy_env_and_the_plain_net():
    """The rollout is captured and replayed (three rollouts, one capture), and what it stores is what the
    numpy env and the plain net give under its actions."""
    env, agent, storage, rollout = gpu_rollout(3)
    for round in range(3):
        levels = levels_with_a_goal_ahead(env, 32, seed=round)
        seed_state = env.rng.bit_generator.state
        advantages, _, episode_returns = rollout(levels)
        replay_env = MazeEnv("maze", 32, seed=0)
        replay_env.rng.bit_generator.state = seed_state
        replay_on_numpy_env_and_plain_net(agent, levels, storage, replay_env, advantages, episode_returns, 0.995, 0.95)
    assert rollout.graph_replays == 3 and rollout.cuda_graph is not None


@cuda
def test_on_a_gpu_a_rollout_never_waits_for_the_device():
    """torch.cuda.set_sync_debug_mode("error") stays silent over a whole rollout, played eagerly and replayed."""
    env, agent, storage, rollout = gpu_rollout(4)
    rollout(env.random_levels(32, np.random.default_rng(0)))  # capture, and the derived weights' check
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        rollout.play()
        rollout.replay_graph()
    finally:
        torch.cuda.set_sync_debug_mode("default")


@cuda
def test_on_a_gpu_a_seed_repeats_and_replays_draw_fresh_actions():
    levels = MazeEnv("maze", 32, seed=0).random_levels(32, np.random.default_rng(1))
    actions = []
    for _ in range(2):
        env, agent, storage, rollout = gpu_rollout(5)
        rollout(levels)
        first = storage.actions.clone()
        rollout(levels)
        actions.append((first, storage.actions.clone()))
    assert torch.equal(actions[0][0], actions[1][0]) and torch.equal(actions[0][1], actions[1][1])
    assert not torch.equal(actions[0][0], actions[0][1])


def test_the_device_player_is_the_registry_s_and_chosen_on_a_gpu_only(monkeypatch):
    """The maze's REGISTRY entry names DeviceRollout; on a CPU, or with --no-device-rollouts, or with returns
    normalized, the scripts keep their own rollout (rollouts_on_device gives None); on a GPU otherwise, it
    is built, as a CUDA graph (the class stood in for here: building it needs a GPU)."""
    import importlib

    import envs
    import envs.maze.on_device
    from envs.runs import rollouts_on_device

    module, name = envs.REGISTRY["maze"].device_rollout.split(":")
    assert getattr(importlib.import_module(module), name) is DeviceRollout
    assert envs.REGISTRY["carracing"].device_rollout is None
    env = MazeEnv("maze", 2, seed=0)
    args = SimpleNamespace(env="maze", device_rollouts=True, gamma=0.995, gae_lambda=0.95)
    assert rollouts_on_device(env, MazeStudent(), None, args, torch.device("cpu")) is None
    gpu = torch.device("cuda")
    no_device_rollouts = SimpleNamespace(**{**vars(args), "device_rollouts": False})
    assert rollouts_on_device(env, MazeStudent(), None, no_device_rollouts, gpu) is None
    assert rollouts_on_device(env, MazeStudent(), None, args, gpu, normalizer=ReturnNormalizer(2, 0.995)) is None
    built = []
    monkeypatch.setattr(envs.maze.on_device, "DeviceRollout", lambda *given, **options: built.append((given, options)) or "player")
    agent = MazeStudent()
    assert rollouts_on_device(env, agent, None, args, gpu) == "player"
    assert built == [((env, agent, None, 0.995, 0.95, gpu), {"graph": True})]
