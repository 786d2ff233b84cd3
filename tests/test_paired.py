"""PAIRED's parts on worked examples (paired.py, paired_hient.py, paired_bc.py): the regret, GAE for the
students and for the teacher's one-reward episode, the behavioural-cloning KL of PAIRED+BC and its
schedule, bad input and the paper's defaults per script and env."""

import concurrent.futures
import copy
import csv
import os

import gymnasium as gym
import numpy as np
import pytest
import script_runs
import torch

import paired
import paired_bc
import paired_hient
from envs.evaluation import to_torch
from envs.maze import MazeEnv

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# One torch thread per run: on a loaded 2-core machine, two busy-waiting OpenMP threads per
# process slow the small ops of these runs down by an order of magnitude.
SUBPROCESS_ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """The same for the in-process tests (restored afterwards)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ---------------------------------------------------------------------------------------------------
# The regret (Algorithm 1, line 8)
# ---------------------------------------------------------------------------------------------------
def test_regret_is_max_antagonist_minus_mean_protagonist_per_level():
    protagonist = [[0.5, 0.7], [0.2, 0.4, 0.9], [0.6]]
    antagonist = [[0.9, 0.1], [0.3, 0.8], [0.95, 0.2, 0.7]]
    # level 0: 0.9 - 0.6 = 0.3; level 1: 0.8 - 0.5 = 0.3; level 2: 0.95 - 0.6 = 0.35
    assert np.allclose(paired.regret(protagonist, antagonist), [0.3, 0.3, 0.35])


def test_regret_counts_a_student_without_completed_episode_as_zero():
    protagonist = [[], [0.4], [], [0.3, 0.5]]
    antagonist = [[0.8, 0.6], [], [], [0.9]]
    # level 0: 0.8 - 0; level 1: 0 - 0.4 < 0 -> 0; level 2: nothing finished -> 0; level 3: 0.9 - 0.4
    assert np.allclose(paired.regret(protagonist, antagonist), [0.8, 0.0, 0.0, 0.5])


def test_regret_clips_a_negative_difference_to_zero():
    # The protagonist's mean (0.85) beats the antagonist's best (0.7): regret 0, not -0.15. Only the
    # antagonist's max counts: its mean (0.4) would give another (also clipped) value.
    result = paired.regret([[0.8, 0.9], [0.1, 0.9]], [[0.1, 0.7], [0.1, 0.7]])
    assert np.allclose(result, [0.0, 0.2])
    assert result.shape == (2,)


# ---------------------------------------------------------------------------------------------------
# GAE on tiny hand-worked rollouts
# ---------------------------------------------------------------------------------------------------
def storage_of(rewards, values, episode_starts):
    storage = paired.Rollout({"x": np.zeros((len(rewards[0]), 1), np.float32)}, gym.spaces.Discrete(2), len(rewards), len(rewards[0]), "cpu")
    storage.rewards[:] = torch.tensor(rewards)
    storage.values[:] = torch.tensor(values)
    storage.episode_starts[:] = torch.tensor(episode_starts)
    return storage


def test_gae_hand_worked_with_a_reset_and_a_bootstrap():
    gamma, lam = 0.9, 0.8  # gamma * lambda = 0.72
    # Time-major [3 steps, 2 copies]. Copy 0: an episode ends after step 1 (done[2] = 1 marks the next
    # episode's start), the unfinished one at step 2 is bootstrapped from next_value 0.4.
    # Copy 1: one episode that ends at the last step (next_done = 1): nothing is bootstrapped.
    storage = storage_of(rewards=[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]],
                         values=[[0.5, 0.1], [0.6, 0.2], [0.2, 0.3]],
                         episode_starts=[[1.0, 1.0], [0.0, 0.0], [1.0, 0.0]])
    next_value, next_done = torch.tensor([0.4, 0.7]), torch.tensor([0.0, 1.0])
    advantages, returns = paired.gae(storage, next_value, next_done, gamma, lam)
    # copy 0: d2 = 0 + 0.9 * 0.4 - 0.2 = 0.16           A2 = 0.16
    #         d1 = 1 - 0.6 = 0.4 (terminal)              A1 = 0.4
    #         d0 = 0 + 0.9 * 0.6 - 0.5 = 0.04            A0 = 0.04 + 0.72 * 0.4 = 0.328
    # copy 1: d2 = 1 - 0.3 = 0.7 (terminal)              A2 = 0.7
    #         d1 = 0 + 0.9 * 0.3 - 0.2 = 0.07            A1 = 0.07 + 0.72 * 0.7 = 0.574
    #         d0 = 0 + 0.9 * 0.2 - 0.1 = 0.08            A0 = 0.08 + 0.72 * 0.574 = 0.49328
    expected = torch.tensor([[0.328, 0.49328], [0.4, 0.574], [0.16, 0.7]])
    assert torch.allclose(advantages, expected, atol=1e-6)
    assert torch.allclose(returns, expected + storage.values, atol=1e-6)


def test_gae_one_step_is_the_td_error():
    storage = storage_of(rewards=[[0.5]], values=[[0.25]], episode_starts=[[1.0]])
    advantages, _ = paired.gae(storage, torch.tensor([2.0]), torch.tensor([0.0]), 0.5, 0.9)
    assert torch.allclose(advantages, torch.tensor([[0.5 + 0.5 * 2.0 - 0.25]]))


def teacher_gae(regret, values, gamma, lam, next_value=0.0):
    """GAE as paired.py's main loop does it for the teacher: the reward (the regret) only at the last
    step, an episode start only at t = 0, next_done = 1 (the teacher's episode ends with the level)."""
    n = len(regret)
    storage = storage_of(rewards=[[0.0] * n, [0.0] * n, list(regret)], values=values,
                         episode_starts=[[1.0] * n, [0.0] * n, [0.0] * n])
    return paired.gae(storage, torch.full((n,), next_value), torch.ones(n), gamma, lam)


def test_teacher_regret_at_the_final_step_hand_worked_for_t_3():
    gamma, lam = 0.9, 0.8
    regret = [0.5, 0.0]
    values = [[0.1, 0.3], [0.2, 0.1], [0.4, 0.2]]
    advantages, returns = teacher_gae(regret, values, gamma, lam)
    # d_t = gamma * V_{t+1} - V_t for t < 2 (no reward before the end), d_2 = regret - V_2;
    # A_t = sum_k (gamma * lambda)^(k - t) d_k.
    for i in range(2):
        v0, v1, v2 = values[0][i], values[1][i], values[2][i]
        d0, d1, d2 = gamma * v1 - v0, gamma * v2 - v1, regret[i] - v2
        a2 = d2
        a1 = d1 + gamma * lam * d2
        a0 = d0 + gamma * lam * d1 + (gamma * lam) ** 2 * d2
        assert torch.allclose(advantages[:, i], torch.tensor([a0, a1, a2]), atol=1e-6)
    # copy 0 by the numbers: d = (0.08, 0.16, 0.1) -> A = (0.08 + 0.72 * 0.16 + 0.5184 * 0.1, 0.232, 0.1)
    assert torch.allclose(advantages[:, 0], torch.tensor([0.24704, 0.232, 0.1]), atol=1e-6)
    assert torch.allclose(returns, advantages + torch.tensor(values), atol=1e-6)


def test_teacher_return_is_the_discounted_regret_and_nothing_is_bootstrapped():
    gamma = 0.9
    regret = [0.5, 0.25, 0.0]
    values = [[0.1, 0.3, 0.0], [0.2, 0.1, 0.0], [0.4, 0.2, 0.0]]
    # lambda = 1: A_t = gamma^(T - 1 - t) * regret - V_t, the Monte Carlo return minus the value.
    advantages, returns = teacher_gae(regret, values, gamma, 1.0)
    expected_returns = torch.tensor([[gamma ** (2 - t) * r for r in regret] for t in range(3)])
    assert torch.allclose(returns, expected_returns, atol=1e-6)
    assert torch.allclose(advantages, expected_returns - torch.tensor(values), atol=1e-6)
    # The level is finished after the teacher's last step: a bootstrap value must change nothing.
    again, _ = teacher_gae(regret, values, gamma, 0.8, next_value=100.0)
    assert torch.allclose(again, teacher_gae(regret, values, gamma, 0.8)[0])


# ---------------------------------------------------------------------------------------------------
# PAIRED+BC's cloning term (eq. 1)
# ---------------------------------------------------------------------------------------------------
def student(seed: int, sharpen: float = 1.0):
    """A maze student; `sharpen` scales its policy logits (at init they are near uniform)."""
    torch.manual_seed(seed)
    agent = MazeEnv("maze", 1, 0).Student()
    with torch.no_grad():
        agent.actor[-1].weight.mul_(sharpen)
        agent.actor[-1].bias.normal_(0.0, sharpen * 0.01)
    return agent


def observed_batch(num_envs=3, num_steps=6, seed=0):
    """Time-major flattened observations of random play on random levels, with episode starts."""
    env = MazeEnv("maze", num_envs, seed)
    rng = np.random.default_rng(seed)
    obs = env.reset(env.random_levels(num_envs, rng))
    steps, dones = [], []
    done = np.ones(num_envs)
    for _ in range(num_steps):
        steps.append(to_torch(obs, "cpu"))
        dones.append(torch.as_tensor(done, dtype=torch.float32))
        obs, _, terminated, truncated, _ = env.step(rng.integers(0, 3, num_envs))
        done = (terminated | truncated).astype(np.float32)
    batch = {k: torch.cat([s[k] for s in steps]) for k in steps[0]}
    return batch, torch.cat(dones), num_envs


def test_cloning_kl_is_zero_between_identical_policies():
    agent, target = student(0, sharpen=50.0), student(1)
    target.load_state_dict(agent.state_dict())
    obs, done, n = observed_batch()
    state = agent.initial_state(n)
    kl = paired_bc.cloning_kl(target, agent.dist(obs, state, done), obs, state, done)
    assert abs(kl.item()) < 1e-6


def test_cloning_kl_equals_hand_computed_kl_and_grads_only_the_cloner():
    agent, target = student(0, sharpen=30.0), student(1, sharpen=30.0)
    obs, done, n = observed_batch()
    state = agent.initial_state(n)
    kl = paired_bc.cloning_kl(target, agent.dist(obs, state, done), obs, state, done)
    with torch.no_grad():
        p = target.dist(obs, state, done).probs  # the target's policy, [T * n, 7]
        q = agent.dist(obs, state, done).probs
        by_hand = (p * (p.log() - q.log())).sum(-1).mean()  # KL(target || agent), averaged over the batch
    assert by_hand > 0.05  # clearly different policies
    assert torch.allclose(kl, by_hand, rtol=1e-4)
    kl.backward()
    assert all(p.grad is None for p in target.parameters())
    assert agent.actor[-1].weight.grad is not None and agent.actor[-1].weight.grad.abs().sum() > 0
    assert agent.conv.weight.grad.abs().sum() > 0  # through the LSTM into the encoder


def test_cloning_kl_uses_the_targets_recurrent_state_on_the_cloners_observations():
    # The target sees the cloner's observations through its own LSTM with the episode resets: a
    # different reset pattern changes the target's distribution, hence the KL.
    agent, target = student(0, sharpen=30.0), student(1, sharpen=30.0)
    obs, done, n = observed_batch()
    state = agent.initial_state(n)
    no_resets = torch.zeros_like(done)
    no_resets[:n] = 1.0
    all_resets = torch.ones_like(done)
    with torch.no_grad():
        dist = agent.dist(obs, state, no_resets)
        kl_a = paired_bc.cloning_kl(target, dist, obs, state, no_resets)
        kl_b = paired_bc.cloning_kl(target, dist, obs, state, all_resets)
    assert not torch.allclose(kl_a, kl_b)


def bc_setup(lr=1e-2):
    """A tiny paired_bc configuration and one protagonist rollout on random levels."""
    args = paired_bc.resolve_args(paired_bc.paper_args(env="maze", num_envs=4, num_steps=32, learning_rate=lr))
    env = MazeEnv("maze", args.num_envs, 0)
    levels = env.random_levels(args.num_envs, np.random.default_rng(0))
    agent = student(0)
    storage = paired_bc.Rollout(env.reset(levels), env.single_action_space, args.num_steps, args.num_envs, "cpu")
    torch.manual_seed(0)
    advantages, returns, _ = paired_bc.student_rollout(agent, env, levels, storage, args, "cpu")
    return args, agent, storage, advantages, returns


def kl_on(storage, target, agent, n):
    obs = {k: v.reshape((-1,) + v.shape[2:]) for k, v in storage.obs.items()}
    done = storage.episode_starts.reshape(-1)
    state = agent.initial_state(n)
    with torch.no_grad():
        return paired_bc.cloning_kl(target, agent.dist(obs, state, done), obs, state, done).item()


def test_ppo_update_with_clone_target_moves_the_cloner_toward_the_target():
    args, start, storage, advantages, returns = bc_setup()
    target = student(5, sharpen=30.0)
    target_before = copy.deepcopy(target.state_dict())
    results = {}
    for name, clone_target in (("cloning", target), ("plain", None)):
        agent = copy.deepcopy(start)
        optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
        np.random.seed(0)
        torch.manual_seed(0)
        stats = paired_bc.ppo_update(agent, optimizer, storage, advantages, returns, args.student_ent_coef, args.update_epochs, args.num_minibatches, args, 1, "cpu",
                                     clone_target=clone_target, bc_coef=1.0)
        results[name] = (stats, kl_on(storage, target, agent, args.num_envs))
    kl_start = kl_on(storage, target, start, args.num_envs)
    (cloning_stats, kl_cloning), (plain_stats, kl_plain) = results["cloning"], results["plain"]
    assert cloning_stats["kl"] > 0.01 and plain_stats["kl"] == 0.0
    assert kl_cloning < 0.8 * kl_plain, (kl_start, kl_cloning, kl_plain)
    assert kl_cloning < 0.8 * kl_start
    # The target is only read: no gradient, no change.
    assert all(p.grad is None for p in target.parameters())
    assert all(torch.equal(v, target_before[k]) for k, v in target.state_dict().items())


def test_ppo_update_kl_coef_zero_is_plain_ppo():
    args, start, storage, advantages, returns = bc_setup()
    target = student(5, sharpen=30.0)
    weights = []
    for clone_target in (target, None):
        agent = copy.deepcopy(start)
        optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
        np.random.seed(0)
        paired_bc.ppo_update(agent, optimizer, storage, advantages, returns, args.student_ent_coef, args.update_epochs, args.num_minibatches, args, 1, "cpu",
                             clone_target=clone_target, bc_coef=0.0)
        weights.append(agent.state_dict())
    assert all(torch.allclose(weights[0][k], weights[1][k], atol=1e-6) for k in weights[0])


def run_script(script, args, cwd):
    return script_runs.run([os.path.join(ROOT, script), *args], cwd, SUBPROCESS_ENV, timeout=400)


def metrics_of(cwd):
    (name,) = os.listdir(os.path.join(cwd, "runs"))
    with open(os.path.join(cwd, "runs", name, "metrics.csv"), newline="") as f:
        return list(csv.DictReader(f))


def test_cloning_on_every_kth_update_protagonist_only_unless_bidirectional(tmp_path):
    tiny = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", "--total-timesteps", "512", "--bc-interval", "2",
            "--teacher-conv-channels", "4", "--eval-episodes", "0", "--levels-interval", "100", "--checkpoint-interval", "100"]
    flags = {"uni": [], "bi": ["--bidirectional"]}
    for name in flags:
        (tmp_path / name).mkdir()
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        results = dict(zip(flags, pool.map(lambda n: run_script("paired_bc.py", tiny + flags[n], tmp_path / n), flags)))
    for name, result in results.items():
        assert result.returncode == 0, result.stderr
        rows = metrics_of(tmp_path / name)
        assert [int(r["update"]) for r in rows] == [1, 2, 3, 4]
        for r in rows:
            cloning = int(r["update"]) % 2 == 0
            assert (r["kl_protagonist"] != "") == cloning, (name, r)
            assert (r["kl_antagonist"] != "") == (cloning and name == "bi"), (name, r)
            if cloning:
                assert float(r["kl_protagonist"]) > 0
                if name == "bi":
                    assert float(r["kl_antagonist"]) > 0


