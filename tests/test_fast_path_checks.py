"""A maze net's fast path never acts with another function or with stale weights: an edit of `features`
that the derivation does not follow is caught by the check against the plain net, and the net runs
plainly from then on; weights changed where no version counter sees it (through `.data`, by a fused
Adam step) are derived again. In each case the actions, log-probabilities and values are the plain
net's for the same seed. And each net says at its first use which path it runs."""

import numpy as np
import pytest
import torch
from torch import nn

from envs.maze.env import MazeEnv, MazeStudent, MazeTeacher, MazeTeacherMDP
from envs.nets import ResettableLSTM

NUM_COPIES = 6


@pytest.fixture(autouse=True)
def fast_paths_on(monkeypatch):
    monkeypatch.delenv("CLEANUED_PLAIN_NETS", raising=False)
    # The orthogonal init of the teacher's LSTM input weights is slow and not what is tested here.
    monkeypatch.setattr(nn.init, "orthogonal_", lambda tensor, gain=1.0: nn.init.normal_(tensor, 0.0, 0.05 * gain))


def as_torch(obs: dict) -> dict:
    return {k: torch.as_tensor(v) for k, v in obs.items()}


def student() -> MazeStudent:
    """A small student whose policy is far from uniform (its last actor layer scaled up), so that a small
    change of its outputs changes the actions drawn."""
    torch.manual_seed(0)
    net = MazeStudent(32)
    with torch.no_grad():
        net.actor[2].weight.mul_(300.0)
    return net


def teacher() -> MazeTeacher:
    torch.manual_seed(0)
    net = MazeTeacher(27, conv_channels=8, hidden_size=32)
    with torch.no_grad():
        net.actor[2].weight.mul_(300.0)
    return net


def acting(net, steps: int, plain: bool, monkeypatch, seed: int = 1):
    """Acts `steps` steps without gradient from a fixed seed (on maze levels for a student, designing
    levels for a teacher), on the plain path or as the net chooses -> the time-major training batch of
    the steps, their episode starts, and [action, log-probability, value] stacked over the steps."""
    monkeypatch.setenv("CLEANUED_PLAIN_NETS", "1" if plain else "0")
    torch.manual_seed(seed)
    if isinstance(net, MazeTeacher):
        mdp = MazeTeacherMDP(25, False, np.random.default_rng(seed))
        obs, env_step = mdp.reset(NUM_COPIES), lambda action: mdp.step(action)[0]
    else:
        env = MazeEnv("maze", NUM_COPIES, seed=seed)
        obs, env_step = env.reset(env.random_levels(NUM_COPIES, np.random.default_rng(seed))), lambda action: env.step(action)[0]
    obs, state, done = as_torch(obs), net.initial_state(NUM_COPIES), torch.ones(NUM_COPIES)
    steps_obs, dones, outputs = [], [], []
    with torch.no_grad():
        for _ in range(steps):
            action, logprob, _, value, state = net.get_action_and_value(obs, state, done)
            steps_obs.append(obs)
            dones.append(done)
            outputs.append(torch.stack([action.float(), logprob, value]))
            obs, done = as_torch(env_step(action.numpy())), torch.zeros(NUM_COPIES)
    monkeypatch.delenv("CLEANUED_PLAIN_NETS")
    batch = {k: torch.cat([step[k] for step in steps_obs]) for k in steps_obs[0]}
    return batch, torch.cat(dones), torch.stack(outputs)


def assert_acts_as_plain(net, steps: int, monkeypatch, seed: int = 1):
    """The same actions, log-probabilities and values as the plain net's, from the same seed."""
    *_, expected = acting(net, steps, True, monkeypatch, seed)
    *_, got = acting(net, steps, False, monkeypatch, seed)
    assert torch.equal(got[:, 0], expected[:, 0])
    assert torch.allclose(got[:, 1:], expected[:, 1:], atol=1e-5, rtol=1e-5)


def without_relu(self, obs: dict) -> torch.Tensor:
    """MazeStudent.features as if edited: the ReLU after the conv dropped."""
    view = self.conv(obs["image"].permute(0, 3, 1, 2).float() / self.image_scale).flatten(1)
    direction = self.direction_embed(nn.functional.one_hot(obs["direction"].long(), 4).float())
    return torch.cat([view, direction], dim=1)


def teacher_without_relu(self, obs: dict) -> torch.Tensor:
    """MazeTeacher.features as if edited: the ReLU after the conv dropped."""
    image = obs["image"].permute(0, 3, 1, 2).float() / self.image_scale
    return torch.cat([self.conv[0](image).flatten(1), self.dense_features(obs)], dim=1)


def test_an_edited_student_features_acts_as_the_plain_net(monkeypatch, capsys):
    monkeypatch.setattr(MazeStudent, "features", without_relu)
    net = student()
    assert_acts_as_plain(net, 30, monkeypatch)
    assert net.fast_path() is None
    warning = [line for line in capsys.readouterr().out.splitlines() if line.startswith("warning:")]
    assert len(warning) == 1 and warning[0].startswith("warning: MazeStudent: its fast path's ")
    assert warning[0].endswith("it runs the plain path from now on")


