"""The maze UPOMDP: MiniGrid-style navigation on levels a teacher designs.

Everything an algorithm script needs for the maze lives here: the level batch, the student env
(all copies stepped at once with numpy), the teacher's MDP (PAIRED's adversary), the DR and empty-room
generators, ACCEL's mutation, level metrics, rendering and the paper's networks. The level batch
itself is in `envs/maze/levels.py`, the 12 held-out test mazes in `envs/maze/held_out.py`.

Coordinates are (x, y): x the column from the left, y the row from the top, outer wall ring included.
Directions: 0 east (+x), 1 south (+y), 2 west, 3 north.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from envs.levels import HeldOutLevels
from envs.maze.fast_paths import MazeStudentFastPath, MazeTeacherFastPath
from envs.maze.held_out import held_out_levels
from envs.maze.levels import MazeLevels, empty_grid, random_free_cells
from envs.nets import RecurrentCategoricalActorCritic, ResettableLSTM, layer_init

EMPTY, WALL, GOAL = 0, 1, 2
# MiniGrid's (type, colour, state) encoding of each cell code; the networks divide it by 10.
CELL_ENCODING = np.array([[1, 0, 0], [2, 5, 0], [8, 1, 0]], dtype=np.uint8)
DIRECTION_VECTORS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
RANDOM_DIRECTION = -1
VIEW_SIZE = 5
NUM_ACTIONS = 7  # MiniGrid's: left, right, forward, pickup, drop, toggle, done
LEFT, RIGHT, FORWARD = 0, 1, 2
TURN = np.array([-1, 1, 0, 0, 0, 0, 0])
TRAIN_SIZE = 15
TRAIN_MAX_STEPS = 250
BLOCK_BUDGETS = {"maze": 60, "maze25": 25}  # maze: uniform budget of 0-59 walls; maze25: 25 walls
NOISE_DIM = 50


# ---------------------------------------------------------------------------------------------------
# The teacher's MDP: one interior cell per step, walls first, then goal, agent.
# ---------------------------------------------------------------------------------------------------
class MazeTeacherMDP:
    """PAIRED's adversary MDP over n mazes at once, all stepping in lockstep.

    Action a in [0, 169) is the interior cell x = a % 13 + 1, y = a // 13 + 1. With a fixed budget of
    25 walls the episode has 27 steps: 25 walls, the goal, the agent. With the uniform 0-60 budget the
    first action also sets n = int(a / 169 * 60) and is itself placed (a wall if n >= 1, else the goal);
    then walls up to n, the goal, the agent, and the episode always lasts 62 steps (later actions are
    no-ops). A wall on an occupied cell is a no-op; goal and agent clear a wall under them; an agent
    placed on the goal moves to a uniformly random free cell.

    Observation: the full grid image [n, H, W, 3] (uint8, MiniGrid encoding), the time step [n] and a
    fresh noise vector [n, 50] of U[0, 1) numbers at every step.
    """

    def __init__(self, block_budget: int, uniform_budget: bool, rng: np.random.Generator, size: int = TRAIN_SIZE):
        self.block_budget = block_budget
        self.uniform_budget = uniform_budget
        self.rng = rng
        self.size = size
        self.interior = size - 2
        self.num_actions = self.interior**2
        self.num_steps = block_budget + 2
        self.action_space = gym.spaces.Discrete(self.num_actions)

    def reset(self, n: int) -> dict:
        self.n = n
        self.t = 0
        self.walls = empty_grid(n, self.size)
        self.goal = np.zeros((n, 2), dtype=np.int64)
        self.agent = np.zeros((n, 2), dtype=np.int64)
        self.budget = np.full(n, self.block_budget, dtype=np.int64)
        return self._observation()

    def step(self, actions) -> tuple[dict, bool]:
        """Place one cell per teacher; returns (observation, done). done is True after the last step."""
        self.place(actions)
        return self._observation(), self.t >= self.num_steps

    def place(self, actions) -> None:
        """One step's placements without the observation (the DR generator needs none)."""
        a = np.asarray(actions, dtype=np.int64)
        x, y = a % self.interior + 1, a // self.interior + 1
        index = np.arange(self.n)
        if self.uniform_budget and self.t == 0:
            self.budget = a * self.block_budget // self.num_actions  # int(a / 169 * 60), exact in integers
        place_wall = self.t < self.budget
        place_goal = self.t == self.budget
        place_agent = self.t == self.budget + 1
        self.walls[index[place_wall], y[place_wall], x[place_wall]] = True
        self.walls[index[place_goal], y[place_goal], x[place_goal]] = False
        self.goal[place_goal] = np.stack([x, y], axis=1)[place_goal]
        self.walls[index[place_agent], y[place_agent], x[place_agent]] = False
        self.agent[place_agent] = np.stack([x, y], axis=1)[place_agent]
        on_goal = place_agent & np.all(self.agent == self.goal, axis=1)
        if on_goal.any():
            free = ~self.walls[on_goal]
            free[np.arange(len(free)), self.goal[on_goal, 1], self.goal[on_goal, 0]] = False
            self.agent[on_goal] = random_free_cells(free, self.rng)
        self.t += 1

    def levels(self) -> MazeLevels:
        return MazeLevels(self.walls.copy(), self.goal.copy(), self.agent.copy(), np.full(self.n, RANDOM_DIRECTION, np.int8))

    def _observation(self) -> dict:
        codes = self.walls.astype(np.uint8)
        if self.t > 0:
            placed = self.t > self.budget
            codes[np.arange(self.n)[placed], self.goal[placed, 1], self.goal[placed, 0]] = GOAL
        return {
            "image": CELL_ENCODING[codes],
            "time": np.full(self.n, min(self.t, self.num_steps - 1), dtype=np.int64),
            "noise": self.rng.random((self.n, NOISE_DIM), dtype=np.float32),
        }