# ---------------------------------------------------------------------------------------------------
# Bad input and the paper's defaults
# ---------------------------------------------------------------------------------------------------
BAD = [
    (paired_bc, dict(bc_coef=-0.1)),
    (paired_bc, dict(bc_interval=0)),
    (paired, dict(student_ent_coef=-0.01)),
    (paired, dict(teacher_ent_coef=-0.01)),
    (paired_hient, dict(student_ent_coef=-0.01)),
    (paired_hient, dict(teacher_ent_coef=-0.01)),
    (paired_bc, dict(teacher_ent_coef=-0.01)),
    (paired, dict(num_envs=30, num_minibatches=4)),
    (paired_hient, dict(num_envs=30, num_minibatches=4)),
    (paired_bc, dict(num_envs=30, num_minibatches=4)),
    (paired, dict(env="mars")),
    (paired_hient, dict(env="mars")),
    (paired_bc, dict(env="mars")),
]


@pytest.mark.parametrize("module, bad", BAD, ids=[f"{m.__name__}-{'-'.join(b)}" for m, b in BAD])
def test_bad_arguments_exit_with_status_2(module, bad):
    with pytest.raises(SystemExit) as exit_info:
        make = module.Args if "env" in bad else module.paper_args  # an unknown env has no paper values
        module.resolve_args(make(**bad))
    assert exit_info.value.code == 2


