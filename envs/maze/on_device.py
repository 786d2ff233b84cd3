"""The maze's student rollouts on a GPU: the env as torch ops on the device, the acting step and the env
step together, the whole rollout replayed as one CUDA graph.

On a CPU the scripts play the maze with the numpy env of envs/maze/env.py, and nothing here runs. On a GPU
that path costs a few dozen tiny kernel launches per step for the policy, a copy of the actions to the
host, the numpy step there and a copy of the observations back. Here instead:

- `MazeTorchEnv` is the student env of `MazeEnv` as torch ops (gathers and selections, no branch on a
  value): `env_step` and `observe` on the tables `student_layout` builds once per rollout.
  tests/test_maze_on_device.py holds it equal to the numpy env step for step.
- `act` is `MazeStudentFastPath`'s acting step with no host sync: the LSTM state is zeroed by a multiply
  where an episode starts, and the action drawn by inverting the policy's CDF at a uniform number drawn
  on the device. It samples the plain net's distribution (its derived weights are checked against the
  plain net, as on the CPU); the draws differ from Categorical.sample's, so a seed repeats on the GPU but
  does not repeat the CPU's actions (a GPU's random stream never did).
- `DeviceRollout` plays a whole rollout: it writes the rollout's storage and its GAE, all on the device,
  then computes each copy's episode returns on the host from one copy of the rewards. On a GPU the
  rollout (256 acting steps, env steps and GAE) is captured once as a CUDA graph and replayed for each
  later rollout: its inputs (the level tables, the derived weights) are fixed buffers refreshed in place,
  and its random numbers are fresh at every replay. The derived weights are checked against the plain
  net outside the graph, whenever they are rebuilt after an update. A net with no fast path (a modified
  net) plays its rollouts through its own `get_action_and_value` on the device env, with no graph.
"""

from __future__ import annotations

import numpy as np
import torch

from envs.maze.env import CELL_ENCODING, EMPTY, FORWARD, GOAL, TRAIN_MAX_STEPS, TURN, VIEW_SIZE, WALL, MazeEnv, student_layout
from envs.maze.fast_paths import MazeStudentFastPath, lstm_cell_and_heads

LAYOUT_KEYS = ("codes", "base", "start", "start_dir", "move", "view", "turn", "cell_encoding")
CARRY_KEYS = ("pos", "direction", "t")  # the env's state, carried from step to step


def observe(layout: dict, pos: torch.Tensor, direction: torch.Tensor) -> dict:
    """The observation of every copy (MazeEnv's): the 5x5 view ahead, seen through walls, the agent's own
    cell empty; and the direction."""
    cells = layout["codes"][(layout["base"] + pos).unsqueeze(1) + layout["view"][direction]]
    own_cell = torch.arange(VIEW_SIZE * VIEW_SIZE, device=pos.device) == VIEW_SIZE * VIEW_SIZE - 1 - VIEW_SIZE // 2
    cells = torch.where(own_cell, EMPTY, cells)
    image = layout["cell_encoding"][cells].view(len(pos), VIEW_SIZE, VIEW_SIZE, 3)
    return {"image": image, "direction": direction}


def env_step(layout: dict, max_steps: int, pos: torch.Tensor, direction: torch.Tensor, t: torch.Tensor, actions: torch.Tensor):
    """MazeEnv.step as torch ops: turn, move forward unless a wall is ahead, reward on the goal, truncate at
    max_steps, and restart an ended episode from its start. -> pos, direction, t, reward, terminated,
    truncated."""
    direction = (direction + layout["turn"][actions]) & 3
    target = pos + layout["move"][direction]
    cell = layout["codes"][layout["base"] + target]
    moved = (actions == FORWARD) & (cell != WALL)
    pos = torch.where(moved, target, pos)
    t = t + 1
    terminated = moved & (cell == GOAL)
    # In float64 and then float32, as numpy computes it: the same reward to the last bit.
    reward = torch.where(terminated, 1.0 - 0.9 * t.double() / max_steps, 0.0).float()
    truncated = (t >= max_steps) & ~terminated
    ended = terminated | truncated
    pos = torch.where(ended, layout["start"], pos)
    direction = torch.where(ended, layout["start_dir"], direction)
    t = torch.where(ended, 0, t)
    return pos, direction, t, reward, terminated, truncated


