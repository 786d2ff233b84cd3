"""The fast sequence path of ResettableLSTM computes exactly what stepping the LSTM one step at a time does."""

import pytest
import torch
from torch import nn

from conftest import assert_acting_equals_training
from envs.nets import MaskedLSTMRecurrence, RecurrentCategoricalActorCritic, ResettableLSTM


def step_by_step(lstm, x, state, done, num_copies):
    outputs = []
    for t in range(x.shape[0] // num_copies):
        rows = slice(t * num_copies, (t + 1) * num_copies)
        out, state = lstm(x[rows], state, done[rows])
        outputs.append(out)
    return torch.cat(outputs), state


def test_sequence_path_equals_step_loop_with_resets():
    torch.manual_seed(0)
    lstm = ResettableLSTM(7, 16)
    steps, copies = 40, 6
    x = torch.randn(steps * copies, 7)
    done = (torch.rand(steps * copies) < 0.15).float()
    done[:copies] = torch.tensor([1.0, 0, 1, 0, 0, 0])  # some copies carry the initial state in
    done[5 * copies + 2] = 1.0
    state = (torch.randn(1, copies, 16), torch.randn(1, copies, 16))
    fast, fast_state = lstm(x, state, done)
    slow, _ = step_by_step(lstm, x, state, done, copies)
    assert fast_state is None
    assert torch.allclose(fast, slow, atol=1e-5)


def test_sequence_path_gradients_equal_step_loop():
    torch.manual_seed(1)
    lstm = ResettableLSTM(5, 8)
    steps, copies = 25, 4
    x = torch.randn(steps * copies, 5)
    done = (torch.rand(steps * copies) < 0.2).float()
    state = lstm.initial_state(copies)
    fast, _ = lstm(x, state, done)
    fast.square().sum().backward()
    fast_grads = [p.grad.clone() for p in lstm.parameters()]
    lstm.zero_grad()
    slow, _ = step_by_step(lstm, x, state, done, copies)
    slow.square().sum().backward()
    for a, b in zip(fast_grads, (p.grad for p in lstm.parameters())):
        assert torch.allclose(a, b, atol=1e-4)


def test_reset_steps_reset_exactly_with_large_weights_and_states():
    """The inserted reset steps zero the state even with the input and forget gates' biases at +95 (far
    beyond what training reaches; with them an incomplete reset would carry c forward) and large inputs
    and state: outputs equal the step loop's, and nothing leaks back through a reset."""
    torch.manual_seed(6)
    lstm = ResettableLSTM(4, 8)
    with torch.no_grad():
        for param in lstm.parameters():
            param.mul_(3.0)
        lstm.lstm.bias_ih_l0[:16] = 95.0
    steps, copies = 12, 3
    x = (50 * torch.randn(steps * copies, 4)).requires_grad_()
    done = torch.zeros(steps * copies)
    done[[4 * copies, 5 * copies, 9 * copies + 1]] = 1.0  # copy 0 resets twice in a row
    state = (torch.full((1, copies, 8), 0.9), torch.full((1, copies, 8), 40.0))
    fast, _ = lstm(x, state, done)
    slow, _ = step_by_step(lstm, x, state, done, copies)
    assert torch.allclose(fast, slow, atol=1e-5)
    # The loss of copy 0's steps after its last reset has no gradient at the inputs before it.
    after_reset = fast.view(steps, copies, 8)[5:, 0].sum()
    grad = torch.autograd.grad(after_reset, x)[0].view(steps, copies, 4)
    assert grad[:5, 0].abs().max() == 0 and grad[5:, 0].abs().max() > 0 and grad[:, 1:].abs().max() == 0


class SmallNet(RecurrentCategoricalActorCritic):
    def __init__(self):
        super().__init__()
        self.lstm = ResettableLSTM(5, 6)
        self.actor = nn.Sequential(nn.Linear(6, 32), nn.Tanh(), nn.Linear(32, 3))
        self.critic = nn.Sequential(nn.Linear(6, 32), nn.Tanh(), nn.Linear(32, 1))

    def features(self, obs):
        return obs["x"]


def test_acting_step_equals_the_training_step():
    """Without gradient a rollout step runs on derived weights (transposed LSTM weights in the gate order
    i, f, o, g, fused heads); it computes what torch's LSTM cell and the heads compute, with and
    without copy 1's state reset, and the derived weights follow an optimizer step and a load_state_dict."""
    torch.manual_seed(7)
    net = SmallNet()
    obs, done = {"x": torch.randn(4, 5)}, torch.tensor([False, True, False, False])
    state = (torch.randn(1, 4, 6), torch.randn(1, 4, 6))
    optimizer = torch.optim.Adam(net.parameters(), lr=0.1)
    for change in ("none", "optimizer step", "load_state_dict"):
        if change == "optimizer step":
            net.get_action_and_value(obs, state, done)[3].sum().backward()
            optimizer.step()
        elif change == "load_state_dict":
            net.load_state_dict(SmallNet().state_dict())
        for starts in (done, torch.zeros(4, dtype=torch.bool)):
            assert_acting_equals_training(net, obs, state, starts, atol=1e-6)


def test_fused_heads_equal_the_actor_and_critic_modules():
    """get_action_and_value runs the heads as two fused matmuls; its log-probabilities, entropies, values
    and their gradients equal those of the actor and critic modules (what dist_and_value uses)."""
    torch.manual_seed(8)
    net = SmallNet()
    obs, done = {"x": torch.randn(6, 5)}, torch.zeros(6)
    state, action = net.initial_state(6), torch.tensor([0, 1, 2, 2, 1, 0])
    _, logprob, entropy, value, _ = net.get_action_and_value(obs, state, done, action)
    dist, module_value = net.dist_and_value(obs, state, done)
    expected = (dist.log_prob(action), dist.entropy(), module_value)
    for got, want in zip((logprob, entropy, value), expected):
        assert torch.allclose(got, want, atol=1e-6)
    weights = torch.randn(3, 6)
    params = list(net.actor.parameters()) + list(net.critic.parameters())
    got = torch.autograd.grad(sum((w * x).sum() for w, x in zip(weights, (logprob, entropy, value))), params)
    want = torch.autograd.grad(sum((w * x).sum() for w, x in zip(weights, expected)), params)
    for a, b in zip(got, want):
        assert torch.allclose(a, b, atol=1e-6)


def test_reset_zeroes_state():
    torch.manual_seed(2)
    lstm = ResettableLSTM(3, 4)
    x = torch.randn(2, 3)
    state = (torch.randn(1, 2, 4), torch.randn(1, 2, 4))
    out_reset, _ = lstm(x, state, torch.ones(2))
    out_fresh, _ = lstm(x, lstm.initial_state(2), torch.zeros(2))
    out_carry, _ = lstm(x, state, torch.zeros(2))
    assert torch.allclose(out_reset, out_fresh)
    assert not torch.allclose(out_reset, out_carry)


@pytest.mark.parametrize("project_inputs_first", [False, True])
def test_sequence_path_gradients_reach_the_initial_state_and_inputs(project_inputs_first):
    torch.manual_seed(3)
    lstm = ResettableLSTM(9, 12, project_inputs_first=project_inputs_first)
    steps, copies = 15, 3
    x = torch.randn(steps * copies, 9, requires_grad=True)
    done = (torch.rand(steps * copies) < 0.2).float()
    done[:copies] = torch.tensor([0.0, 1.0, 0.0])  # copy 1's initial state is reset away: no gradient
    state = (torch.randn(1, copies, 12, requires_grad=True), torch.randn(1, copies, 12, requires_grad=True))
    fast, _ = lstm(x, state, done)
    slow, _ = step_by_step(lstm, x, state, done, copies)
    weights = torch.randn_like(fast)
    grads_fast = torch.autograd.grad((fast * weights).sum(), (x, *state))
    grads_slow = torch.autograd.grad((slow * weights).sum(), (x, *state))
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


class FixedPolicy(RecurrentCategoricalActorCritic):
    """A recurrent net whose policy is the same categorical distribution for every input: its heads'
    weights are 0 and the actor's output bias is the logits."""

    def __init__(self, logits: torch.Tensor):
        super().__init__()
        self.lstm = ResettableLSTM(1, 2)
        self.actor = nn.Sequential(nn.Linear(2, 32), nn.Tanh(), nn.Linear(32, len(logits)))
        self.critic = nn.Sequential(nn.Linear(2, 32), nn.Tanh(), nn.Linear(32, 1))
        for param in self.parameters():
            nn.init.zeros_(param)
        with torch.no_grad():
            self.actor[2].bias.copy_(logits)

    def features(self, obs):
        return obs["x"]


def test_sampled_actions_follow_the_policy():
    torch.manual_seed(5)
    probs = torch.tensor([0.5, 0.0, 0.3, 0.2, 0.0])
    net = FixedPolicy(torch.log(probs.clamp(min=1e-12)))
    n = 200_000
    with torch.no_grad():
        action, logprob, entropy, _, _ = net.get_action_and_value({"x": torch.zeros(n, 1)}, net.initial_state(n), torch.ones(n))
    counts = torch.bincount(action, minlength=5).float()
    assert counts[1] == 0 and counts[4] == 0  # actions of probability 0 (up to 1e-12) never drawn
    tolerance = 4 * torch.sqrt(probs * (1 - probs) / n)  # 4 standard errors
    assert torch.all((counts / n - probs).abs() <= tolerance + 1e-9)
    assert torch.allclose(logprob, torch.log(probs.clamp(min=1e-12))[action])
    assert torch.allclose(entropy, torch.full((n,), -(probs[probs > 0] * probs[probs > 0].log()).sum().item()), atol=1e-5)
