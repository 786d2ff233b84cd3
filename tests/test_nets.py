"""The sequence path of ResettableLSTM computes exactly what stepping the LSTM one step at a time does."""

import torch

from envs.nets import ResettableLSTM


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
    lstm = ResettableLSTM(9, 12)
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


def test_a_given_padding_gives_the_same_sequence_pass():
    """The PPO update reads the most resets of any copy once and gives it as `most_resets`: the same outputs and
    gradients as the LSTM reading it from `done` itself, bit for bit; a larger bound only pads more at the end."""
    torch.manual_seed(4)
    lstm = ResettableLSTM(6, 10)
    steps, copies = 20, 5
    x = torch.randn(steps * copies, 6)
    done = (torch.rand(steps * copies) < 0.2).float()
    most_resets = int(done.view(steps, copies)[1:].sum(0).max())
    assert most_resets >= 2
    passes = []
    for given in (None, most_resets, most_resets + 7):
        lstm.zero_grad()
        out, _ = lstm(x, lstm.initial_state(copies), done, given)
        out.square().sum().backward()
        passes.append([out.detach()] + [p.grad.clone() for p in lstm.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(passes[0], passes[1]))
    assert all(torch.allclose(a, b, atol=1e-5) for a, b in zip(passes[0], passes[2]))


def test_the_parameters_stay_dense_for_foreach_and_fused_adam():
    """Each LSTM parameter is a dense tensor, as foreach Adam's fast path needs (one strided parameter sends all of
    its group's foreach ops to the per-tensor loop; fused Adam refuses it on a GPU): after construction, after
    load_state_dict and after optimizer steps. Why the weights are not one cuDNN chunk: ResettableLSTM's docstring."""
    torch.manual_seed(5)
    lstm = ResettableLSTM(7, 12)
    lstm.load_state_dict(ResettableLSTM(7, 12).state_dict())
    optimizer = torch.optim.Adam(lstm.parameters(), lr=1e-3, foreach=True)
    for _ in range(2):
        out, _ = lstm(torch.randn(5 * 3, 7), lstm.initial_state(3), torch.zeros(5 * 3))
        optimizer.zero_grad()
        out.sum().backward()
        optimizer.step()
    for param in lstm.parameters():
        assert param.is_contiguous()