def layout_tensors(env: MazeEnv, levels, device) -> dict:
    """The tables of `student_layout` for `levels` as tensors on the device, with the start directions
    drawn as MazeEnv.reset draws them (from the env's generator) and the env's constant tables."""
    layout = student_layout(levels)
    layout["start_dir"] = env.drawn_directions(levels.agent_dir)
    layout["codes"] = layout["codes"].astype(np.int64)
    layout["turn"] = TURN
    layout["cell_encoding"] = CELL_ENCODING
    return {key: torch.as_tensor(np.asarray(layout[key])).to(device, non_blocking=True) for key in LAYOUT_KEYS}


class MazeTorchEnv:
    """MazeEnv's student env on a device, with its interface: `reset(levels)` and `step(actions)` take and
    return tensors. Start directions are drawn from the numpy env's generator, as its reset draws them."""

    def __init__(self, env: MazeEnv, device):
        self.env, self.device, self.num_envs = env, device, env.num_envs

    def reset(self, levels, max_steps: int = TRAIN_MAX_STEPS) -> dict:
        if len(levels) != self.num_envs:
            raise ValueError(f"reset got {len(levels)} levels for {self.num_envs} env copies")
        self.layout, self.max_steps = layout_tensors(self.env, levels, self.device), max_steps
        self.pos, self.direction = self.layout["start"].clone(), self.layout["start_dir"].clone()
        self.t = torch.zeros_like(self.pos)
        return observe(self.layout, self.pos, self.direction)

    def step(self, actions: torch.Tensor):
        self.pos, self.direction, self.t, reward, terminated, truncated = env_step(self.layout, self.max_steps, self.pos, self.direction,
                                                                                   self.t, actions.long())
        return observe(self.layout, self.pos, self.direction), reward, terminated, truncated, {}


def act(weights: dict, obs: dict, h: torch.Tensor, c: torch.Tensor, ended: torch.Tensor, uniforms: torch.Tensor):
    """The student's acting step on its derived weights, with no host sync: the state h, c [N, H] zeroed
    where an episode starts, the LSTM cell and heads, and an action drawn at `uniforms` [N] in [0, 1) by
    inverting the policy's cumulative distribution. -> action, log-probability, value, h, c."""
    keep = (~ended).to(h.dtype).unsqueeze(1)
    gate_inputs = MazeStudentFastPath.gate_inputs(weights, obs)
    log_probs, value, h, c = lstm_cell_and_heads(gate_inputs, h * keep, c * keep, weights)
    below = log_probs.exp().cumsum(-1) <= uniforms.unsqueeze(1)
    action = below.sum(-1).clamp_(max=log_probs.shape[1] - 1)  # a rounding of the last sum below 1 is not an action
    return action, log_probs.gather(1, action.unsqueeze(1)).squeeze(1), value, h, c


def rollout_step(weights: dict, layout: dict, max_steps: int, obs: dict, carry: dict, h, c, ended, uniforms):
    """One step of a rollout: the acting step on this observation, then the env step. -> the step's
    action, log-probability, value, reward; the next observation, env state, LSTM state and episode ends."""
    action, logprob, value, h, c = act(weights, obs, h, c, ended, uniforms)
    pos, direction, t, reward, terminated, truncated = env_step(layout, max_steps, carry["pos"], carry["direction"], carry["t"], action)
    carry = {"pos": pos, "direction": direction, "t": t}
    return action, logprob, value, reward, observe(layout, pos, direction), carry, h, c, terminated | truncated


