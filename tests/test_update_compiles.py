"""The PPO update's minibatch step compiles whole: torch.compile(fullgraph=True) of the scripts' `ppo_loss` (the
net's pass and the loss) raises at any graph break, so a host sync in the step (an `.item()`, a Python `if` on a
tensor, a shape read from the data) fails here. Over several updates on fresh rollouts it compiles once
(error_on_recompile). What is compiled: `ppo_loss`, whose backward AOTAutograd traces with it, so `loss.backward()`
runs a compiled graph too; clipping and the optimizer step stay eager (torch compiles an optimizer's step on its
own). The backend is aot_eager: dynamo's capture and AOTAutograd's joint forward and backward trace, where breaks
and data-dependent shapes show, without Inductor's code generation (a GPU's concern, minutes of C++ here).

Settings a compiled GPU run needs as well: distributions unchecked (envs/runs.py sets it; each check waits for a
GPU), `torch._dynamo.config.allow_rnn` (dynamo declines modules holding an nn.LSTM, and ResettableLSTM keeps one as
its parameters' holder, for the checkpoints' names), and the LSTM's padding fixed per rollout shape: here its bound,
T - 1 resets. The scripts read the exact number once per update instead, which would compile once per number.

plr.py's ppo_loss stands for accel.py's, paired.py's and paired_hient.py's, paired_bc.py's for paired_evo.py's
(tests/test_duplicated_helpers.py holds the copies equal)."""

from __future__ import annotations

import copy
import types

import pytest
import torch
from torch._dynamo.utils import counters

import paired_bc
import plr
from envs.maze.env import MazeStudent

STEPS, COPIES = 4, 3  # a short rollout: the compile unrolls the LSTM over its padded length
FIXED_PADDING = {"most_resets": STEPS - 1}  # the bound for any rollout of STEPS steps


def small_student(seed: int) -> MazeStudent:
    torch.manual_seed(seed)
    return MazeStudent(hidden_size=8, conv_channels=2)


def rollout_storage():
    """A rollout's storage as the scripts' Rollout holds it (time-major [T, N, ...]), with advantages and returns."""
    storage = types.SimpleNamespace(
        obs={"image": torch.zeros(STEPS, COPIES, 5, 5, 3, dtype=torch.uint8), "direction": torch.zeros(STEPS, COPIES, dtype=torch.long)},
        actions=torch.zeros(STEPS, COPIES, dtype=torch.long), logprobs=torch.zeros(STEPS, COPIES), values=torch.zeros(STEPS, COPIES),
        episode_starts=torch.zeros(STEPS, COPIES))
    return storage, torch.zeros(STEPS, COPIES), torch.zeros(STEPS, COPIES)


def fill_rollout(storage, advantages, returns, seed: int) -> None:
    """A fresh rollout in place (as collect_rollout refills its storage): new views, actions, values and episode starts."""
    generator = torch.Generator().manual_seed(seed)
    storage.obs["image"].copy_(torch.randint(0, 11, storage.obs["image"].shape, generator=generator))
    storage.obs["direction"].copy_(torch.randint(0, 4, (STEPS, COPIES), generator=generator))
    storage.actions.copy_(torch.randint(0, 7, (STEPS, COPIES), generator=generator))
    storage.logprobs.copy_(-1.5 - torch.rand(STEPS, COPIES, generator=generator))
    storage.values.copy_(torch.randn(STEPS, COPIES, generator=generator))
    storage.episode_starts.copy_((torch.rand(STEPS, COPIES, generator=generator) < 0.4).float())
    storage.episode_starts[0] = 1.0
    advantages.copy_(torch.randn(STEPS, COPIES, generator=generator))
    returns.copy_(torch.randn(STEPS, COPIES, generator=generator))


@pytest.fixture
def compiling(monkeypatch):
    """Dynamo fresh, distributions unchecked, nn.LSTM holders traced, a recompilation an error."""
    monkeypatch.setattr(torch.distributions.Distribution, "_validate_args", False)
    torch._dynamo.reset()
    counters.clear()
    with torch._dynamo.config.patch(allow_rnn=True, error_on_recompile=True):
        yield
    torch._dynamo.reset()