# ---------------------------------------------------------------------------------------------------
# Level metrics: walls, passable, shortest path length by BFS (interior cells + 1 if none).
# ---------------------------------------------------------------------------------------------------
def shortest_path_lengths(levels: MazeLevels) -> np.ndarray:
    """BFS moves from agent to goal (4-connected) for every level at once; (H-2)*(W-2)+1 if impassable."""
    n, h, w = levels.walls.shape
    free = ~levels.walls
    index = np.arange(n)
    reached = np.zeros_like(free)
    reached[index, levels.agent[:, 1], levels.agent[:, 0]] = True
    frontier = reached.copy()
    unreachable = (h - 2) * (w - 2) + 1
    lengths = np.full(n, unreachable, dtype=np.int64)
    active = np.any(levels.agent != levels.goal, axis=1)
    lengths[~active] = 0
    for distance in range(1, unreachable):
        grown = np.zeros_like(frontier)
        grown[:, 1:, :] |= frontier[:, :-1, :]
        grown[:, :-1, :] |= frontier[:, 1:, :]
        grown[:, :, 1:] |= frontier[:, :, :-1]
        grown[:, :, :-1] |= frontier[:, :, 1:]
        frontier = grown & free & ~reached
        reached |= frontier
        hit = active & frontier[index, levels.goal[:, 1], levels.goal[:, 0]]
        lengths[hit] = distance
        active &= ~hit & frontier.reshape(n, -1).any(axis=1)
        if not active.any():
            break
    return lengths


