"""Faster, exact ways to run the maze's two networks, derived from their plain definitions in envs/maze/env.py.

`MazeStudent` and `MazeTeacher` are written plainly (nn.Conv2d, nn.Linear, an LSTM with episode resets,
torch.distributions.Categorical): that is their definition, and what any modified net runs. This module
is the only place that knows how to run them faster. Each class here serves one network class, which
names it (`FastPath = ...` in its body); envs/nets.py uses it only for that exact class, so a subclass
(a modified net) runs the plain path with no other change, and only while `recognises(net)` finds the
modules the derivation relies on. With CLEANUED_PLAIN_NETS=1 in the environment every net runs plainly.
Each net prints at its first use which path it runs. tests/test_fast_paths.py checks each path against
the plain net.

**Never another function, never stale weights.** A derivation follows the net's modules and weights, but
it assumes the class's `features` as written. So the derived weights are checked whenever they are built:
on a few copies of the step at hand, as they are and with some image cells changed, they must give the
plain net's log-probabilities, value and LSTM state within float tolerance (`FastPath.check`). If they do
not (an edit of `features` that the derivation does not follow, say), a warning names the net and the
difference, and the net runs the plain path from then on. The teacher's training path assumes the same
function: it runs only once a check has passed. The derived weights are rebuilt after every change of
the parameters that autograd or an optimizer sees: a write to a parameter (its version counter: an
in-place op under torch.no_grad(), load_state_dict), a parameter moved (its storage), a step of any
torch.optim optimizer (counted by a global hook: fused Adam writes past the version counters), and a
pass of the net with gradient (a hand-written update through `.data` follows one). A write through
`.data` with none of these is invisible: write under torch.no_grad() instead.

**Acting** (a rollout step: no gradient, no given action) costs more in per-call overhead than in
arithmetic at a batch of 32, so it runs on tensors derived from the parameters once per change of them:
the LSTM's transposed weights with the gates ordered i, f, o, g (the three sigmoids side by side); the
actor's and critic's layers fused into two matmuls; and the input layers, folded as far as they are
linear. The student's conv over its 5x5 view is a linear map from 75 inputs to 144, so it becomes a
[75, 144] matrix (found by running the conv on unit images), and its direction embedding times the
LSTM's input weights plus the LSTM's biases a [4, 4H] table of gate inputs, one row per direction. The
teacher's grid changes in at most one cell per step, so the conv features' share of its gates is
carried from step to step and only the conv windows over a changed cell are recomputed
(envs/maze/sparse_projection.py); its time embedding becomes a table of gate inputs too. The action is drawn
as the plain path's Categorical.sample draws it, with torch.multinomial on the same probabilities, so
both paths draw the same actions from the same random stream. The held-out evaluation's step
(`policy_and_state`: the policy and new state, the action drawn by envs/evaluation.py) runs on the same
derived weights.

**Training** the teacher (a whole rollout, T > 1) computes the LSTM's input projection from the changed
cells only (envs/maze/sparse_projection.py), then the recurrence with `MaskedLSTMRecurrence`. The student
trains on the plain path: at a training batch its conv costs what the folded matrix does.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.distributions import Categorical
from torch.optim.optimizer import register_optimizer_step_post_hook

from envs.maze.sparse_projection import RunningConvGates, sparse_gate_inputs
from envs.nets import ResettableLSTM

# The check of derived weights runs on the first CHECK_COPIES copies of a step, as they are and again with
# CHECK_CELLS cells of each image set to random values and their episode starts flipped. An output may
# differ from the plain net's by CHECK_TOLERANCE times (1 + its largest magnitude there): float rounding
# stays under a hundredth of that (at the initial weights and at 3 to 10 times them), an edit of the
# features far above it (dropping the conv's ReLU moves the LSTM state by 5-15% in the student, 4-8% in
# the teacher).
CHECK_COPIES = 4
CHECK_CELLS = 3
CHECK_TOLERANCE = 1e-4

optimizer_steps = 0  # the steps taken by any torch.optim optimizer in this process


def count_optimizer_step(optimizer, args, kwargs) -> None:
    global optimizer_steps
    optimizer_steps += 1


register_optimizer_step_post_hook(count_optimizer_step)


def check_rows(obs: dict, state, done: torch.Tensor):
    """The rows a check runs on: the first CHECK_COPIES copies of an acting step as they are, then again
    with CHECK_CELLS cells of each image set to random values (up to the image's largest; from a generator
    of their own, so the net's random stream is untouched) and their episode starts flipped."""
    copies = min(CHECK_COPIES, len(done))
    images = obs["image"][:copies]
    generator = torch.Generator(images.device).manual_seed(0)
    cells = images.reshape(copies, -1, images.shape[-1]).clone()
    changed = torch.randint(cells.shape[1], (copies, CHECK_CELLS), generator=generator, device=images.device)
    values = torch.randint(int(images.max()) + 1, (copies, CHECK_CELLS, cells.shape[2]), generator=generator, device=images.device)
    cells[torch.arange(copies, device=images.device).unsqueeze(1), changed] = values.to(cells.dtype)
    rows = {key: torch.cat([value[:copies], value[:copies]]) for key, value in obs.items()}
    rows["image"] = torch.cat([images, cells.view_as(images)])
    rows_state = tuple(torch.cat([part[:, :copies], part[:, :copies]], 1) for part in state)
    return rows, rows_state, torch.cat([done[:copies], (done[:copies] == 0).to(done.dtype)])


class FastPath:
    """What both nets' fast paths share: the derived weights, rebuilt after any change of the net's
    parameters (the module's docstring) and checked against the plain net at every build; and the plain
    path for good once a check fails (`mismatch`, which envs/nets.py reads).

    A subclass gives `recognises(net)`, `derive(net, obs)` (the derived weights: `lstm_and_head_weights`'s
    and its own) and `gate_inputs(weights, obs)` (W_ih x + b_ih + b_hh [N, 4H], in the gate order of
    `lstm_and_head_weights`); and `fast_lstm_output` if it has a faster training path."""

    def __init__(self):
        self.children, self.params, self.key, self.weights = None, None, None, None
        self.checked = False  # whether a check has passed: the net computes what its fast path was derived from
        self.mismatch = None  # why the net runs the plain path for good, once a check failed

    def act(self, net, obs: dict, state, done: torch.Tensor):
        """An acting step -> action, log-probability, entropy, value, new state; None if the check of
        rebuilt weights fails now (the plain path then runs it)."""
        weights = self.checked_weights(net, obs, state, done)
        if weights is None:
            return None
        return act_from_gate_inputs(self.gate_inputs(weights, obs), state, done, weights)

    def policy_and_state(self, net, obs: dict, state, done: torch.Tensor):
        """An acting step's policy (a Categorical of the normalized log-probabilities) and new state, drawing
        no action; None if the check of rebuilt weights fails now."""
        weights = self.checked_weights(net, obs, state, done)
        if weights is None:
            return None
        log_probs, _, state = step_from_gate_inputs(self.gate_inputs(weights, obs), state, done, weights)
        return Categorical(logits=log_probs), state

    def lstm_output(self, net, obs: dict, state, done: torch.Tensor):
        """A pass that is not an acting step: the LSTM's output and state from a faster training path, or
        None where the plain path runs it. A pass with gradient marks the derived weights stale: the
        weights are about to change, perhaps through `.data`, which no version counter sees."""
        if torch.is_grad_enabled():
            self.key = None
        return self.fast_lstm_output(net, obs, state, done)

    def fast_lstm_output(self, net, obs: dict, state, done: torch.Tensor):
        """No faster training path: the plain one runs."""
        return None

    def checked_weights(self, net, obs: dict, state, done: torch.Tensor):
        """The derived weights of the net's current parameters, rebuilt and checked on this step if any
        changed since the last build; None if that check fails. (The parameters are listed again only
        when one of the net's direct children was replaced: listing them costs more than the rest.)"""
        children = tuple(net.children())
        if children != self.children:
            self.children, self.params = children, list(net.parameters())
        key = [optimizer_steps, obs["image"].shape[1:], *((p.data_ptr(), p._version) for p in self.params)]
        if key != self.key:
            self.key, self.weights = None, None
            with torch.no_grad():
                weights = self.derive(net, obs)
            self.mismatch = self.check(net, weights, obs, state, done)
            if self.mismatch is not None:
                net.announce_path(f"{self.mismatch}; it runs the plain path from now on", warning=True)
                return None
            net.announce_path("fast path (derived from the plain net, checked against it)")
            self.checked, self.key, self.weights = True, key, weights
        return self.weights

    def check(self, net, weights: dict, obs: dict, state, done: torch.Tensor) -> str | None:
        """What differs beyond float tolerance between the derived weights' outputs and the plain net's
        (its features, LSTM and heads, as envs/nets.py runs them) on `check_rows` of this step, or None."""
        rows, rows_state, rows_done = check_rows(obs, state, done)
        with torch.no_grad():
            log_probs, value, (h, c) = step_from_gate_inputs(self.gate_inputs(weights, rows), rows_state, rows_done, weights)
            hidden, (plain_h, plain_c) = net.lstm(net.features(rows), rows_state, rows_done)
            plain = (Categorical(logits=net.actor(hidden)).logits, net.critic(hidden).squeeze(-1), plain_h, plain_c)
        for name, got, expected in zip(("log-probabilities", "values", "LSTM outputs", "LSTM cell states"), (log_probs, value, h, c), plain):
            tolerance = CHECK_TOLERANCE * (1 + expected.nan_to_num().abs().max().item())
            if not torch.isclose(got, expected, rtol=0, atol=tolerance, equal_nan=True).all():
                difference = (got - expected).abs().max().item()
                return (f"its fast path's {name} differ from the plain net's by {difference:.2g} (tolerance {tolerance:.2g}): "
                        "the net computes something its fast path was not derived from")
        return None


def is_two_layer_tanh_head(head: nn.Module) -> bool:
    return type(head) is nn.Sequential and [type(layer) for layer in head] == [nn.Linear, nn.Tanh, nn.Linear]


def recurrent_parts_recognised(net: nn.Module) -> bool:
    """The LSTM and the heads `lstm_and_head_weights` derives from: a ResettableLSTM, and the actor and
    critic each Linear, Tanh, Linear."""
    return type(net.lstm) is ResettableLSTM and is_two_layer_tanh_head(net.actor) and is_two_layer_tanh_head(net.critic)


def lstm_and_head_weights(net: nn.Module) -> dict[str, torch.Tensor]:
    """W_ih^T [F, 4H], W_hh^T [H, 4H] and b_ih + b_hh [4H], their gate columns reordered to i, f, o, g;
    and the heads as two matmuls: the actor's and critic's first layers side by side, hidden -> [actor |
    critic], then a block-diagonal matrix -> [logits | value] (its zeros add nothing)."""
    lstm = net.lstm.lstm
    order = torch.arange(4 * lstm.hidden_size, device=lstm.weight_ih_l0.device).view(4, -1)[[0, 1, 3, 2]].reshape(-1)
    actor_in, actor_out, critic_in, critic_out = net.actor[0], net.actor[2], net.critic[0], net.critic[2]
    heads = (torch.cat([actor_in.weight, critic_in.weight]).t().contiguous(), torch.cat([actor_in.bias, critic_in.bias]),
             torch.block_diag(actor_out.weight, critic_out.weight).t().contiguous(), torch.cat([actor_out.bias, critic_out.bias]))
    return {"lstm_input": lstm.weight_ih_l0.t().index_select(1, order), "lstm_recurrent": lstm.weight_hh_l0[order].t().contiguous(),
            "lstm_bias": (lstm.bias_ih_l0 + lstm.bias_hh_l0)[order], "heads": heads}


def step_from_gate_inputs(gate_inputs: torch.Tensor, state, done: torch.Tensor, weights: dict):
    """An acting step from the input's share of the gates, W_ih x + b_ih + b_hh [N, 4H] in the gate order
    of `lstm_and_head_weights` (it is overwritten): the state zeroed where an episode starts, then
    `lstm_cell_and_heads`. -> the normalized log-probabilities [N, A], value, new state."""
    reset = done.view(-1, 1).bool()
    h, c = state[0][0], state[1][0]
    # Zero the state of copies whose episode starts. On a CPU, most steps have none, and asking costs less
    # than the fill; on a GPU the question would wait for the device, so the fill always runs there.
    if reset.device.type != "cpu" or reset.any():
        h, c = h.masked_fill(reset, 0.0), c.masked_fill(reset, 0.0)
    log_probs, value, h, c = lstm_cell_and_heads(gate_inputs, h, c, weights)
    return log_probs, value, (h.unsqueeze(0), c.unsqueeze(0))


def lstm_cell_and_heads(gate_inputs: torch.Tensor, h: torch.Tensor, c: torch.Tensor, weights: dict):
    """torch's LSTM cell in place on the gate inputs (overwritten), from the state h, c [N, H], and the
    fused heads. -> the normalized log-probabilities [N, A] (as Categorical(logits=...) holds them),
    value [N], new h and c [N, H]."""
    hidden_size = weights["lstm_recurrent"].shape[0]
    gates = gate_inputs.addmm_(h, weights["lstm_recurrent"])
    gates[:, : 3 * hidden_size].sigmoid_()
    gates[:, 3 * hidden_size :].tanh_()
    i, f, o, g = gates.chunk(4, 1)
    c = torch.addcmul(f * c, i, g)
    h = o * torch.tanh(c)
    first, first_bias, second, second_bias = weights["heads"]
    out = torch.addmm(second_bias, torch.addmm(first_bias, h, first).tanh_(), second)
    logits, value = out[:, :-1], out[:, -1]
    return logits - logits.logsumexp(-1, keepdim=True), value, h, c


def act_from_gate_inputs(gate_inputs: torch.Tensor, state, done: torch.Tensor, weights: dict):
    """`step_from_gate_inputs`, then Categorical's sampling and maths. -> action, log-probability,
    entropy, value, new state."""
    log_probs, value, state = step_from_gate_inputs(gate_inputs, state, done, weights)
    probs = torch.softmax(log_probs, -1)  # Categorical's probabilities, which its sample() draws from
    action = torch.multinomial(probs, 1, True).squeeze(1)
    entropy = -(probs * log_probs).sum(-1)
    logprob = log_probs.gather(-1, action.unsqueeze(-1)).squeeze(-1)
    return action, logprob, entropy, value, state


class MazeStudentFastPath(FastPath):
    """Acting for envs.maze.MazeStudent on the folded weights described in the module's docstring."""

    @staticmethod
    def recognises(net: nn.Module) -> bool:
        return type(net.conv) is nn.Conv2d and type(net.direction_embed) is nn.Linear and recurrent_parts_recognised(net)

    @staticmethod
    def gate_inputs(weights: dict, obs: dict) -> torch.Tensor:
        image = obs["image"]
        view = torch.addmm(weights["view_bias"], image.reshape(len(image), -1).float(), weights["view_matrix"]).relu_()
        return weights["direction_gates"].index_select(0, obs["direction"].long()).addmm_(view, weights["view_input"])

    @staticmethod
    def derive(net, obs: dict) -> dict[str, torch.Tensor]:
        """The conv as a matrix on the raw image flattened as (y, x, channel) (the image scale folded in)
        and its output for an all-zero image (the bias), both with the outputs flattened as `features`
        flattens them; the LSTM input weights of the view's features; and the direction's gate inputs,
        its embedding of each one-hot times its LSTM input weights plus the LSTM's biases."""
        weights = lstm_and_head_weights(net)
        image_shape = obs["image"].shape[1:]
        pixels = math.prod(image_shape)
        like_weight = {"dtype": net.conv.weight.dtype, "device": net.conv.weight.device}
        unit_images = torch.cat([torch.eye(pixels, **like_weight), torch.zeros(1, pixels, **like_weight)]).view(pixels + 1, *image_shape)
        outputs = net.conv(unit_images.permute(0, 3, 1, 2) / net.image_scale).flatten(1)
        view_bias = outputs[-1]
        lstm_input = weights.pop("lstm_input")
        view_size = len(view_bias)
        directions = net.direction_embed(torch.eye(net.direction_embed.in_features, device=view_bias.device))
        direction_gates = torch.addmm(weights.pop("lstm_bias"), directions, lstm_input[view_size:])
        return {**weights, "view_matrix": outputs[:-1] - view_bias, "view_bias": view_bias,
                "view_input": lstm_input[:view_size].contiguous(), "direction_gates": direction_gates}


class MazeTeacherFastPath(FastPath):
    """Acting and training for envs.maze.MazeTeacher from the cells of the grid that changed (the module's
    docstring). Its reference image, whose conv features' share of the gates is computed densely, is the
    first image of the step its weights are derived on: every teacher episode starts from the same empty
    grid.

    Both paths read W_ih^T's conv rows, so their first use stores the teacher's 22M W_ih transposed (the
    same values and shape, strides (1, 4H)): the sparse products then read a view and return the
    gradient in that layout, with no transposed copy of it in either direction."""

    @staticmethod
    def recognises(net: nn.Module) -> bool:
        conv = net.conv
        if type(conv) is not nn.Sequential or [type(layer) for layer in conv] != [nn.Conv2d, nn.ReLU, nn.Flatten]:
            return False
        conv = conv[0]
        plain_window = conv.stride == (1, 1) and conv.padding == (0, 0) and conv.dilation == (1, 1) and conv.groups == 1
        square_window = conv.kernel_size[0] == conv.kernel_size[1] and conv.bias is not None
        return plain_window and square_window and type(net.time_embed) is nn.Linear and recurrent_parts_recognised(net)

    @staticmethod
    def store_input_weights_transposed(net) -> None:
        weight_ih = net.lstm.lstm.weight_ih_l0
        if weight_ih.stride(0) != 1:
            weight_ih.data = weight_ih.data.t().contiguous().t()

    def fast_lstm_output(self, net, obs: dict, state, done: torch.Tensor):
        """A training sequence (T > 1): the LSTM's output [T * N, H] and None (its final state is never
        needed); None for one step, if no check has passed yet and the check on the sequence's first
        step fails, or if too many cells change for the sparse projection to pay."""
        num_copies = state[0].shape[1]
        images = obs["image"]
        if len(images) == num_copies:
            return None
        if not self.checked and self.checked_weights(net, {k: v[:num_copies] for k, v in obs.items()}, state, done[:num_copies]) is None:
            return None
        self.store_input_weights_transposed(net)
        lstm = net.lstm.lstm
        projected = sparse_gate_inputs(net.conv[0], net.image_scale, images[0], images, net.dense_features(obs),
                                       lstm.weight_ih_l0, lstm.bias_ih_l0 + lstm.bias_hh_l0, num_copies)
        if projected is None:
            return None
        steps = len(images) // num_copies
        keep = (1.0 - done.float()).view(steps, num_copies, 1)
        h = MaskedLSTMRecurrence.apply(projected.view(steps, num_copies, -1), lstm.weight_hh_l0, state[0][0], state[1][0], keep)
        return h.view(steps * num_copies, lstm.hidden_size), None

    def act(self, net, obs: dict, state, done: torch.Tensor):
        self.store_input_weights_transposed(net)
        return super().act(net, obs, state, done)

    def check(self, net, weights: dict, obs: dict, state, done: torch.Tensor) -> str | None:
        """FastPath's check; then the running conv gates forget the check's images."""
        mismatch = super().check(net, weights, obs, state, done)
        weights["running_conv_gates"].start_over()
        return mismatch

    @staticmethod
    def gate_inputs(weights: dict, obs: dict) -> torch.Tensor:
        gate_inputs = weights["running_conv_gates"](obs["image"])
        return gate_inputs.addmm_(obs["noise"].float(), weights["noise_input"]).add_(weights["time_gates"].index_select(0, obs["time"].long()))

    @staticmethod
    def derive(net, obs: dict) -> dict:
        """The running conv gates (W f(I) per copy, on W_ih^T's conv rows as [C, P, 4H]); the time's gate
        inputs, its embedding of each one-hot times its LSTM input weights plus the LSTM's biases
        [num_steps, 4H]; and the noise's LSTM input weights."""
        reference = obs["image"][0].clone()  # a copy: the caller may reuse its buffer
        weights = lstm_and_head_weights(net)
        lstm_input = weights.pop("lstm_input")
        time_size = net.time_embed.out_features
        conv = net.conv[0]
        reference_features = net.conv(reference.permute(2, 0, 1).unsqueeze(0).to(conv.weight) / net.image_scale)[0]
        conv_size = len(reference_features)
        conv_weight_t = lstm_input[:conv_size].view(conv.out_channels, -1, lstm_input.shape[1])
        running = RunningConvGates(conv, net.image_scale, reference, conv_weight_t, reference_features @ lstm_input[:conv_size])
        times = net.time_embed(torch.eye(net.time_embed.in_features, device=lstm_input.device))
        time_gates = torch.addmm(weights.pop("lstm_bias"), times, lstm_input[conv_size : conv_size + time_size])
        return {**weights, "running_conv_gates": running, "time_gates": time_gates, "noise_input": lstm_input[conv_size + time_size :]}


class MaskedLSTMRecurrence(torch.autograd.Function):
    """The recurrence of an LSTM over a whole rollout, with the state zeroed where `keep` is 0, and its
    hand-written backward pass (backpropagation through time).

    Inputs: `projected` [T, N, 4H], the input projection W_ih x + b_ih + b_hh of every step (computed
    outside: for the teacher, sparsely); `weight_hh` [4H, H]; the initial state h0, c0 [N, H]; `keep`
    [T, N, 1], 0 where an episode starts at step t. Output: h [T, N, H]. Gates in PyTorch's order i, f,
    g, o.

    Autograd over a Python loop of LSTM steps is slow on CPU: the backward of each step's slice of
    `projected` allocates and adds a gradient the size of all of it. Here the forward keeps the activated
    gates, the backward runs only the small sequential part step by step (one [N, 4H] x [4H, H] matmul
    and a few elementwise ops) and forms the weight gradient in one [H, T * N] x [T * N, 4H] matmul. Its
    cost does not depend on where the episodes end.
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
