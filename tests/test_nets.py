"""The fast sequence path of ResettableLSTM computes exactly what stepping the LSTM one step at a time does."""

import torch

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


def test_sequence_path_gradients_reach_the_initial_state_and_inputs():
    torch.manual_seed(3)
    lstm = ResettableLSTM(9, 12, project_inputs_first=True)
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
    """A recurrent net whose policy is the same categorical distribution for every input."""

    def __init__(self, logits: torch.Tensor):
        super().__init__()
        self.lstm = ResettableLSTM(1, 2)
        self.logits = logits
        self.actor = lambda hidden: self.logits.expand(len(hidden), -1)
        self.critic = lambda hidden: hidden[:, :1]

    def _hidden(self, obs, state, done):
        return self.lstm(obs["x"], state, done)


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
