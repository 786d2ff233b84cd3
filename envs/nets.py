"""Network parts shared by the envs' networks: layer init and an LSTM that resets at episode starts.

Every network of `envs` follows one calling convention (DESIGN.md), so an algorithm script does not care
which env it runs. Inputs are flattened time-major batches: a rollout step is T=1 row per env copy, a
training sequence is T rows per copy laid out as [T * N] (row t * N + n is step t of copy n).
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.distributions import Categorical, Distribution


def layer_init(layer: nn.Module, gain: float = math.sqrt(2), bias: float = 0.0) -> nn.Module:
    """Orthogonal weights, constant bias (SPEC 1: gain sqrt(2) hidden, 0.01 policy, 1 value)."""
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.constant_(layer.bias, bias)
    return layer


# Segments whose lengths are within this factor of each other share one padded nn.LSTM call: the
# padding waste stays under 1/factor while the number of calls stays small (measured best on CPU).
BUCKET_LENGTH_FACTOR = 0.75


class MaskedLSTMRecurrence(torch.autograd.Function):
    """The recurrence of an LSTM over a whole rollout, with the state zeroed where `keep` is 0, and its
    hand-written backward pass (backpropagation through time).

    Inputs: `projected` [T, N, 4H], the input projection W_ih x + b_ih + b_hh of every step (one large
    matmul outside); `weight_hh` [4H, H]; the initial state h0, c0 [N, H]; `keep` [T, N, 1], 0 where an
    episode starts at step t. Output: h [T, N, H]. Gates in PyTorch's order i, f, g, o.

    Autograd over a Python loop of LSTM steps is slow on CPU: the backward of each step's slice of
    `projected` allocates and adds a gradient the size of all of it. Here the forward keeps the activated gates, the backward runs only the small
    sequential part step by step (one [N, 4H] x [4H, H] matmul and a few elementwise ops) and forms the
    weight gradient in one [H, T * N] x [T * N, 4H] matmul. Its cost does not depend on where the
    episodes end. tests/test_nets.py checks it against stepping nn.LSTM's cell and with gradcheck.
    """

    @staticmethod
    def forward(ctx, projected, weight_hh, h0, c0, keep):
        steps, n, four_h = projected.shape
        hidden = four_h // 4
        gates = torch.empty_like(projected)
        c_all = projected.new_empty(steps, n, hidden)
        h_all = projected.new_empty(steps, n, hidden)
        h_in = projected.new_empty(steps, n, hidden)  # the state entering step t, after any reset
        c_in = projected.new_empty(steps, n, hidden)
        weight_t = weight_hh.t().contiguous()  # [H, 4H]: the faster layout for h @ W_hh^T
        h, c = h0, c0
        for t in range(steps):
            torch.mul(h, keep[t], out=h_in[t])
            torch.mul(c, keep[t], out=c_in[t])
            g = torch.addmm(projected[t], h_in[t], weight_t, out=gates[t])
            g[:, : 2 * hidden].sigmoid_()  # i, f
            g[:, 2 * hidden : 3 * hidden].tanh_()  # g
            g[:, 3 * hidden :].sigmoid_()  # o
            c = torch.addcmul(g[:, hidden : 2 * hidden] * c_in[t], g[:, :hidden], g[:, 2 * hidden : 3 * hidden], out=c_all[t])
            h = torch.mul(g[:, 3 * hidden :], torch.tanh(c), out=h_all[t])
        ctx.save_for_backward(weight_hh, gates, c_all, h_in, c_in, keep)
        return h_all

    @staticmethod
    def backward(ctx, grad_h):
        weight_hh, gates, c_all, h_in, c_in, keep = ctx.saved_tensors
        steps, n, four_h = gates.shape
        hidden = four_h // 4
        i, f, g, o = gates.view(steps, n, 4, hidden).unbind(2)
        tanh_c = torch.tanh(c_all)
        # Everything that does not depend on the incoming gradient, for all steps at once:
        # dc_t += dh_t * dc_from_dh; d(i, f, g pre-activations) = dc_t * ifg_factors; d(o) = dh_t * o_factor.
        dc_from_dh = o * (1 - tanh_c * tanh_c)
        ifg_factors = torch.stack([g * i * (1 - i), c_in * f * (1 - f), i * (1 - g * g)], 2)
        o_factor = tanh_c * o * (1 - o)
        dc_carry = f * keep
        grad_gates = torch.empty_like(gates)
        grad_gates_split = grad_gates.view(steps, n, 4, hidden)
        dh_carry = gates.new_zeros(n, hidden)
        dc = gates.new_zeros(n, hidden)
        for t in reversed(range(steps)):
            dh = grad_h[t] + dh_carry
            dc = torch.addcmul(dc, dh, dc_from_dh[t])
            torch.mul(dc.unsqueeze(1), ifg_factors[t], out=grad_gates_split[t, :, :3])
            torch.mul(dh, o_factor[t], out=grad_gates_split[t, :, 3])
            dh_carry = torch.mm(grad_gates[t], weight_hh).mul_(keep[t])
            dc = dc * dc_carry[t]
        grad_weight_hh = grad_gates.view(steps * n, four_h).t() @ h_in.view(steps * n, hidden)
        return grad_gates, grad_weight_hh, dh_carry, dc, None


class ResettableLSTM(nn.Module):
    """An LSTM whose state is zeroed before every step marked `done` (the first step of an episode).

    `forward(x, state, done)` takes x [T * N, F], state (h, c) each [1, N, H] and done [T * N].
    For T = 1 (acting in a rollout) it is one LSTM step and returns the new state. For T > 1 (training on
    a whole rollout) every episode segment becomes a row of its own, zero-initialised except the first
    segment of each copy, which starts from `state`; segments of similar length are padded into one
    batch and run by one fused `nn.LSTM` call, and the valid steps are gathered back. This computes the
    same outputs as stepping T times (tests/test_nets.py checks it) several times faster on CPU. With
    `project_inputs_first`, the T > 1 path instead projects all inputs in one matmul and runs the
    recurrence with `MaskedLSTMRecurrence`: faster when the input is far wider than the state (the maze
    teacher); for the student's narrow input both cost the same within 10%. The state after a training
    sequence is never needed, so both paths return None for it.
    """

    def __init__(self, input_size: int, hidden_size: int, project_inputs_first: bool = False):
        super().__init__()
        self.hidden_size = hidden_size
        self.project_inputs_first = project_inputs_first
        self.lstm = nn.LSTM(input_size, hidden_size)
        for name, param in self.lstm.named_parameters():
            if "bias" in name:
                nn.init.constant_(param, 0.0)
            else:
                nn.init.orthogonal_(param, 1.0)

    def initial_state(self, n: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        zeros = torch.zeros(1, n, self.hidden_size, device=device)
        return zeros, zeros.clone()

    def forward(self, x: torch.Tensor, state, done: torch.Tensor):
        num_copies = state[0].shape[1]
        steps = x.shape[0] // num_copies
        if steps == 1:  # one fused cell step: much cheaper than a one-step nn.LSTM call on CPU
            keep = (1.0 - done.float()).view(num_copies, 1)
            lstm = self.lstm
            h, c = torch.lstm_cell(x, (state[0][0] * keep, state[1][0] * keep), lstm.weight_ih_l0, lstm.weight_hh_l0, lstm.bias_ih_l0, lstm.bias_hh_l0)
            return h, (h.unsqueeze(0), c.unsqueeze(0))
        if self.project_inputs_first:
            lstm = self.lstm
            projected = nn.functional.linear(x, lstm.weight_ih_l0, lstm.bias_ih_l0 + lstm.bias_hh_l0).view(steps, num_copies, -1)
            keep = (1.0 - done.float()).view(steps, num_copies, 1)
            h = MaskedLSTMRecurrence.apply(projected, lstm.weight_hh_l0, state[0][0], state[1][0], keep)
            return h.view(steps * num_copies, self.hidden_size), None
        return self._run_segments(x.view(steps, num_copies, -1), state, done.view(steps, num_copies).bool()), None

    def _run_segments(self, x: torch.Tensor, state, done: torch.Tensor) -> torch.Tensor:
        steps, num_copies = done.shape
        device = x.device
        # Segments in copy-major order (position k = n * steps + t): each is a contiguous run of k.
        starts = done.clone()
        starts[0] = True
        starts = starts.t().reshape(-1)
        segment_start = torch.nonzero(starts).squeeze(1)
        segment_length = torch.diff(segment_start, append=torch.tensor([steps * num_copies], device=device))
        segment_copy, segment_t0 = segment_start // steps, segment_start % steps
        # Initial state per segment: the given state for a copy's first segment (unless it starts an
        # episode), zero for every later segment (index 0 of the padded states below is zero).
        first = (segment_t0 == 0) & ~done[0, segment_copy]
        state_source = torch.where(first, segment_copy + 1, 0)
        h_all = torch.cat([x.new_zeros(1, self.hidden_size), state[0][0]]).index_select(0, state_source)
        c_all = torch.cat([x.new_zeros(1, self.hidden_size), state[1][0]]).index_select(0, state_source)

        # Bucket segments by length; pad each bucket into one [length, segments] batch gathered from
        # the time-major rows of x (row steps * num_copies is a zero row for the padding). Rows are
        # gathered with index_select: its backward (index_add) is ~5x faster on CPU than indexing's.
        x_rows = torch.cat([x.reshape(steps * num_copies, -1), x.new_zeros(1, x.shape[2])])
        longest = segment_length.max().float()
        bucket = torch.floor(torch.log(longest / segment_length.float()) / -math.log(BUCKET_LENGTH_FACTOR)).long()
        outputs, position_of_row, used = [], torch.empty(steps * num_copies, dtype=torch.long, device=device), 0
        for b in torch.unique(bucket).tolist():
            members = torch.nonzero(bucket == b).squeeze(1)
            length = segment_length[members]
            padded_length = int(length.max())
            t = torch.arange(padded_length, device=device).unsqueeze(1)
            valid = t < length.unsqueeze(0)
            rows = (segment_t0[members].unsqueeze(0) + t) * num_copies + segment_copy[members].unsqueeze(0)
            rows = torch.where(valid, rows, steps * num_copies)
            padded = x_rows.index_select(0, rows.reshape(-1)).view(padded_length, len(members), -1)
            bucket_out, _ = self.lstm(padded, (h_all.index_select(0, members).unsqueeze(0), c_all.index_select(0, members).unsqueeze(0)))
            outputs.append(bucket_out.reshape(-1, self.hidden_size))
            slots = torch.arange(used, used + rows.numel(), device=device).view_as(rows)
            position_of_row[rows[valid]] = slots[valid]
            used += rows.numel()
        return torch.cat(outputs).index_select(0, position_of_row)


class RecurrentCategoricalActorCritic(nn.Module):
    """The calling convention of every network, for a recurrent net with a discrete policy.

    A subclass defines `self.lstm` (a ResettableLSTM), `self.actor` (hidden -> logits), `self.critic`
    (hidden -> 1) and `_hidden(obs, state, done) -> (hidden, state)`.
    """

    is_recurrent = True  # PPO keeps each copy's rollout whole: minibatches are split over env copies

    def initial_state(self, n: int, device=None):
        return self.lstm.initial_state(n, device)

    def dist(self, obs: dict, state, done) -> Categorical:
        hidden, _ = self._hidden(obs, state, done)
        return Categorical(logits=self.actor(hidden))

    def dist_and_value(self, obs: dict, state, done):
        """-> the policy distribution and the value, from one pass (for losses that need both)."""
        hidden, _ = self._hidden(obs, state, done)
        return Categorical(logits=self.actor(hidden)), self.critic(hidden).squeeze(-1)

    def get_value(self, obs: dict, state, done) -> torch.Tensor:
        hidden, _ = self._hidden(obs, state, done)
        return self.critic(hidden).squeeze(-1)

    def get_action_and_value(self, obs: dict, state, done, action=None):
        """-> action, log-probability, entropy, value, new state (None after a training sequence)."""
        hidden, state = self._hidden(obs, state, done)
        log_probs = torch.log_softmax(self.actor(hidden), dim=-1)  # Categorical's maths, minus its overhead
        probs = log_probs.exp()
        if action is None:  # inverse-CDF sampling: ~2x cheaper per call on CPU than torch.multinomial
            uniform = torch.rand(len(probs), 1, device=probs.device)
            action = torch.searchsorted(probs.cumsum(-1), uniform, right=True).squeeze(-1).clamp_(max=probs.shape[-1] - 1)
        entropy = -(probs * log_probs).sum(-1)
        logprob = log_probs.gather(-1, action.unsqueeze(-1)).squeeze(-1)
        return action, logprob, entropy, self.critic(hidden).squeeze(-1), state


class FeedForwardActorCritic(nn.Module):
    """The same calling convention for a feed-forward net (CarRacing, walker, their teachers).

    A subclass defines `dist_and_value(obs) -> (distribution, value [B])`. For a continuous action the
    distribution is an `Independent` over the action's dimensions, so `log_prob`, `entropy` and the BC
    KL are sums over them (SPEC 4, BC). There is no state: `initial_state` is None and `state` and
    `done` are ignored, so PPO may draw minibatches from single samples.
    """

    is_recurrent = False

    def initial_state(self, n: int, device=None):
        return None

    def sample(self, dist: Distribution) -> torch.Tensor:
        """A fresh action from the policy (a subclass may keep it inside the support's interior)."""
        return dist.sample()

    def dist(self, obs: dict, state=None, done=None) -> Distribution:
        return self.dist_and_value(obs)[0]

    def get_value(self, obs: dict, state=None, done=None) -> torch.Tensor:
        return self.dist_and_value(obs)[1]

    def get_action_and_value(self, obs: dict, state=None, done=None, action=None):
        """-> action, log-probability, entropy, value, state (always None)."""
        dist, value = self.dist_and_value(obs)
        if action is None:
            action = self.sample(dist)
        return action, dist.log_prob(action), dist.entropy(), value, None