BAD_INPUT = [
    ("paired_bc.py", ["--bc-coef", "-1"], "--bc-coef"),
    ("paired_bc.py", ["--bc-interval", "0"], "--bc-interval"),
    ("paired_hient.py", ["--teacher-ent-coef", "-0.5"], "entropy"),
    ("paired.py", ["--student-ent-coef", "-0.5"], "entropy"),
    ("paired.py", ["--num-envs", "30", "--num-minibatches", "4"], "does not divide"),
    ("paired_bc.py", ["--env", "mars"], "invalid choice 'mars' for argument '--env'"),
    ("paired.py", ["--resume", "not-a-run"], "not a run directory"),
]


@pytest.fixture(scope="module")
def bad_input_runs(tmp_path_factory):
    """The BAD_INPUT commands, two at a time (each in its own empty directory): [(result, cwd)]."""
    cwds = [tmp_path_factory.mktemp("bad") for _ in BAD_INPUT]
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        results = list(pool.map(lambda case: run_script(case[0][0], case[0][1], case[1]), zip(BAD_INPUT, cwds)))
    return list(zip(results, cwds))


@pytest.mark.parametrize("case", range(len(BAD_INPUT)), ids=[f"{s}-{' '.join(a)}" for s, a, _ in BAD_INPUT])
def test_bad_input_is_one_error_line_status_2_nothing_written(bad_input_runs, case):
    message = BAD_INPUT[case][2]
    result, cwd = bad_input_runs[case]
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], result.stderr
    assert os.listdir(cwd) == []  # no runs/ directory, nothing at all