def shifted(cells: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """cells [B, H, W] moved by (dx, dy): out[:, y + dy, x + dx] = cells[:, y, x], edges dropped."""
    out = np.zeros_like(cells)
    h, w = cells.shape[1:]
    out[:, max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = cells[:, max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)]
    return out


def fewest_actions(walls: np.ndarray, goal: np.ndarray, agent: np.ndarray, agent_dir: np.ndarray, limit: int) -> np.ndarray:
    """The fewest actions (turns included) from each start position and direction to the goal, by BFS
    over (direction, cell) for all levels at once; limit + 1 where the goal takes more than `limit`
    actions or cannot be reached. walls [B, H, W]; goal, agent [B, 2] as (x, y); agent_dir [B] in 0-3."""
    n = len(walls)
    index = np.arange(n)
    free = ~walls
    reached = np.zeros((n, 4) + walls.shape[1:], dtype=bool)
    reached[index, agent_dir, agent[:, 1], agent[:, 0]] = True
    frontier = reached.copy()
    actions = np.full(n, limit + 1, dtype=np.int64)
    active = np.ones(n, dtype=bool)
    for step in range(1, limit + 1):
        turned = np.roll(frontier, 1, axis=1) | np.roll(frontier, -1, axis=1)
        moved = np.stack([shifted(frontier[:, d], *DIRECTION_VECTORS[d]) & free for d in range(4)], axis=1)
        frontier = (turned | moved) & ~reached
        reached |= frontier
        hit = active & moved[index, :, goal[:, 1], goal[:, 0]].any(axis=1)
        actions[hit] = step
        active &= ~hit & frontier.reshape(n, -1).any(axis=1)
        if not active.any():
            break
    return actions


def optimal_returns(levels: MazeLevels, max_steps: int = TRAIN_MAX_STEPS) -> np.ndarray:
    """The best return the student can get on each level: 1 - 0.9 * n / max_steps, n the fewest actions
    from the start position and direction to the goal, and 0 if the goal is out of reach within
    max_steps. A level whose start direction is random (not yet drawn) gets the mean over the 4
    directions, its expected optimum."""
    random = levels.agent_dir < 0
    rows = np.concatenate([np.arange(len(levels)), np.repeat(np.nonzero(random)[0], 4)])
    directions = np.concatenate([np.where(random, 0, levels.agent_dir), np.tile(np.arange(4), int(random.sum()))])
    actions = fewest_actions(levels.walls[rows], levels.goal[rows], levels.agent[rows], directions.astype(np.int64), max_steps)
    best = np.where(actions <= max_steps, 1.0 - 0.9 * actions / max_steps, 0.0)
    per_level = best[: len(levels)].copy()
    per_level[random] = best[len(levels) :].reshape(-1, 4).mean(axis=1)
    return per_level


def level_metrics(levels: MazeLevels) -> dict[str, np.ndarray]:
    lengths = shortest_path_lengths(levels)
    h, w = levels.size
    return {
        "walls": levels.walls[:, 1:-1, 1:-1].sum(axis=(1, 2)),
        "passable": lengths <= (h - 2) * (w - 2),
        "path_length": lengths,
    }


# ---------------------------------------------------------------------------------------------------
# Rendering: levels (and optionally an agent's visited cells) to RGB arrays.
# ---------------------------------------------------------------------------------------------------
TILE = 8
COLOURS = np.array([[20, 20, 20], [128, 128, 128], [40, 200, 60], [70, 110, 220]], dtype=np.uint8)  # empty, wall, goal, path
AGENT_COLOUR = np.array([230, 40, 40], dtype=np.uint8)


def render_levels(levels: MazeLevels, visited: np.ndarray | None = None) -> np.ndarray:
    """RGB images [B, H*8, W*8, 3]: walls grey, goal green, agent start red, visited cells [B, H, W] blue."""
    codes = levels.walls.astype(np.int64)
    if visited is not None:
        codes[visited & ~levels.walls] = 3
    index = np.arange(len(levels))
    codes[index, levels.goal[:, 1], levels.goal[:, 0]] = GOAL
    images = np.repeat(np.repeat(COLOURS[codes], TILE, axis=1), TILE, axis=2)
    inset = np.arange(2, TILE - 2)
    rows = levels.agent[:, 1, None, None] * TILE + inset[None, :, None]
    cols = levels.agent[:, 0, None, None] * TILE + inset[None, None, :]
    images[index[:, None, None], rows, cols] = AGENT_COLOUR
    return images


# ---------------------------------------------------------------------------------------------------
# The student env: every copy plays its own level; an ended episode restarts the same level.
# ---------------------------------------------------------------------------------------------------
def student_layout(levels: MazeLevels) -> dict:
    """The student env's tables for a batch of levels, as flat indices: each level's codes padded by a
    ring of walls as deep as the view, so a view never leaves the grid; a cell (x, y) of copy i is
    codes[base[i] + (y + pad) * width + x + pad]. start: each copy's start cell; move[d]: the index step
    of direction d; view[d]: the 25 cells of the view (row 0 farthest) relative to the agent's cell."""
    n = len(levels)
    h, w = levels.size
    pad = VIEW_SIZE - 1
    height, width = h + 2 * pad, w + 2 * pad
    codes = np.full((n, height, width), WALL, dtype=np.uint8)
    codes[:, pad : pad + h, pad : pad + w] = levels.walls
    index = np.arange(n)
    codes[index, levels.goal[:, 1] + pad, levels.goal[:, 0] + pad] = GOAL
    forward = np.arange(VIEW_SIZE - 1, -1, -1)[:, None]  # row 0 is the farthest
    lateral = np.arange(VIEW_SIZE)[None, :] - VIEW_SIZE // 2
    fx, fy = DIRECTION_VECTORS[:, 0, None, None], DIRECTION_VECTORS[:, 1, None, None]
    rx, ry = -fy, fx  # the agent's right
    return {"width": width, "codes": codes.reshape(-1), "base": index * height * width,
            "start": (levels.agent[:, 1] + pad) * width + levels.agent[:, 0] + pad,
            "move": DIRECTION_VECTORS[:, 0] + DIRECTION_VECTORS[:, 1] * width,
            "view": ((forward * fx + lateral * rx) + (forward * fy + lateral * ry) * width).reshape(4, -1)}


class MazeEnv:
    """The maze UPOMDP over `num_envs` copies, stepped together with numpy.

    Observation: {"image": uint8 [N, 5, 5, 3], "direction": int64 [N]}. The image is the 5x5 square in
    front of the agent (row 0 farthest, row 4 the agent's row, the agent in column 2, looking up), seen
    through walls; cells outside the grid read as walls, the agent's own cell as empty.
    Action: Discrete(7); only left, right and forward act. Reward: 1 - 0.9 * t / max_steps on reaching
    the goal (t the 1-based step count of the episode), else 0. At max_steps the episode is truncated.
    Either way the copy restarts its level at once, from the same start position and direction.
    A level whose start direction is random (RANDOM_DIRECTION) gets one drawn at `reset`, kept for all
    its episodes until the next `reset`, as the reference does: to give two agents the same start,
    draw it first with `draw_starts` and reset both with the result.
    """

    def __init__(self, name: str = "maze", num_envs: int = 32, seed: int = 0):
        if name not in BLOCK_BUDGETS:
            raise ValueError(f"unknown maze setting {name!r}: expected one of {sorted(BLOCK_BUDGETS)}")
        self.name = name
        self.num_envs = num_envs
        self.block_budget = BLOCK_BUDGETS[name]
        self.uniform_budget = name == "maze"
        self.rng = np.random.default_rng(seed)
        self.single_observation_space = gym.spaces.Dict(
            {
                "image": gym.spaces.Box(0, 255, (VIEW_SIZE, VIEW_SIZE, 3), np.uint8),
                "direction": gym.spaces.Discrete(4),
            }
        )
        self.single_action_space = gym.spaces.Discrete(NUM_ACTIONS)
        self.Levels = MazeLevels
        self.Student = MazeStudent
        self.Teacher = MazeTeacher
        self.solved_threshold = 0.0  # solved = return > 0
        self.validation_levels = ("SixteenRooms", "Labyrinth", "Maze")  # the paper's validation mazes
        self.level_metric_names = ("walls", "passable", "path_length")
        self.level_generators = {"random": self.random_levels, "empty": self.empty_levels}
        self.training = True  # the maze has no training-only reward shaping; kept for the common interface

    def close(self) -> None:
        """Nothing to release: the maze runs in this process (the common interface of every env)."""

    # --- level generators, teacher, held-out set, mutation, metrics, rendering -------------------------
    def teacher(self) -> MazeTeacherMDP:
        return MazeTeacherMDP(self.block_budget, self.uniform_budget, self.rng)

    def random_levels(self, n: int, rng: np.random.Generator) -> MazeLevels:
        """The DR generator: a uniformly random teacher run through the teacher MDP's placement rules."""
        mdp = MazeTeacherMDP(self.block_budget, self.uniform_budget, rng)
        mdp.reset(n)
        for _ in range(mdp.num_steps):
            mdp.place(rng.integers(0, mdp.num_actions, n))
        return mdp.levels()

    def empty_levels(self, n: int, rng: np.random.Generator) -> MazeLevels:
        """ACCEL's "empty" generator: no walls, goal and agent on two distinct random interior cells."""
        cells = np.argsort(rng.random((n, (TRAIN_SIZE - 2) ** 2)), axis=1)[:, :2]
        xy = np.stack([cells % (TRAIN_SIZE - 2) + 1, cells // (TRAIN_SIZE - 2) + 1], axis=2)
        return MazeLevels(empty_grid(n, TRAIN_SIZE), xy[:, 0], xy[:, 1], np.full(n, RANDOM_DIRECTION, np.int8))

    def mutate(self, levels: MazeLevels, rng: np.random.Generator, num_edits: int = 5) -> MazeLevels:
        """ACCEL's maze editor, as the reference's ACCEL mazes edit (dcd's `mutate_level` with the
        wall / empty / goal editor): `num_edits` random interior cells per level, drawn with replacement
        (a repeated cell is edited once), each set to wall, empty or goal with equal probability. An
        edited cell loses what it held; a goal edit moves the goal there. A goal or agent start that an
        edit erased is placed afterwards on a uniformly random cell that was free (no wall, goal or
        agent) after the edits, the goal first. So the start moves only when an edit lands on it."""
        child = levels.copy()
        n, h, w = child.walls.shape
        index = np.arange(n)
        free = ~child.walls
        free[index, child.goal[:, 1], child.goal[:, 0]] = False
        free[index, child.agent[:, 1], child.agent[:, 0]] = False
        goal_erased = np.zeros(n, dtype=bool)
        agent_erased = np.zeros(n, dtype=bool)
        edited = np.zeros((num_edits, n, 2), dtype=np.int64)
        for e in range(num_edits):
            xy = np.stack([rng.integers(1, w - 1, n), rng.integers(1, h - 1, n)], axis=1)
            kind = rng.integers(0, 3, n)  # 0 wall, 1 empty, 2 goal
            edited[e] = xy
            act = ~np.any(np.all(edited[:e] == xy, axis=2), axis=0)  # first edit of this cell
            x, y = xy[:, 0], xy[:, 1]
            goal_erased |= act & np.all(xy == child.goal, axis=1)
            agent_erased |= act & np.all(xy == child.agent, axis=1)
            child.walls[index[act], y[act], x[act]] = kind[act] == 0
            moved_goal = act & (kind == 2)
            old_goal = moved_goal & ~goal_erased  # the goal leaves its old cell, which becomes free
            free[index[old_goal], child.goal[old_goal, 1], child.goal[old_goal, 0]] = True
            free[index[act], y[act], x[act]] = kind[act] == 1
            child.goal[moved_goal] = xy[moved_goal]
            goal_erased &= ~moved_goal
        for erased, position in ((goal_erased, child.goal), (agent_erased, child.agent)):
            if erased.any():
                position[erased] = random_free_cells(free[erased], rng)
                free[index[erased], position[erased, 1], position[erased, 0]] = False
        return child

    def draw_starts(self, levels: MazeLevels) -> MazeLevels:
        """The levels with every random start direction drawn now (PAIRED's two students then play
        each level from the same start, so their regret compares like with like)."""
        drawn = levels.copy()
        drawn.agent_dir = self.drawn_directions(levels.agent_dir).astype(np.int8)
        return drawn

    def drawn_directions(self, agent_dir: np.ndarray) -> np.ndarray:
        """The start directions with every random one (RANDOM_DIRECTION) drawn from the env's generator."""
        directions = agent_dir.astype(np.int64)
        random = directions < 0
        directions[random] = self.rng.integers(0, 4, int(random.sum()))
        return directions

    def optimal_returns(self, levels: MazeLevels) -> np.ndarray:
        """The best achievable return of each level from its start (see `optimal_returns`): with the
        student's expected return, it gives the level's true regret."""
        return optimal_returns(levels, TRAIN_MAX_STEPS)

    def test_levels(self) -> HeldOutLevels:
        """The 12 held-out mazes (`envs.maze.held_out.held_out_levels`)."""
        return held_out_levels()

    level_metrics = staticmethod(level_metrics)
    render = staticmethod(render_levels)

    def render_trajectory(self, level: MazeLevels, positions: np.ndarray) -> np.ndarray:
        """One level's image [H*8, W*8, 3] (level: a batch of one) with the cells an agent visited in
        blue: positions [T, 2] are its (x, y) cells, e.g. agent_positions() collected over an episode."""
        cells = np.asarray(positions, dtype=np.int64).reshape(-1, 2)
        visited = np.zeros((1, *level.size), dtype=bool)
        visited[0, cells[:, 1], cells[:, 0]] = True
        return render_levels(level, visited)[0]

    # --- the vectorized student env ---------------------------------------------------------------
    def reset(self, levels: MazeLevels, max_steps: int = TRAIN_MAX_STEPS) -> dict:
        """Copy i now plays levels[i]; returns the first observations."""
        if len(levels) != self.num_envs:
            raise ValueError(f"reset got {len(levels)} levels for {self.num_envs} env copies")
        self.max_steps = max_steps
        layout = student_layout(levels)
        self.width, self.codes, self.base, self.start, self.move, self.view = (layout[k] for k in ("width", "codes", "base", "start", "move", "view"))
        self.start_dir = self.drawn_directions(levels.agent_dir)
        self.pos = self.start.copy()
        self.dir = np.zeros(self.num_envs, dtype=np.int64)
        self.t = np.zeros(self.num_envs, dtype=np.int64)
        self._restart(np.ones(self.num_envs, dtype=bool))
        return self._observation()

    def step(self, actions):
        a = np.asarray(actions)
        self.dir = (self.dir + TURN[a]) & 3
        target = self.pos + self.move[self.dir]
        cell = self.codes[self.base + target]
        moved = (a == FORWARD) & (cell != WALL)
        self.pos = np.where(moved, target, self.pos)
        self.t += 1
        terminated = moved & (cell == GOAL)
        reward = np.zeros(self.num_envs, dtype=np.float32)
        if terminated.any():
            reward[terminated] = 1.0 - 0.9 * self.t[terminated] / self.max_steps
        truncated = (self.t >= self.max_steps) & ~terminated
        done = terminated | truncated
        if done.any():
            self._restart(done)
        return self._observation(), reward, terminated, truncated, {}

    def agent_positions(self) -> np.ndarray:
        """Current (x, y) of every copy, for drawing paths."""
        pad = VIEW_SIZE - 1
        return np.stack([self.pos % self.width - pad, self.pos // self.width - pad], axis=1)

    def _restart(self, done: np.ndarray) -> None:
        self.pos[done] = self.start[done]
        self.dir[done] = self.start_dir[done]
        self.t[done] = 0

    def _observation(self) -> dict:
        # np.take: ~30% faster than indexing with an index array at these sizes.
        cells = np.take(self.codes, (self.base + self.pos)[:, None] + np.take(self.view, self.dir, axis=0))
        cells[:, -1 - VIEW_SIZE // 2] = EMPTY  # the agent's own cell
        return {"image": np.take(CELL_ENCODING, cells, axis=0).reshape(self.num_envs, VIEW_SIZE, VIEW_SIZE, 3), "direction": self.dir.copy()}


# ---------------------------------------------------------------------------------------------------
# Networks: the paper's, with the calling convention of envs/nets.py.
# ---------------------------------------------------------------------------------------------------
class MazeStudent(RecurrentCategoricalActorCritic):
    """Conv 3->16 (3x3) on the 5x5 view -> 144, ReLU; direction one-hot -> Linear 5; LSTM 256;
    actor 256 -> 32 tanh -> 7 logits; critic 256 -> 32 tanh -> 1. `conv_channels` and `hidden_size` (the
    LSTM's) change its sizes; a run records the class it trained, which evaluation and --resume build with
    no arguments, so other sizes belong in a subclass's defaults.

    To try another network, subclass it: a subclass runs exactly what it defines. This class itself
    acts through a faster path derived from it, at any sizes (envs/maze/fast_paths.py), which
    tests/test_fast_paths.py checks against it."""

    FastPath = MazeStudentFastPath
    image_scale = 10.0  # the view's MiniGrid codes are divided by 10
    direction_size = 5  # the direction embedding's width

    def __init__(self, hidden_size: int = 256, conv_channels: int = 16):
        super().__init__()
        self.conv = layer_init(nn.Conv2d(3, conv_channels, 3))
        self.direction_embed = layer_init(nn.Linear(4, self.direction_size))
        self.lstm = ResettableLSTM(conv_channels * (VIEW_SIZE - 2) ** 2 + self.direction_size, hidden_size)
        self.actor = nn.Sequential(layer_init(nn.Linear(hidden_size, 32)), nn.Tanh(), layer_init(nn.Linear(32, NUM_ACTIONS), gain=0.01))
        self.critic = nn.Sequential(layer_init(nn.Linear(hidden_size, 32)), nn.Tanh(), layer_init(nn.Linear(32, 1), gain=1.0))

    def features(self, obs: dict) -> torch.Tensor:
        """[ReLU(conv(view / 10)) flattened as (channel, y, x), direction embedding] from the env's observation."""
        view = torch.relu(self.conv(obs["image"].permute(0, 3, 1, 2).float() / self.image_scale)).flatten(1)
        direction = self.direction_embed(nn.functional.one_hot(obs["direction"].long(), 4).float())
        return torch.cat([view, direction], dim=1)


class MazeTeacher(RecurrentCategoricalActorCritic):
    """Conv 3->128 (3x3) on the 15x15 grid -> 21632, ReLU; time one-hot -> Linear 10; noise (50);
    LSTM 256; actor 256 -> 32 tanh -> 169 logits; critic 256 -> 32 tanh -> 1. `conv_channels` below
    the paper's 128 gives a lighter teacher (its LSTM input shrinks in proportion).

    Its LSTM's input projection has 22M weights at 128 channels. This class acts and trains through a
    faster path derived from it (envs/maze/fast_paths.py): a teacher step changes at most one cell of the
    grid, so only the conv windows over changed cells are projected. A subclass runs exactly what it
    defines."""

    FastPath = MazeTeacherFastPath
    image_scale = 10.0  # the grid's MiniGrid codes are divided by 10

    def __init__(self, num_steps: int, size: int = TRAIN_SIZE, hidden_size: int = 256, conv_channels: int = 128):
        super().__init__()
        self.num_steps = num_steps
        self.conv = nn.Sequential(layer_init(nn.Conv2d(3, conv_channels, 3)), nn.ReLU(), nn.Flatten())
        self.time_embed = layer_init(nn.Linear(num_steps, 10))
        self.lstm = ResettableLSTM(conv_channels * (size - 2) ** 2 + 10 + NOISE_DIM, hidden_size)
        num_actions = (size - 2) ** 2
        self.actor = nn.Sequential(layer_init(nn.Linear(hidden_size, 32)), nn.Tanh(), layer_init(nn.Linear(32, num_actions), gain=0.01))
        self.critic = nn.Sequential(layer_init(nn.Linear(hidden_size, 32)), nn.Tanh(), layer_init(nn.Linear(32, 1), gain=1.0))

    def features(self, obs: dict) -> torch.Tensor:
        image = obs["image"].permute(0, 3, 1, 2).float() / self.image_scale
        return torch.cat([self.conv(image), self.dense_features(obs)], dim=1)

    def dense_features(self, obs: dict) -> torch.Tensor:
        """The LSTM input's small dense part: the time embedding (10) and the noise (50)."""
        time = nn.functional.one_hot(obs["time"].long(), self.num_steps).float()
        return torch.cat([self.time_embed(time), obs["noise"].float()], dim=1)