def gae(rewards, values, starts, last_step_ended, next_value, gamma: float, gae_lambda: float):
    """Generalized advantage estimation over the rollout ([T, N]; starts: 1 where an episode starts at
    step t), as the scripts compute it on the host. -> advantages [T, N]."""
    next_nonterminal = 1.0 - torch.cat([starts[1:], last_step_ended.unsqueeze(0).to(starts.dtype)])
    following = torch.cat([values[1:], next_value.unsqueeze(0)])
    delta = rewards + gamma * following * next_nonterminal - values
    advantages = torch.empty_like(rewards)
    last = torch.zeros_like(rewards[0])
    for t in reversed(range(len(rewards))):
        last = delta[t] + gamma * gae_lambda * next_nonterminal[t] * last
        advantages[t] = last
    return advantages


def episode_returns(rewards: np.ndarray, starts: np.ndarray, last_step_ended: np.ndarray) -> list[list[float]]:
    """Each copy's completed episodes' returns, from a rollout's rewards and episode starts [T, N]."""
    ends = np.concatenate([starts[1:], last_step_ended[None]]).astype(bool)
    returns = [[] for _ in range(rewards.shape[1])]
    running = np.zeros(rewards.shape[1])
    for t in range(len(rewards)):
        running += rewards[t]
        for i in np.nonzero(ends[t])[0]:
            returns[i].append(running[i])
        running[ends[t]] = 0.0
    return returns


class CapturedPlay:
    """A player whose `play` runs with no host sync, so that on a GPU it can be captured once as a CUDA graph
    and replayed (`replay_graph`); it keeps `cuda_graph` (None until captured), `device` and `graph_replays`."""

    def replay_graph(self) -> None:
        """Replay the captured `play`; capture it first (after warm-up runs on a side stream, as CUDA
        graphs need). The random stream is put back after the capture, so the replays draw what they
        would have drawn had the graph been captured earlier: a resumed run captures anew and goes on
        exactly."""
        if self.cuda_graph is None:
            random_state = torch.cuda.get_rng_state(self.device)
            side = torch.cuda.Stream(self.device)
            side.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(side):
                for _ in range(2):
                    self.play()
            torch.cuda.current_stream(self.device).wait_stream(side)
            self.cuda_graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.cuda_graph):
                self.play()
            torch.cuda.set_rng_state(random_state, self.device)
        self.cuda_graph.replay()
        self.graph_replays += 1