def train_compiled(loss_of, agent, storage, advantages, returns, updates: int, epochs: int) -> None:
    """Updates on fresh rollouts, each `epochs` steps of the compiled loss, its backward and Adam's step; the compiled
    loss and statistics must equal the plain call's at each step. The net has run once before, as it acts in the
    rollout before its first update (its first use sets up its fast path and prints which path it runs)."""
    loss_of()
    compiled = torch.compile(loss_of, fullgraph=True, backend="aot_eager")
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-3)
    for update in range(updates):
        fill_rollout(storage, advantages, returns, seed=update)
        for _ in range(epochs):
            loss, stats = compiled()
            plain_loss, plain_stats = loss_of()
            assert torch.allclose(loss, plain_loss, atol=1e-6) and torch.allclose(stats, plain_stats, atol=1e-6)
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
            optimizer.step()
    assert counters["stats"]["unique_graphs"] == 1 and counters["stats"]["calls_captured"] > 0  # compiled, once
    assert not counters["graph_break"]


def test_the_plain_update_step_compiles_whole_and_once(compiling):
    agent = small_student(0)
    storage, advantages, returns = rollout_storage()
    state = agent.initial_state(COPIES)
    args = plr.paper_args(num_envs=COPIES, num_steps=STEPS)

    def loss_of():
        return plr.ppo_loss(agent, storage, advantages, returns, slice(None), state, FIXED_PADDING, args.ent_coef, args)

    train_compiled(loss_of, agent, storage, advantages, returns, updates=3, epochs=2)


def test_the_cloning_update_step_compiles_whole_and_once(compiling):
    """paired_bc.py's step with a clone target: the target's pass (no gradient) and the KL join the graph."""
    agent, target = small_student(0), small_student(1)
    storage, advantages, returns = rollout_storage()
    state = agent.initial_state(COPIES)
    args = paired_bc.paper_args(num_envs=COPIES, num_steps=STEPS)

    def loss_of():
        return paired_bc.ppo_loss(agent, storage, advantages, returns, slice(None), state, FIXED_PADDING, 0.01, args, target, 1.0)

    train_compiled(loss_of, agent, storage, advantages, returns, updates=2, epochs=1)
    assert loss_of()[1][-1] > 0  # the cloning KL was part of the loss


def test_a_step_that_reads_its_padding_breaks_the_graph(compiling):
    """The control: without the padding given, the LSTM reads it from the episode starts (a host sync) and sizes
    its sequence by it, a shape that depends on the data: the compile refuses it. The update's single read before
    its epochs is what spares its steps this."""
    agent = small_student(0)
    storage, advantages, returns = rollout_storage()
    fill_rollout(storage, advantages, returns, seed=0)
    args = plr.paper_args(num_envs=COPIES, num_steps=STEPS)
    step = torch.compile(plr.ppo_loss, fullgraph=True, backend="aot_eager")
    with pytest.raises((torch._dynamo.exc.Unsupported, torch._dynamo.exc.UserError), match="data-dependent"):
        step(agent, storage, advantages, returns, slice(None), agent.initial_state(COPIES), {}, args.ent_coef, args)


def test_foreach_adam_takes_the_same_steps_as_the_for_loop():
    """Adam's multi-tensor (foreach) step, a GPU's default, changes the student's weights bit for bit as the
    per-parameter loop, the CPU's default, over PPO updates of the plain step. (Fused Adam is 4-5x faster on this
    CPU but rounds differently, by about 1e-8 a step: the scripts keep the default.)"""
    storage, advantages, returns = rollout_storage()
    args = plr.paper_args(num_envs=COPIES, num_steps=STEPS)
    weights = []
    for foreach in (False, True):
        agent = small_student(0)
        state = agent.initial_state(COPIES)
        optimizer = torch.optim.Adam(agent.parameters(), lr=1e-3, eps=1e-5, foreach=foreach)
        for update in range(3):
            fill_rollout(storage, advantages, returns, seed=update)
            for _ in range(2):
                loss, _ = plr.ppo_loss(agent, storage, advantages, returns, slice(None), state, FIXED_PADDING, args.ent_coef, args)
                optimizer.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
                optimizer.step()
        weights.append(copy.deepcopy(agent.state_dict()))
    assert all(torch.equal(weights[0][name], weights[1][name]) for name in weights[0])
    assert not torch.equal(weights[0]["lstm.lstm.weight_hh_l0"], small_student(0).state_dict()["lstm.lstm.weight_hh_l0"])
