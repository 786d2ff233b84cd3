"""The fast paths of envs/maze/fast_paths.py equal the plain nets they are derived from, and serve only the
unmodified nets: a subclass with another conv or hidden size trains and acts on the plain path. Each
test of a fast path asserts that it ran. (The teacher's sparse training path:
tests/test_sparse_projection.py; a net edited, or written past its version counters:
tests/test_fast_path_checks.py.)"""

import numpy as np
import pytest
import torch
from torch import nn

import envs.maze.fast_paths as fast_paths
from envs.maze.env import MazeEnv, MazeStudent, MazeTeacher, MazeTeacherMDP
from envs.maze.fast_paths import MaskedLSTMRecurrence
from envs.nets import ResettableLSTM


@pytest.fixture(autouse=True)
def fast_paths_on(monkeypatch):
    monkeypatch.delenv("CLEANUED_PLAIN_NETS", raising=False)


def as_torch(obs: dict) -> dict:
    return {k: torch.as_tensor(v) for k, v in obs.items()}


def count_calls(monkeypatch, name: str) -> list:
    """Replaces envs.maze.fast_paths' function `name` (for the monkeypatch's life) with one that calls it and
    notes in the returned list, per call, whether it returned something (not None)."""
    returned = []
    original = getattr(fast_paths, name)

    def counted(*args, **kwargs):
        result = original(*args, **kwargs)
        returned.append(result is not None)
        return result

    monkeypatch.setattr(fast_paths, name, counted)
    return returned


def fast_acting_step(net, obs, state, done):
    """An acting step (no gradient, no action given), asserted to run on the fast path."""
    with pytest.MonkeyPatch.context() as patch:
        fast_acts = count_calls(patch, "act_from_gate_inputs")
        with torch.no_grad():
            result = net.get_action_and_value(obs, state, done)
    assert fast_acts == [True]
    return result


def plain_step(net, obs, state, done, monkeypatch):
    """An acting step (no gradient, no action given) with every fast path off."""
    monkeypatch.setenv("CLEANUED_PLAIN_NETS", "1")
    with torch.no_grad():
        result = net.get_action_and_value(obs, state, done)
    monkeypatch.delenv("CLEANUED_PLAIN_NETS")
    return result


def assert_fast_step_equals_plain(net, obs, state, done, monkeypatch, atol=1e-5):
    """The fast acting step draws the plain step's actions from the same random stream, with its
    log-probabilities, entropies, values and new state."""
    torch.manual_seed(11)
    plain = plain_step(net, obs, state, done, monkeypatch)
    torch.manual_seed(11)
    fast = fast_acting_step(net, obs, state, done)
    assert torch.equal(fast[0], plain[0])
    for got, expected in zip((*fast[1:4], *fast[4]), (*plain[1:4], *plain[4])):
        assert torch.allclose(got, expected, atol=atol, rtol=1e-5)
    return fast


@pytest.mark.parametrize("hidden_size", [256, 24])
def test_student_fast_acting_equals_plain_after_weight_changes(hidden_size, monkeypatch):
    """With and without episode starts; after an optimizer step and a load_state_dict (the derived
    weights follow both); over the steps of a rollout, on their own sampled actions."""
    torch.manual_seed(0)
    net = MazeStudent(hidden_size)
    assert net.fast_path() is not None
    num_copies = 8
    env = MazeEnv("maze", num_copies, seed=1)
    obs = as_torch(env.reset(env.random_levels(num_copies, np.random.default_rng(1))))
    state = (torch.randn(1, num_copies, hidden_size), torch.randn(1, num_copies, hidden_size))
    optimizer = torch.optim.Adam(net.parameters(), lr=0.01)
    for change in ("none", "optimizer step", "load_state_dict"):
        if change == "optimizer step":
            _, logprob, _, value, _ = net.get_action_and_value(obs, state, torch.zeros(num_copies))
            (value.square().sum() - logprob.sum()).backward()
            optimizer.step()
        elif change == "load_state_dict":
            net.load_state_dict(MazeStudent(hidden_size).state_dict())
        for done in (torch.tensor([1.0, 0, 0, 1, 0, 0, 0, 0]), torch.zeros(num_copies)):
            assert_fast_step_equals_plain(net, obs, state, done, monkeypatch)
    done = torch.ones(num_copies)
    for _ in range(20):
        action, _, _, _, state = assert_fast_step_equals_plain(net, obs, state, done, monkeypatch)
        step_obs, _, terminated, truncated, _ = env.step(action.numpy())
        obs, done = as_torch(step_obs), torch.as_tensor(terminated | truncated, dtype=torch.float32)