@pytest.mark.parametrize("module, env, expected", [
    (paired, "maze", dict(student_ent_coef=0.0, teacher_ent_coef=0.0)),
    (paired, "maze25", dict(student_ent_coef=0.0, teacher_ent_coef=0.0)),
    (paired_hient, "maze", dict(student_ent_coef=0.005, teacher_ent_coef=0.05)),
    (paired_hient, "maze25", dict(student_ent_coef=0.005, teacher_ent_coef=0.01)),
    (paired_bc, "maze", dict(bc_coef=0.01, bc_interval=5, student_ent_coef=0.005, teacher_ent_coef=0.005)),
    (paired_bc, "maze25", dict(bc_coef=0.1, bc_interval=25, student_ent_coef=0.005, teacher_ent_coef=0.05)),
    (paired_bc, "maze25", dict(hient=False, bc_coef=0.1, bc_interval=25, student_ent_coef=0.0, teacher_ent_coef=0.0, exp_name="paired_unibc")),
])
def test_paper_defaults_per_script_and_env(module, env, expected):
    switches = {"hient": expected["hient"]} if "hient" in expected else {}
    args = module.resolve_args(module.paper_args(env=env, **switches))
    assert {k: getattr(args, k) for k in expected} == expected
    # The two mazes share the paper's PPO settings (its hyperparameter table) in every script.
    assert (args.num_envs, args.num_steps, args.learning_rate, args.gamma, args.gae_lambda, args.update_epochs,
            args.num_minibatches, args.value_loss) == (32, 256, 1e-4, 0.995, 0.95, 5, 1, "clipped")
    assert not getattr(args, "bidirectional", False)


