"""Network parts shared by the envs' networks: layer init and an LSTM that resets at episode starts.

Every network of `envs` follows one calling convention, so an algorithm script does not care
which env it runs. Inputs are flattened time-major batches: a rollout step is T=1 row per env copy, a
training sequence is T rows per copy laid out as [T * N] (row t * N + n is step t of copy n).
"""

from __future__ import annotations

import math
import os

import torch
from torch import nn
from torch.distributions import Categorical, Distribution


def layer_init(layer: nn.Module, gain: float = math.sqrt(2), bias: float = 0.0) -> nn.Module:
    """Orthogonal weights, constant bias (gain sqrt(2) hidden, 0.01 policy, 1 value)."""
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.constant_(layer.bias, bias)
    return layer


# The weight from a reset step's input (a feature of 1) into the input and forget gates: it drives their
# pre-activations to about -1e6, where their sigmoids are exactly 0 in float32 (below about -104, however
# the sigmoid is computed) with any state and weights a network could reach, so the state becomes zero.
GATE_SHUTTING_RESET_WEIGHT = -1e6


class ResettableLSTM(nn.Module):
    """An LSTM whose state is zeroed before every step marked `done` (the first step of an episode).

    `forward(x, state, done)` takes x [T * N, F], state (h, c) each [1, N, H] and done [T * N].
    For T = 1 it is one step of torch's LSTM cell and returns the new state. For T > 1 (training on a
    whole rollout) the whole rollout is one fused `nn.LSTM` call: before each episode start after the
    first step a *reset step* is inserted into that copy's sequence, whose only input is an extra
    feature of 1 that drives the input and forget gates to exactly 0, so its cell and hidden state are
    0: the next step starts from a zero state as an episode start must. A copy's sequence grows by its
    number of resets; the sequences are padded at the end to the longest, and the real steps' outputs
    gathered back. Nothing flows back through a reset step: its gates' sigmoids are saturated at 0, so
    their derivatives are 0 too. This computes the same outputs and gradients as stepping T times
    (tests/test_nets.py checks both) 2.6-3.6x faster on CPU, and ~1.3x faster than running each episode
    segment as its own padded sequence. The state after a training sequence is never needed: it returns
    None for it.

    The padded length is T plus the most resets of any copy, a number read from `done`; on a GPU that read
    waits for the device. A caller that runs many passes over one rollout (the PPO update) reads it once
    and gives it as `most_resets` (at least the most episode starts after step 0 of any copy; a larger
    number pads more and changes no output). With it a pass has no host sync and fixed shapes.

    The reset weight joins the input weights in a fresh tensor at every fused call, so on a GPU cuDNN
    copies the weights into one chunk at every call (a few small copies, and its warning). Keeping them in
    one chunk would need W_ih as a strided view beside the reset column, and a strided parameter takes
    foreach Adam off its fast path (fused Adam refuses it): tests/test_nets.py keeps the parameters dense.
    """

    def __init__(self, input_size: int, hidden_size: int):
        super().__init__()
        self.hidden_size = hidden_size
        self.lstm = nn.LSTM(input_size, hidden_size)
        for name, param in self.lstm.named_parameters():
            if "bias" in name:
                nn.init.constant_(param, 0.0)
            else:
                nn.init.orthogonal_(param, 1.0)
        # The reset input's weights: GATE_SHUTTING_RESET_WEIGHT into the input and forget gates (PyTorch's
        # gate order i, f, g, o), nothing into the others.
        reset_weight = torch.zeros(4 * hidden_size, 1)
        reset_weight[: 2 * hidden_size] = GATE_SHUTTING_RESET_WEIGHT
        self.register_buffer("reset_weight", reset_weight, persistent=False)

    def initial_state(self, n: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        zeros = torch.zeros(1, n, self.hidden_size, device=device)
        return zeros, zeros.clone()

    def forward(self, x: torch.Tensor, state, done: torch.Tensor, most_resets: int | None = None):
        num_copies = state[0].shape[1]
        steps = x.shape[0] // num_copies
        if steps == 1:
            keep = (1.0 - done.float()).view(num_copies, 1)
            lstm = self.lstm
            h, c = torch.lstm_cell(x, (state[0][0] * keep, state[1][0] * keep), lstm.weight_ih_l0, lstm.weight_hh_l0, lstm.bias_ih_l0, lstm.bias_hh_l0)
            return h, (h.unsqueeze(0), c.unsqueeze(0))
        return self._run_with_reset_steps(x.view(steps, num_copies, -1), state, done.view(steps, num_copies).bool(), most_resets), None

    def _run_with_reset_steps(self, x: torch.Tensor, state, done: torch.Tensor, most_resets: int | None) -> torch.Tensor:
        steps, num_copies, features = x.shape
        copy = torch.arange(num_copies, device=x.device)
        # Step t of copy n moves to position t + (resets of copy n at steps 1..t); a reset at step t
        # (t > 0) takes the position just before it. An episode start at step 0 zeroes the given state.
        resets = done.clone()
        resets[0] = False
        position = torch.arange(steps, device=x.device).unsqueeze(1) + resets.long().cumsum(0)
        length = steps + (int(resets.sum(0).max()) if most_resets is None else most_resets)  # the padded length
        rows = (position * num_copies + copy).reshape(-1)  # each step's row in the [length * N] layout
        # The row before each step t > 0: its reset step's where it has one, else step t - 1's (whose reset
        # input stays 0). All distinct and as many as the steps, so no shape depends on where episodes start.
        rows_before = ((position[1:] - 1) * num_copies + copy).reshape(-1)
        # Rows are placed with index_copy (its backward is an index_select) and read back with
        # index_select (its backward an index_add): ~5x cheaper on CPU than indexing's accumulate.
        placed = x.new_zeros(length * num_copies, features).index_copy_(0, rows, x.reshape(steps * num_copies, features))
        reset_input = x.new_zeros(length * num_copies, 1).index_copy_(0, rows_before, resets[1:].to(x.dtype).reshape(-1, 1))
        inputs = torch.cat([placed, reset_input], 1).view(length, num_copies, features + 1)
        keep = (~done[0]).to(x.dtype).view(1, num_copies, 1)
        lstm = self.lstm
        weight_ih = torch.cat([lstm.weight_ih_l0, self.reset_weight], 1)
        weights = [weight_ih, lstm.weight_hh_l0, lstm.bias_ih_l0, lstm.bias_hh_l0]
        out, _, _ = torch.lstm(inputs, (state[0] * keep, state[1] * keep), weights, True, 1, 0.0, self.training, False, False)
        return out.reshape(length * num_copies, self.hidden_size).index_select(0, rows)


class RecurrentCategoricalActorCritic(nn.Module):
    """The calling convention of every network, for a recurrent net with a discrete policy.

    A subclass defines `features(obs)`, the LSTM's input [B, F]; `self.lstm`, a ResettableLSTM; and the
    heads `self.actor` (hidden -> logits) and `self.critic` (hidden -> 1). That is the whole network,
    and every method below runs it as written: features, LSTM, heads, a torch Categorical.

    A net class may also name a faster, exact way to run it: `FastPath`, a class of envs/maze/fast_paths.py
    derived from that net's definition. It is looked up in the net's own class only, never inherited,
    so a subclass (a modified net) runs the plain path with no other change; and it serves only nets
    whose modules its `recognises` accepts. Acting (no gradient, no given action) then runs its `act`,
    and a training sequence its `lstm_output` where that returns one, until its check against this plain
    definition fails. The first use of a net prints which path it runs.
    """

    is_recurrent = True  # PPO keeps each copy's rollout whole: minibatches are split over env copies
    FastPath = None

    def __init__(self):
        super().__init__()
        self.fast_path_state = None  # the FastPath instance of this net (its derived weights), made at first use
        self.path_announced = False

    def fast_path(self):
        """This net's fast path, or None if it runs plainly: its own class names none, it does not
        recognise the net's modules, CLEANUED_PLAIN_NETS=1 is set in the environment, or a check of its
        derived weights against this plain net failed."""
        fast_path_class = type(self).__dict__.get("FastPath")
        if fast_path_class is None:
            if getattr(type(self), "FastPath", None) is not None:
                return self.plain_path("a fast path serves only the class it is derived for, not a subclass")
            return self.plain_path("no fast path is derived for it")
        if os.environ.get("CLEANUED_PLAIN_NETS") == "1":
            return self.plain_path("CLEANUED_PLAIN_NETS=1")
        if not fast_path_class.recognises(self):
            return self.plain_path("its modules are not the kinds its fast path is derived from")
        if self.fast_path_state is None:
            self.fast_path_state = fast_path_class()
        return None if self.fast_path_state.mismatch else self.fast_path_state

    def plain_path(self, reason: str) -> None:
        self.announce_path(f"plain path ({reason})")
        return None

    def announce_path(self, path: str, warning: bool = False) -> None:
        """Prints the path this net runs, once, at its first use; and a warning whenever it is given."""
        if warning or not self.path_announced:
            self.path_announced = True
            print(f"{'warning: ' if warning else ''}{type(self).__name__}: {path}", flush=True)

    def initial_state(self, n: int, device=None):
        return self.lstm.initial_state(n, device)

    def lstm_output(self, obs: dict, state, done, most_resets: int | None = None):
        """The LSTM's output [T * N, H] and its new state (None after a training sequence); `most_resets` as
        ResettableLSTM takes it, for a training sequence."""
        fast_path = self.fast_path()
        if fast_path is not None:
            result = fast_path.lstm_output(self, obs, state, done)
            if result is not None:
                return result
        return self.lstm(self.features(obs), state, done, most_resets)

    def dist(self, obs: dict, state, done, most_resets: int | None = None) -> Categorical:
        hidden, _ = self.lstm_output(obs, state, done, most_resets)
        return Categorical(logits=self.actor(hidden))

    def dist_and_value(self, obs: dict, state, done, most_resets: int | None = None):
        """-> the policy distribution and the value, from one pass (for losses that need both)."""
        hidden, _ = self.lstm_output(obs, state, done, most_resets)
        return Categorical(logits=self.actor(hidden)), self.critic(hidden).squeeze(-1)

    def get_value(self, obs: dict, state, done) -> torch.Tensor:
        hidden, _ = self.lstm_output(obs, state, done)
        return self.critic(hidden).squeeze(-1)

    def policy_and_state(self, obs: dict, state, done):
        """An acting step's policy and new state, drawing no action: for a caller that draws each batch's
        actions from a random stream of its own (the held-out evaluation, envs/evaluation.py)."""
        if not torch.is_grad_enabled():
            fast_path = self.fast_path()
            if fast_path is not None:
                stepped = fast_path.policy_and_state(self, obs, state, done)
                if stepped is not None:
                    return stepped
        hidden, state = self.lstm_output(obs, state, done)
        return Categorical(logits=self.actor(hidden)), state

    def sample(self, dist: Categorical) -> torch.Tensor:
        """A fresh action from the policy."""
        return dist.sample()

    def get_action_and_value(self, obs: dict, state, done, action=None, most_resets: int | None = None):
        """-> action, log-probability, entropy, value, new state (None after a training sequence)."""
        if action is None and not torch.is_grad_enabled():
            fast_path = self.fast_path()
            if fast_path is not None:
                acted = fast_path.act(self, obs, state, done)
                if acted is not None:
                    return acted
        hidden, state = self.lstm_output(obs, state, done, most_resets)
        dist = Categorical(logits=self.actor(hidden))
        if action is None:
            action = self.sample(dist)
        return action, dist.log_prob(action), dist.entropy(), self.critic(hidden).squeeze(-1), state


class FeedForwardActorCritic(nn.Module):
    """The same calling convention for a feed-forward net (CarRacing, walker, their teachers).

    A subclass defines `dist_and_value(obs) -> (distribution, value [B])`. For a continuous action the
    distribution is an `Independent` over the action's dimensions, so `log_prob` and the BC KL are sums
    over them. The entropy (the PPO loss's) is the distribution's own `entropy()`, as each net's
    reference reduces it: the walker's Gaussian sums over the dimensions, CarRacing's Beta averages
    (its BetaPolicy). There is no state: `initial_state` is None and `state` and `done` are ignored,
    so PPO may draw minibatches from single samples.
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

    def policy_and_state(self, obs: dict, state=None, done=None):
        """The policy and the state (always None), drawing no action (envs/evaluation.py draws it)."""
        return self.dist(obs), None

    def get_action_and_value(self, obs: dict, state=None, done=None, action=None):
        """-> action, log-probability, entropy, value, state (always None)."""
        dist, value = self.dist_and_value(obs)
        if action is None:
            action = self.sample(dist)
        return action, dist.log_prob(action), dist.entropy(), value, None