def test_an_edited_teacher_features_acts_and_trains_as_the_plain_net(monkeypatch):
    """Acting over a whole design episode, and the training pass on it: the teacher's sparse training
    path assumes the same function, and never runs unchecked, even before any acting step."""
    monkeypatch.setattr(MazeTeacher, "features", teacher_without_relu)
    net = teacher()
    assert_acts_as_plain(net, 27, monkeypatch)
    batch, dones, outputs = acting(net, 27, True, monkeypatch)
    actions = outputs[:, 0].long().reshape(-1)
    for trained in (net, teacher()):  # the second net trains before it ever acts
        _, logprob, _, value, _ = trained.get_action_and_value(batch, trained.initial_state(NUM_COPIES), dones, actions)
        monkeypatch.setenv("CLEANUED_PLAIN_NETS", "1")
        _, plain_logprob, _, plain_value, _ = trained.get_action_and_value(batch, trained.initial_state(NUM_COPIES), dones, actions)
        monkeypatch.delenv("CLEANUED_PLAIN_NETS")
        assert torch.allclose(logprob, plain_logprob, atol=1e-5) and torch.allclose(value, plain_value, atol=1e-5)
        assert trained.fast_path() is None


def test_features_edited_later_are_caught_at_the_next_rebuild(monkeypatch, capsys):
    """The first build passes its check; the edit shows at the build after a weight change."""
    net = student()
    acting(net, 5, False, monkeypatch)
    monkeypatch.setattr(MazeStudent, "features", without_relu)
    with torch.no_grad():
        net.critic[2].bias.add_(0.5)
    assert_acts_as_plain(net, 20, monkeypatch)
    assert net.fast_path() is None
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and lines[0] == "MazeStudent: fast path (derived from the plain net, checked against it)"
    assert lines[1].startswith("warning: MazeStudent: its fast path's ")


def training_pass(net, monkeypatch):
    """A forward and backward pass with gradient on a short rollout (PPO's log-likelihood and value terms)."""
    batch, dones, outputs = acting(net, 4, False, monkeypatch, seed=7)
    _, logprob, _, value, _ = net.get_action_and_value(batch, net.initial_state(NUM_COPIES), dones, outputs[:, 0].long().reshape(-1))
    (value.square().mean() - logprob.mean()).backward()


@pytest.mark.parametrize("make_net", [student, teacher])
def test_an_update_through_data_is_seen(make_net, monkeypatch):
    """A hand-written SGD step on `.data`, which no version counter sees, after the training pass that
    gave its gradients."""
    net = make_net()
    assert_acts_as_plain(net, 5, monkeypatch)
    training_pass(net, monkeypatch)
    versions = [p._version for p in net.parameters()]
    for param in net.parameters():
        param.data.add_(param.grad, alpha=-0.5)
    assert [p._version for p in net.parameters()] == versions
    assert_acts_as_plain(net, 20, monkeypatch)
    assert net.fast_path() is not None


@pytest.mark.parametrize("make_net", [student, teacher])
def test_a_fused_adam_step_is_seen(make_net, monkeypatch):
    """Fused Adam writes the parameters past their version counters. Its gradients are set by hand here,
    with no pass of the net: the optimizer step alone marks the derived weights stale."""
    net = make_net()
    assert_acts_as_plain(net, 5, monkeypatch)
    optimizer = torch.optim.Adam(net.parameters(), lr=0.05, fused=True)
    versions = [p._version for p in net.parameters()]
    for param in net.parameters():
        param.grad = torch.randn_like(param)
    optimizer.step()
    assert [p._version for p in net.parameters()] == versions
    assert_acts_as_plain(net, 20, monkeypatch)
    assert net.fast_path() is not None


class WiderViewStudent(MazeStudent):
    def __init__(self):
        super().__init__(hidden_size=16)
        self.conv = nn.Conv2d(3, 8, 2, padding=1)
        self.lstm = ResettableLSTM(8 * 6 * 6 + 5, 16)


def test_each_net_names_its_path_once_at_its_first_use(monkeypatch, capsys):
    torch.manual_seed(0)
    nets = [MazeStudent(16), WiderViewStudent(), MazeStudent(16), MazeTeacher(27, conv_channels=2, hidden_size=8)]
    nets[3].time_embed = nn.Sequential(nn.Linear(27, 10))
    assert capsys.readouterr().out == ""
    for net in nets[:2]:
        for _ in range(2):
            acting(net, 3, False, monkeypatch)
    acting(nets[2], 3, True, monkeypatch)
    acting(nets[2], 3, False, monkeypatch)
    acting(nets[3], 3, False, monkeypatch)
    assert capsys.readouterr().out.splitlines() == [
        "MazeStudent: fast path (derived from the plain net, checked against it)",
        "WiderViewStudent: plain path (a fast path serves only the class it is derived for, not a subclass)",
        "MazeStudent: plain path (CLEANUED_PLAIN_NETS=1)",
        "MazeTeacher: plain path (its modules are not the kinds its fast path is derived from)",
    ]