@pytest.mark.parametrize("module, teacher_ent_coef", [(paired, 0.0), (paired_hient, 0.01), (paired_bc, 0.01)])
def test_walker_teacher_takes_the_references_ppo_settings(module, teacher_ent_coef):
    """The reference's walker PAIRED teacher: 8 epochs, 4 minibatches (students: 5 and 32); its entropy the
    paper's (PAIRED 0.0; the reference's 0.01 for HiEnt, Appendix C's 0.01 for BC); the maze teacher
    trains as its students (5 epochs, 1 minibatch); value loss smooth L1 on the walker."""
    args = module.resolve_args(module.paper_args(env="walker"))
    assert (args.teacher_update_epochs, args.teacher_num_minibatches, args.teacher_ent_coef) == (8, 4, teacher_ent_coef)
    assert (args.update_epochs, args.num_minibatches, args.value_loss) == (5, 32, "huber")
    args = module.resolve_args(module.paper_args(env="maze"))
    assert (args.teacher_update_epochs, args.teacher_num_minibatches) == (5, 1)


def test_teacher_update_uses_its_own_epochs_and_minibatches():
    """ppo_update takes the epochs and minibatches it is given (the teacher's), not the students'."""
    args, start, storage, advantages, returns = bc_setup()
    steps = []
    for epochs, minibatches in ((1, 1), (3, 2)):
        agent = copy.deepcopy(start)
        optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
        paired.ppo_update(agent, optimizer, storage, advantages, returns, 0.0, epochs, minibatches, args, 1, "cpu")
        steps.append(optimizer.state_dict()["state"][0]["step"].item())
    assert steps == [1, 6]


def test_explicit_options_override_the_paper_defaults():
    args = paired_bc.resolve_args(paired_bc.paper_args(env="maze25", bc_interval=3, bc_coef=0.0, teacher_ent_coef=0.0))
    assert (args.bc_interval, args.bc_coef, args.teacher_ent_coef, args.student_ent_coef) == (3, 0.0, 0.0, 0.005)
    args = paired_hient.resolve_args(paired_hient.paper_args(env="maze", student_ent_coef=0.0))
    assert (args.student_ent_coef, args.teacher_ent_coef) == (0.0, 0.05)