def test_student_fast_acting_follows_a_changed_conv(monkeypatch):
    """The folded view matrix is found by running the conv, so it follows any nn.Conv2d (here 2x2 with
    padding 1, 8 channels) put into the student itself, as an edit of its class would."""
    torch.manual_seed(12)
    net = MazeStudent(24)
    net.conv = nn.Conv2d(3, 8, 2, padding=1)
    net.lstm = ResettableLSTM(8 * 6 * 6 + 5, 24)
    assert net.fast_path() is not None
    env = MazeEnv("maze", 6, seed=4)
    obs = as_torch(env.reset(env.random_levels(6, np.random.default_rng(4))))
    state = (torch.randn(1, 6, 24), torch.randn(1, 6, 24))
    assert_fast_step_equals_plain(net, obs, state, torch.tensor([0.0, 1, 0, 0, 0, 1]), monkeypatch)


def test_student_fast_policy_step_equals_plain(monkeypatch):
    """The held-out evaluation's step (the policy and new state, no action drawn: envs/evaluation.py) runs
    on the fast path once its weights are built, and gives the plain net's probabilities and state."""
    torch.manual_seed(13)
    net = MazeStudent()
    env = MazeEnv("maze", 6, seed=5)
    obs = as_torch(env.reset(env.random_levels(6, np.random.default_rng(5))))
    state = (torch.randn(1, 6, 256), torch.randn(1, 6, 256))
    done = torch.tensor([1.0, 0, 0, 1, 0, 0])
    with torch.no_grad():
        net.policy_and_state(obs, state, done)  # builds and checks the derived weights
        with pytest.MonkeyPatch.context() as patch:
            fast_steps = count_calls(patch, "step_from_gate_inputs")
            fast_policy, (fast_h, fast_c) = net.policy_and_state(obs, state, done)
        assert fast_steps == [True]
        monkeypatch.setenv("CLEANUED_PLAIN_NETS", "1")
        plain_policy, (plain_h, plain_c) = net.policy_and_state(obs, state, done)
    for got, expected in ((fast_policy.probs, plain_policy.probs), (fast_h, plain_h), (fast_c, plain_c)):
        assert torch.allclose(got, expected, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("setting,budget,uniform", [("maze", 60, True), ("maze25", 25, False)])
def test_teacher_fast_acting_equals_plain_over_an_episode(setting, budget, uniform, monkeypatch):
    """A whole teacher episode, each step from the fast step's own state and action (the running conv
    gates carried along), then a second episode after a weight change."""
    monkeypatch.setattr(nn.init, "orthogonal_", lambda tensor, gain=1.0: nn.init.normal_(tensor, 0.0, 0.05 * gain))
    torch.manual_seed(1)
    num_copies = 4
    mdp = MazeTeacherMDP(budget, uniform, np.random.default_rng(2))
    net = MazeTeacher(mdp.num_steps, conv_channels=8)
    assert net.fast_path() is not None
    for episode in range(2):
        obs, state, done = as_torch(mdp.reset(num_copies)), net.initial_state(num_copies), torch.ones(num_copies)
        for _ in range(mdp.num_steps):
            action, _, _, _, state = assert_fast_step_equals_plain(net, obs, state, done, monkeypatch, atol=1e-4)
            step_obs, _ = mdp.step(action.numpy())
            obs, done = as_torch(step_obs), torch.zeros(num_copies)
        with torch.no_grad():
            for param in net.parameters():
                param.add_(0.01 * torch.randn_like(param))


FIXED_POLICY = torch.tensor([0.5, 0.0, 0.3, 0.2, 0.0, 0.0, 0.0])


def student_with_a_fixed_policy() -> MazeStudent:
    """A student (LSTM of 8) whose heads ignore their input and whose policy is FIXED_POLICY, by the actor's
    output bias."""
    net = MazeStudent(8)
    with torch.no_grad():
        for head in (net.actor, net.critic):
            for param in head.parameters():
                param.zero_()
        net.actor[2].bias.copy_(torch.log(FIXED_POLICY.clamp(min=1e-12)))
    return net


def test_fast_sampling_follows_the_policy():
    """The fast step's actions are distributed as the policy: `student_with_a_fixed_policy`."""
    torch.manual_seed(5)
    probs, net = FIXED_POLICY, student_with_a_fixed_policy()
    n = 100_000
    obs = {"image": torch.zeros(n, 5, 5, 3, dtype=torch.uint8), "direction": torch.zeros(n, dtype=torch.long)}
    action, logprob, entropy, _, _ = fast_acting_step(net, obs, net.initial_state(n), torch.ones(n))
    counts = torch.bincount(action, minlength=7).float()
    assert counts[[1, 4, 5, 6]].sum() == 0  # actions of probability 0 (up to 1e-12) never drawn
    tolerance = 4 * torch.sqrt(probs * (1 - probs) / n)  # 4 standard errors
    assert torch.all((counts / n - probs).abs() <= tolerance + 1e-9)
    assert torch.allclose(logprob, torch.log(probs.clamp(min=1e-12))[action])
    assert torch.allclose(entropy, torch.full((n,), -(probs[probs > 0] * probs[probs > 0].log()).sum().item()), atol=1e-5)


class WiderViewStudent(MazeStudent):
    """A modified student: a 2x2 conv with padding 1 and 8 channels (8 x 6 x 6 features), an LSTM of 32."""

    def __init__(self):
        super().__init__(hidden_size=32)
        self.conv = nn.Conv2d(3, 8, 2, padding=1)
        self.lstm = ResettableLSTM(8 * 6 * 6 + 5, 32)


class StridedTeacher(MazeTeacher):
    """A modified teacher: a stride-2 conv with 4 channels (4 x 7 x 7 features), an LSTM of 16."""

    def __init__(self, num_steps: int):
        super().__init__(num_steps, hidden_size=16, conv_channels=4)
        self.conv = nn.Sequential(nn.Conv2d(3, 4, 3, stride=2), nn.ReLU(), nn.Flatten())
        self.lstm = ResettableLSTM(4 * 7 * 7 + 10 + 50, 16)
        self.actor[0] = nn.Linear(16, 32)
        self.critic[0] = nn.Linear(16, 32)


def rollout(net, obs: dict, env_step, num_steps: int, num_copies: int):
    """Acts for `num_steps` from `obs` (no gradient), as a rollout does, stepping the env with
    `env_step(action) -> obs`; returns the time-major training batch, its episode starts and the actions."""
    state, done = net.initial_state(num_copies), torch.ones(num_copies)
    steps_obs, actions = [], []
    with torch.no_grad():
        for _ in range(num_steps):
            action, logprob, entropy, value, state = net.get_action_and_value(obs, state, done)
            assert action.shape == logprob.shape == entropy.shape == value.shape == (num_copies,) and state[0].shape[1] == num_copies
            steps_obs.append(obs)
            actions.append(action)
            obs, done = as_torch(env_step(action.numpy())), torch.zeros(num_copies)
    batch = {k: torch.cat([step[k] for step in steps_obs]) for k in steps_obs[0]}
    dones = torch.zeros(num_steps * num_copies)
    dones[:num_copies] = 1.0
    return batch, dones, torch.cat(actions)


def assert_trains(net, batch, dones, actions, num_copies):
    """Some Adam steps on the log-likelihood of the taken actions and a value regression lower the loss,
    with a gradient at every parameter."""
    optimizer = torch.optim.Adam(net.parameters(), lr=3e-3)
    targets = torch.linspace(-1, 1, len(actions))
    losses = []
    for _ in range(15):
        _, logprob, entropy, value, _ = net.get_action_and_value(batch, net.initial_state(num_copies), dones, actions)
        loss = -logprob.mean() + (value - targets).square().mean()
        optimizer.zero_grad()
        loss.backward()
        assert all(param.grad is not None and param.grad.abs().max() > 0 for param in net.parameters())
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.9 * losses[0]


def test_a_modified_student_trains_and_acts_on_the_plain_path():
    torch.manual_seed(3)
    net = WiderViewStudent()
    assert net.fast_path() is None
    num_copies, env = 4, MazeEnv("maze", 4, seed=3)
    obs = as_torch(env.reset(env.random_levels(num_copies, np.random.default_rng(3))))
    batch, dones, actions = rollout(net, obs, lambda action: env.step(action)[0], 8, num_copies)
    # Acting is the plain net's: the same step with gradient draws the same actions from the same stream.
    state = (torch.randn(1, num_copies, 32), torch.randn(1, num_copies, 32))
    torch.manual_seed(4)
    with torch.no_grad():
        acting = net.get_action_and_value(obs, state, torch.zeros(num_copies))
    torch.manual_seed(4)
    training = net.get_action_and_value(obs, state, torch.zeros(num_copies))
    assert torch.equal(acting[0], training[0]) and torch.allclose(acting[3], training[3])
    assert net.fast_path_state is None
    assert_trains(net, batch, dones, actions, num_copies)


def test_a_modified_teacher_trains_and_acts_on_the_plain_path():
    torch.manual_seed(6)
    num_copies = 3
    mdp = MazeTeacherMDP(25, False, np.random.default_rng(6))
    net = StridedTeacher(mdp.num_steps)
    assert net.fast_path() is None
    batch, dones, actions = rollout(net, as_torch(mdp.reset(num_copies)), lambda action: mdp.step(action)[0], mdp.num_steps, num_copies)
    assert net.fast_path_state is None
    assert_trains(net, batch, dones, actions, num_copies)


def test_fast_paths_serve_only_the_nets_they_recognise(monkeypatch):
    """The unmodified classes at any hidden size or conv width; not a subclass, not a net whose modules
    were swapped, not with CLEANUED_PLAIN_NETS=1."""
    monkeypatch.setattr(nn.init, "orthogonal_", lambda tensor, gain=1.0: nn.init.normal_(tensor, 0.0, 0.05 * gain))
    assert MazeStudent(16).fast_path() is not None and MazeTeacher(27, conv_channels=2, hidden_size=8).fast_path() is not None

    class Renamed(MazeStudent):
        """MazeStudent under another name: a subclass, which never inherits a fast path."""

    assert Renamed(16).fast_path() is None
    swapped = MazeStudent(16)
    swapped.conv = nn.Sequential(nn.Conv2d(3, 16, 3))
    assert swapped.fast_path() is None
    padded = MazeTeacher(27, conv_channels=2, hidden_size=8)
    padded.conv[0] = nn.Conv2d(3, 2, 3, padding=1)
    assert padded.fast_path() is None
    monkeypatch.setenv("CLEANUED_PLAIN_NETS", "1")
    assert MazeStudent(16).fast_path() is None


def step_by_step(lstm, x, state, done, num_copies):
    outputs = []
    for t in range(x.shape[0] // num_copies):
        rows = slice(t * num_copies, (t + 1) * num_copies)
        out, state = lstm(x[rows], state, done[rows])
        outputs.append(out)
    return torch.cat(outputs)


def test_masked_recurrence_equals_stepping_the_lstm():
    """The teacher's recurrence on its input projection: the outputs and the gradients at the inputs, the
    initial state and the weights of stepping ResettableLSTM, including a copy whose first step resets."""
    torch.manual_seed(3)
    lstm = ResettableLSTM(9, 12)
    steps, copies = 15, 3
    x = torch.randn(steps * copies, 9, requires_grad=True)
    done = (torch.rand(steps * copies) < 0.2).float()
    done[:copies] = torch.tensor([0.0, 1.0, 0.0])  # copy 1's initial state is reset away: no gradient
    state = (torch.randn(1, copies, 12, requires_grad=True), torch.randn(1, copies, 12, requires_grad=True))
    weights = lstm.lstm
    projected = nn.functional.linear(x, weights.weight_ih_l0, weights.bias_ih_l0 + weights.bias_hh_l0).view(steps, copies, -1)
    keep = (1.0 - done).view(steps, copies, 1)
    fast = MaskedLSTMRecurrence.apply(projected, weights.weight_hh_l0, state[0][0], state[1][0], keep).view(steps * copies, 12)
    slow = step_by_step(lstm, x, state, done, copies)
    assert torch.allclose(fast, slow, atol=1e-5)
    inputs = (x, *state, *lstm.parameters())
    out_weights = torch.randn_like(fast)
    grads_fast = torch.autograd.grad((fast * out_weights).sum(), inputs)
    grads_slow = torch.autograd.grad((slow * out_weights).sum(), inputs)
    for a, b in zip(grads_fast, grads_slow):
        assert torch.allclose(a, b, atol=1e-5)
    assert grads_fast[1][0, 1].abs().max() == 0 and grads_fast[1][0, 0].abs().max() > 0


def test_masked_recurrence_passes_gradcheck():
    torch.manual_seed(4)
    steps, copies, hidden = 6, 2, 3
    projected = torch.randn(steps, copies, 4 * hidden, dtype=torch.float64, requires_grad=True)
    weight_hh = torch.randn(4 * hidden, hidden, dtype=torch.float64, requires_grad=True)
    h0 = torch.randn(copies, hidden, dtype=torch.float64, requires_grad=True)
    c0 = torch.randn(copies, hidden, dtype=torch.float64, requires_grad=True)
    keep = torch.ones(steps, copies, 1, dtype=torch.float64)
    keep[2, 0] = keep[4, 1] = 0.0
    assert torch.autograd.gradcheck(MaskedLSTMRecurrence.apply, (projected, weight_hh, h0, c0, keep))
