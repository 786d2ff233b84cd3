"""PAIRED's maze teacher on a GPU: the teacher's MDP as torch ops on the device, and the teacher network's whole
design episode played on it, one CUDA graph.

On a CPU the scripts' `teacher_rollout` plays the design episode with the numpy MDP of envs/maze/env.py
(`MazeTeacherMDP`), and nothing here runs. On a GPU that costs a host round trip per design step (27 or 62
per level batch): the observation to the device, the action back. Here instead:

- `MazeTeacherTorchMDP` is `MazeTeacherMDP` as torch ops (comparisons and selections, no branch on a value):
  the same placements, budgets and observations. Its random numbers are the numpy MDP's own: the noise of
  every observation and the free cell an agent placed on the goal moves to are drawn by numpy from the same
  generator, in the same order. Which draws come first depends on the actions (a relocation comes between
  two noise draws), so they cannot be drawn ahead on the host. Instead the generator's raw 64-bit words for
  the longest episode are drawn ahead from a copy of it, and the device turns them into numbers exactly as
  numpy does (`noise_draw`, `free_cell_draw`), keeping count of the words used; once the levels are read,
  the generator is advanced by that count, to where the numpy MDP leaves it. tests/test_teacher_on_device.py
  holds it equal to the numpy MDP step for step, random numbers and generator state included.
- `act` is the teacher network's acting step as `get_action_and_value` runs it plainly (its features, LSTM
  and heads, the log-probabilities normalized as Categorical does), with the action drawn as
  torch.multinomial draws one sample (the largest probability divided by an exponential draw) without
  multinomial's check of the probabilities, which waits for the device. It draws the plain path's actions
  from the same random stream.
- `TeacherDeviceRollout` plays a whole design episode into the script's teacher storage and returns the
  levels, as `teacher_rollout` does. On a GPU the episode is captured once as a CUDA graph and replayed;
  its inputs are fixed buffers (the raw words, written in place) and the network's parameters, read where
  they lie: a parameter moved (a new storage) is captured anew. Only the paper's teacher class is captured; a
  modified teacher plays the same steps eagerly on the device.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

from envs.maze.env import CELL_ENCODING, GOAL, NOISE_DIM, RANDOM_DIRECTION, TRAIN_SIZE, MazeTeacher, MazeTeacherMDP
from envs.maze.levels import MazeLevels, empty_grid
from envs.maze.on_device import CapturedPlay

LOW_32_BITS = 0xFFFFFFFF
DOUBLE_BITS = 53  # numpy's float64 in [0, 1): the top 53 bits of a word, times 2^-53
FLOAT_BITS = 24  # numpy's float32 in [0, 1): the top 24 bits of a 32-bit half, times 2^-24


def noise_draw(words: torch.Tensor, cursor: torch.Tensor, has_half: torch.Tensor, half: torch.Tensor, n: int):
    """numpy's `rng.random((n, NOISE_DIM), dtype=np.float32)` from the PCG64 words at `cursor`: each float32
    takes a 32-bit half of a word, the low half first, and a half left over from an earlier float32 draw
    (`has_half`, `half`: numpy's has_uint32 and uinteger) comes first. An even count of halves takes
    n * NOISE_DIM / 2 words and leaves the same kind of half over: the last word's high half.
    -> noise [n, NOISE_DIM], the new cursor and half."""
    count = n * NOISE_DIM // 2
    drawn = words[cursor + torch.arange(count, device=words.device)]
    halves = torch.stack([drawn & LOW_32_BITS, (drawn >> 32) & LOW_32_BITS], 1).view(-1)
    halves = torch.where(has_half, torch.cat([half.view(1), halves[:-1]]), halves)
    noise = (halves >> (32 - FLOAT_BITS)).float() * 2.0**-FLOAT_BITS
    return noise.view(n, NOISE_DIM), cursor + count, (drawn[-1] >> 32) & LOW_32_BITS


def free_cell_draw(words: torch.Tensor, cursor: torch.Tensor, drawing: torch.Tensor, free: torch.Tensor):
    """envs.maze.levels.random_free_cells for the levels where `drawing` [n] holds: numpy draws a float64 per
    cell of their grids, [drawing levels, H * W] in order, and takes the first largest over their free cells
    [n, H, W]; comparing the 53-bit integers behind the floats picks the same cell. -> the cells [n, 2] as
    (x, y) (meaningless where not `drawing`) and the new cursor."""
    n, height, width = free.shape
    cells = height * width
    rank = drawing.long().cumsum(0) - drawing.long()  # the level's row in numpy's draw
    index = (cursor + rank * cells).unsqueeze(1) + torch.arange(cells, device=words.device)
    draws = (words[index.clamp(max=len(words) - 1)] >> (64 - DOUBLE_BITS)) & ((1 << DOUBLE_BITS) - 1)
    chosen = torch.where(free.view(n, cells), draws, -1).argmax(1)
    return torch.stack([chosen % width, chosen // width], 1), cursor + drawing.long().sum() * cells


class MazeTeacherTorchMDP(MazeTeacherMDP):
    """MazeTeacherMDP (envs/maze/env.py, whose docstring gives the rules) on `device`: `reset(n)`,
    `step(actions)` and `levels()` with its interface and settings, the observations and actions as tensors.
    Its random numbers are those the numpy MDP would draw from `rng` (a PCG64 generator); `rng` is advanced
    to where the numpy MDP would leave it when the levels are read, and must not be drawn from in between.

    `reset` is `draw_words` (the host's part: the generator's words for the episode, copied into a fixed
    buffer) then `start` (the device's part, which a CUDA graph can hold with every `step`)."""

    def __init__(self, block_budget: int, uniform_budget: bool, rng: np.random.Generator, size: int = TRAIN_SIZE, device="cpu"):
        if type(rng.bit_generator) is not np.random.PCG64:
            raise TypeError(f"the teacher's MDP on the device draws numpy's PCG64 numbers; its generator is {type(rng.bit_generator).__name__}")
        super().__init__(block_budget, uniform_budget, rng, size)
        self.device = torch.device(device)
        self.cell_encoding = torch.as_tensor(CELL_ENCODING, device=self.device)
        self.rows = torch.arange(size, device=self.device).view(1, size, 1)
        self.columns = torch.arange(size, device=self.device).view(1, 1, size)
        self.n, self.words = None, None

    @classmethod
    def like(cls, mdp: MazeTeacherMDP, device) -> MazeTeacherTorchMDP:
        """The device's copy of a numpy MDP: its settings and its generator."""
        return cls(mdp.block_budget, mdp.uniform_budget, mdp.rng, mdp.size, device)

    def reset(self, n: int) -> dict:
        self.draw_words(n)
        return self.start()

    def draw_words(self, n: int) -> None:
        """The generator's next words, enough for the longest episode of n levels (a noise draw per
        observation, a grid's draw per level), from a copy of it, into the words buffer (in place)."""
        self.start_state = self.rng.bit_generator.state
        source = np.random.PCG64()
        source.state = self.start_state
        count = (self.num_steps + 1) * n * NOISE_DIM // 2 + n * self.size**2
        words = torch.from_numpy(source.random_raw(count).view(np.int64))
        if self.device.type == "cuda":  # copied from page-locked memory, the host does not wait for the device
            words = words.pin_memory()
        half = (self.start_state["has_uint32"] == 1, self.start_state["uinteger"])
        if self.n != n:
            self.n, self.words = n, words.to(self.device)
            self.start_has_half = torch.tensor(half[0], device=self.device)
            self.start_half = torch.tensor(half[1], device=self.device)
            self.empty_walls = torch.as_tensor(empty_grid(n, self.size), device=self.device)
        else:
            self.words.copy_(words, non_blocking=True)
            self.start_has_half.fill_(half[0])
            self.start_half.fill_(half[1])

    def start(self) -> dict:
        """The episode's first observation, from the words drawn: no host sync."""
        n = self.n
        self.t = 0
        self.walls = self.empty_walls.clone()
        self.goal = torch.zeros(n, 2, dtype=torch.long, device=self.device)
        self.agent = torch.zeros_like(self.goal)
        self.budget = torch.full((n,), self.block_budget, dtype=torch.long, device=self.device)
        self.cursor, self.half = torch.zeros((), dtype=torch.long, device=self.device), self.start_half.clone()
        return self._observation()

    def step(self, actions: torch.Tensor) -> tuple[dict, bool]:
        if self.t >= self.num_steps:
            raise ValueError(f"the design episode ended after {self.num_steps} steps")
        self.place(actions.long())
        return self._observation(), self.t >= self.num_steps

    def place(self, a: torch.Tensor) -> None:
        """MazeTeacherMDP.place: a wall, the goal or the agent at each action's cell, by the level's budget."""
        x, y = a % self.interior + 1, a // self.interior + 1
        if self.uniform_budget and self.t == 0:
            self.budget = a * self.block_budget // self.num_actions
        place_wall = (self.t < self.budget).view(-1, 1, 1)
        place_goal = self.t == self.budget
        place_agent = self.t == self.budget + 1
        cell = (self.rows == y.view(-1, 1, 1)) & (self.columns == x.view(-1, 1, 1))
        self.walls = torch.where(cell & place_wall, True, self.walls)
        self.walls = torch.where(cell & (place_goal | place_agent).view(-1, 1, 1), False, self.walls)
        xy = torch.stack([x, y], 1)
        self.goal = torch.where(place_goal.view(-1, 1), xy, self.goal)
        self.agent = torch.where(place_agent.view(-1, 1), xy, self.agent)
        on_goal = place_agent & (self.agent == self.goal).all(1)
        free = ~self.walls & ~self.cells_at(self.goal)
        moved, self.cursor = free_cell_draw(self.words, self.cursor, on_goal, free)
        self.agent = torch.where(on_goal.view(-1, 1), moved, self.agent)
        self.t += 1

    def cells_at(self, xy: torch.Tensor) -> torch.Tensor:
        """[n, H, W]: True at each level's cell xy [n, 2]."""
        return (self.rows == xy[:, 1].view(-1, 1, 1)) & (self.columns == xy[:, 0].view(-1, 1, 1))

    def _observation(self) -> dict:
        codes = self.walls.to(torch.uint8)
        if self.t > 0:
            placed = (self.t > self.budget).view(-1, 1, 1)
            codes = torch.where(self.cells_at(self.goal) & placed, GOAL, codes)
        noise, self.cursor, self.half = noise_draw(self.words, self.cursor, self.start_has_half, self.half, self.n)
        time = torch.full((self.n,), min(self.t, self.num_steps - 1), dtype=torch.long, device=self.device)
        return {"image": self.cell_encoding[codes.long()], "time": time, "noise": noise}

    def levels(self) -> MazeLevels:
        """The levels designed (on the host), and the generator advanced past the words the episode used."""
        walls, goal, agent, used, half = (x.cpu() for x in (self.walls, self.goal, self.agent, self.cursor, self.half))
        source = np.random.PCG64()
        source.state = self.start_state
        source.random_raw(int(used))  # raw words leave numpy's half-word unchanged: it is set below
        state = source.state
        state["uinteger"] = int(half)
        self.rng.bit_generator.state = state
        return MazeLevels(walls.numpy(), goal.numpy(), agent.numpy(), np.full(self.n, RANDOM_DIRECTION, np.int8))


def act(teacher, obs: dict, state, episode_start: torch.Tensor):
    """The teacher's acting step as its plain `get_action_and_value` computes it (features, LSTM, heads; the
    logits normalized as Categorical normalizes them), the action drawn as torch.multinomial(probs, 1, True)
    draws it: the index of the largest probability divided by a draw of Exp(1) per action, from the same
    random stream. multinomial first checks that no row of probabilities sums to 0, which waits for the
    device; softmax's rows never do. -> action, log-probability, value, new state."""
    hidden, state = teacher.lstm(teacher.features(obs), state, episode_start)
    logits = teacher.actor(hidden)
    log_probs = logits - logits.logsumexp(-1, keepdim=True)
    probs = torch.softmax(log_probs, -1)
    action = (probs / torch.empty_like(probs).exponential_(1)).argmax(-1)
    return action, log_probs.gather(1, action.unsqueeze(1)).squeeze(1), teacher.critic(hidden).squeeze(-1), state


class TeacherDeviceRollout(CapturedPlay):
    """Plays PAIRED's maze design episodes on the device into a script's teacher storage (obs, actions,
    logprobs, values, episode_starts), as the script's `teacher_rollout` does on `mdp` (a MazeTeacherMDP,
    whose settings and generator it takes). Called with no arguments, it returns the levels.
    `graph`: capture the episode as a CUDA graph (on a GPU; the paper's teacher class only)."""

    def __init__(self, mdp: MazeTeacherMDP, teacher, storage, device, graph: bool):
        self.teacher, self.storage, self.device = teacher, storage, torch.device(device)
        self.num_envs = storage.actions.shape[1]
        self.mdp = MazeTeacherTorchMDP.like(mdp, self.device)
        self.graph = graph and type(teacher) is MazeTeacher
        self.cuda_graph, self.parameters_at = None, None
        self.episodes, self.graph_replays = 0, 0  # episodes played, and of them replayed from the graph (tests read both)

    @torch.no_grad()
    def __call__(self) -> MazeLevels:
        self.mdp.draw_words(self.num_envs)
        if self.graph:
            parameters_at = [t.data_ptr() for t in itertools.chain(self.teacher.parameters(), self.teacher.buffers())]
            if parameters_at != self.parameters_at:  # the graph reads the parameters where they were at its capture
                self.parameters_at, self.cuda_graph = parameters_at, None
            self.replay_graph()
        else:
            self.play()
        self.episodes += 1
        return self.mdp.levels()

    def play(self) -> None:
        """The design episode from the words drawn: every step's acting, MDP step and storage writes. No host
        sync: this is what the CUDA graph captures."""
        storage, n = self.storage, self.num_envs
        obs = self.mdp.start()
        state = self.teacher.initial_state(n, self.device)
        episode_start = torch.ones(n, device=self.device)
        for step in range(self.mdp.num_steps):
            for key, value in obs.items():
                storage.obs[key][step].copy_(value)
            storage.episode_starts[step].copy_(episode_start)
            action, logprob, value, state = act(self.teacher, obs, state, episode_start)
            storage.actions[step].copy_(action)
            storage.logprobs[step].copy_(logprob)
            storage.values[step].copy_(value)
            obs, _ = self.mdp.step(action)
            episode_start = torch.zeros(n, device=self.device)