class DeviceRollout(CapturedPlay):
    """Plays the student's maze rollouts on its device into a script's storage (obs, actions, logprobs,
    values, rewards, episode_starts, and last_step_ended where it has one), as the script's
    own rollout does.
    Called with the levels, it returns advantages, returns and each copy's completed episodes' returns.
    `graph`: capture the rollout as a CUDA graph (on a GPU)."""

    def __init__(self, env: MazeEnv, agent, storage, gamma: float, gae_lambda: float, device, graph: bool):
        self.agent, self.storage, self.device = agent, storage, device
        self.gamma, self.gae_lambda, self.graph = gamma, gae_lambda, graph
        self.num_steps, self.num_envs = storage.rewards.shape
        self.torch_env = MazeTorchEnv(env, device)
        self.layout, self.weights, self.source_weights, self.cuda_graph = None, None, None, None
        self.graph_replays = 0  # rollouts replayed from the captured graph (tests read it)

    @torch.no_grad()
    def __call__(self, levels):
        first_obs = self.torch_env.reset(levels)
        fast_path = self.agent.fast_path()
        weights = None
        if fast_path is not None:
            state = self.agent.initial_state(self.num_envs, self.device)
            done = torch.ones(self.num_envs, device=self.device)
            weights = fast_path.checked_weights(self.agent, first_obs, state, done)  # the check, outside the graph
        if weights is None:
            self.play_plain(first_obs)
        else:
            self.refresh_inputs(weights)
            if self.graph:
                self.replay_graph()
            else:
                self.play()
        storage = self.storage
        returns_per_copy = episode_returns(storage.rewards.cpu().numpy(), storage.episode_starts.cpu().numpy(), self.last_step_ended.cpu().numpy())
        advantages = self.advantages.clone()  # the graph's own tensor is rewritten by the next rollout
        return advantages, advantages + storage.values, returns_per_copy

    def refresh_inputs(self, weights: dict) -> None:
        """The rollout's inputs as fixed buffers, written in place: the level tables at every rollout, the
        derived weights when they were rebuilt (after an update)."""
        if self.layout is None or any(self.layout[k].shape != v.shape for k, v in self.torch_env.layout.items()):
            self.layout = {k: v.clone() for k, v in self.torch_env.layout.items()}
            self.cuda_graph = None
        else:
            for key, value in self.torch_env.layout.items():
                self.layout[key].copy_(value)
        if self.weights is None:
            self.weights = {k: tuple(t.clone() for t in v) if k == "heads" else v.clone() for k, v in weights.items()}
        elif weights is not self.source_weights:
            for key, value in weights.items():
                for buffer, new in zip(self.weights[key] if key == "heads" else (self.weights[key],), value if key == "heads" else (value,)):
                    buffer.copy_(new)
        self.source_weights = weights

    def play(self) -> None:
        """The rollout from the fixed buffers: every step's acting, env step and storage writes, then GAE.
        No host sync: this is what the CUDA graph captures."""
        storage, layout = self.storage, self.layout
        carry = {"pos": layout["start"].clone(), "direction": layout["start_dir"].clone(), "t": torch.zeros_like(layout["start"])}
        obs = observe(layout, carry["pos"], carry["direction"])
        hidden_size = self.weights["lstm_recurrent"].shape[0]
        h = torch.zeros(self.num_envs, hidden_size, device=self.device)
        c = torch.zeros_like(h)
        ended = torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
        for step in range(self.num_steps):
            storage.obs["image"][step].copy_(obs["image"])
            storage.obs["direction"][step].copy_(obs["direction"])
            storage.episode_starts[step].copy_(ended)
            uniforms = torch.rand(self.num_envs, device=self.device)
            action, logprob, value, reward, obs, carry, h, c, ended = rollout_step(self.weights, layout, TRAIN_MAX_STEPS, obs, carry,
                                                                                   h, c, ended, uniforms)
            storage.actions[step].copy_(action)
            storage.logprobs[step].copy_(logprob)
            storage.values[step].copy_(value)
            storage.rewards[step].copy_(reward)
        self.record_last_step_ended(ended)
        next_value = act(self.weights, obs, h, c, ended, torch.zeros(self.num_envs, device=self.device))[2]
        self.advantages = gae(storage.rewards, storage.values, storage.episode_starts, self.last_step_ended, next_value, self.gamma, self.gae_lambda)

    def record_last_step_ended(self, ended: torch.Tensor) -> None:
        """Where the rollout's last step ended an episode: kept here, and in the storage where it has a place."""
        self.last_step_ended = ended
        if hasattr(self.storage, "last_step_ended"):
            self.storage.last_step_ended.copy_(ended)

    def play_plain(self, obs: dict) -> None:
        """A net with no fast path: its own acting step (Categorical.sample) on the device env, step by step."""
        storage, agent = self.storage, self.agent
        state = agent.initial_state(self.num_envs, self.device)
        ended = torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
        for step in range(self.num_steps):
            for key, value in obs.items():
                storage.obs[key][step].copy_(value)
            storage.episode_starts[step].copy_(ended)
            action, logprob, _, value, state = agent.get_action_and_value(obs, state, ended.float())
            storage.actions[step].copy_(action)
            storage.logprobs[step].copy_(logprob)
            storage.values[step].copy_(value)
            obs, reward, terminated, truncated, _ = self.torch_env.step(action)
            ended = terminated | truncated
            storage.rewards[step].copy_(reward)
        self.record_last_step_ended(ended)
        next_value = agent.get_value(obs, state, ended.float())
        self.advantages = gae(storage.rewards, storage.values, storage.episode_starts, self.last_step_ended, next_value, self.gamma, self.gae_lambda)
