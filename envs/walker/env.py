"""The BipedalWalker UPOMDP: gymnasium's walker on terrain a teacher designs.

Everything an algorithm script needs for the walker: the student env (`WalkerEnv`), the teacher's MDP
(PAIRED's adversary), the DR and "easy" generators, ACCEL's mutation, level metrics, rendering, the
held-out courses and the paper's networks. A level's parameters and its terrain are in
envs/walker/terrain.py; gymnasium's step for many copies at once is in envs/walker/stepping.py.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium.envs.box2d import bipedal_walker as gym_walker
from torch import nn
from torch.distributions import Independent, Normal

from envs.levels import HeldOutLevel, HeldOutLevels
from envs.nets import FeedForwardActorCritic, layer_init
from envs.walker.stepping import ACTION_DIM, OBS_DIM, DesignedBipedalWalker, WalkerGroup
from envs.walker.terrain import (
    CUSTOM,
    EASY_PARAMS,
    EASY_ROUGHNESS_HIGH,
    GYM_FLAT,
    GYM_HARDCORE,
    MUTATION_SIZE,
    NUM_EDITS,
    NUM_PARAMS,
    PARAM_HIGH,
    PARAM_LOW,
    PARAM_NAMES,
    ROUGHNESS,
    SEED_BOUND,
    TERRAIN_HEIGHT,
    TERRAIN_LENGTH,
    TERRAIN_STEP,
    WalkerLevels,
    check_levels,
    order_pairs,
)

TRAIN_MAX_STEPS = 2000
NOISE_DIM = 10


# ---------------------------------------------------------------------------------------------------
# The teacher's MDP (PAIRED's adversary): one parameter per step.
# ---------------------------------------------------------------------------------------------------
class WalkerTeacherMDP:
    """PAIRED's adversary MDP over n levels in lockstep: 8 steps, step t sets parameter t (PARAM_NAMES
    order) from an action a in [-1, 1] (clipped), mapped linearly onto its full range: -1 -> low,
    +1 -> high. Observation: "params" [n, 8] float32, the parameters set so far normalised to [0, 1] by
    their full ranges (0 while unset); "noise" [n, 10] U[0, 1) redrawn each step from the env's rng;
    "time" [n] int64, the step index. `levels()` sorts each (low, high) pair and draws terrain seeds."""

    num_steps = NUM_PARAMS
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    observation_space = gym.spaces.Dict(
        {
            "params": gym.spaces.Box(0.0, 1.0, (NUM_PARAMS,), np.float32),
            "noise": gym.spaces.Box(0.0, 1.0, (NOISE_DIM,), np.float32),
            "time": gym.spaces.Discrete(NUM_PARAMS),
        }
    )

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def reset(self, n: int) -> dict:
        """Start designing n levels, every parameter unset; -> the first observation."""
        self.n = n
        self.t = 0
        self.normalised = np.zeros((n, NUM_PARAMS), dtype=np.float32)
        return self._observation()

    def step(self, actions) -> tuple[dict, bool]:
        """Set parameter t of every level; -> (observation, done), done after the 8th step."""
        a = np.clip(np.asarray(actions, dtype=np.float64).reshape(self.n), -1.0, 1.0)
        self.normalised[:, self.t] = (a + 1.0) / 2.0
        self.t += 1
        return self._observation(), self.t >= self.num_steps

    def levels(self) -> WalkerLevels:
        """The designed levels (after the last step): pairs ordered, fresh terrain seeds."""
        params = order_pairs(PARAM_LOW + self.normalised.astype(np.float64) * (PARAM_HIGH - PARAM_LOW))
        return WalkerLevels(params, self.rng.integers(0, SEED_BOUND, self.n), np.full(self.n, CUSTOM, np.int8))

    def _observation(self) -> dict:
        return {
            "params": self.normalised.copy(),
            "noise": self.rng.random((self.n, NOISE_DIM), dtype=np.float32),
            "time": np.full(self.n, min(self.t, self.num_steps - 1), dtype=np.int64),
        }


# ---------------------------------------------------------------------------------------------------
# Level metrics and rendering.
# ---------------------------------------------------------------------------------------------------
LEVEL_METRIC_NAMES = PARAM_NAMES + ("difficulty",)


def level_metrics(levels: WalkerLevels) -> dict[str, np.ndarray]:
    """The 8 parameters by name, and "difficulty": their mean normalised by the full ranges (0 .. 1)."""
    params = np.asarray(levels.params, dtype=np.float64)
    metrics = {name: params[:, j] for j, name in enumerate(PARAM_NAMES)}
    metrics["difficulty"] = ((params - PARAM_LOW) / (PARAM_HIGH - PARAM_LOW)).mean(axis=1)
    return metrics


RENDER_HEIGHT, RENDER_WIDTH = 96, 256
SKY, GROUND, OBSTACLE, TRACE, START = (np.array(c, dtype=np.uint8) for c in ([215, 215, 255], [102, 153, 76], [30, 30, 30], [220, 30, 30], [230, 51, 0]))
WORLD_WIDTH = TERRAIN_LENGTH * TERRAIN_STEP
VERTICAL_EXAGGERATION = 3.0  # heights drawn up to 3x the horizontal scale, so small obstacles show
# A terrain step is 1.3 pixels wide, so a stump or a pit wall drawn to scale is a hairline that vanishes
# in a grid of thumbnails: obstacles are drawn at least this many pixels wide (about their centre) and
# high (up from their base), in near-black against the light sky and the green ground.
MIN_OBSTACLE_PIXELS = 4


def _draw_course(walker: DesignedBipedalWalker, trace: np.ndarray | None) -> np.ndarray:
    """One RGB image [96, 256, 3] of the course the walker is on: sky, ground below the terrain line,
    obstacles in near-black (at least MIN_OBSTACLE_PIXELS wide and high), the start flag, and an
    optional hull trace [T, 2] (world x, y) in red. The horizontal scale is fixed (the whole course);
    the vertical one is 3x larger unless the course is too high to fit, and the view is centred on the
    terrain's height range."""
    ground_x, ground_y = np.asarray(walker.terrain_x), np.asarray(walker.terrain_y)
    boxes = walker.obstacle_boxes()
    heights = np.concatenate([ground_y, boxes[:, 1], boxes[:, 3]])
    low, high = heights.min(), heights.max()
    scale = RENDER_WIDTH / WORLD_WIDTH
    scale_y = min(VERTICAL_EXAGGERATION * scale, (RENDER_HEIGHT - 8) / max(high - low, 1e-6))
    centre = (low + high) / 2
    columns = (np.arange(RENDER_WIDTH) + 0.5) / scale
    rows = centre + (RENDER_HEIGHT / 2 - (np.arange(RENDER_HEIGHT) + 0.5)) / scale_y  # world y of each row
    image = np.broadcast_to(SKY, (RENDER_HEIGHT, RENDER_WIDTH, 3)).copy()
    image[rows[:, None] < np.interp(columns, ground_x, ground_y)[None, :]] = GROUND
    if len(boxes):
        middle = (boxes[:, 0] + boxes[:, 2]) / 2
        half_width = np.maximum((boxes[:, 2] - boxes[:, 0]) / 2, MIN_OBSTACLE_PIXELS / 2 / scale)
        top = np.maximum(boxes[:, 3], boxes[:, 1] + MIN_OBSTACLE_PIXELS / scale_y)
        inside = (
            (np.abs(columns[None, None, :] - middle[:, None, None]) <= half_width[:, None, None])
            & (rows[None, :, None] >= boxes[:, 1, None, None])
            & (rows[None, :, None] <= top[:, None, None])
        )
        image[inside.any(axis=0)] = OBSTACLE

    def to_pixels(x, y):
        col = np.clip((np.asarray(x) * scale).astype(np.int64), 0, RENDER_WIDTH - 1)
        row = np.clip((RENDER_HEIGHT / 2 - (np.asarray(y) - centre) * scale_y).astype(np.int64), 0, RENDER_HEIGHT - 1)
        return row, col

    flag_row, flag_col = to_pixels(TERRAIN_STEP * 3, TERRAIN_HEIGHT + np.linspace(0, 50 / gym_walker.SCALE, 6))
    image[flag_row, flag_col] = START
    if trace is not None and len(trace):
        trace_row, trace_col = to_pixels(trace[:, 0], trace[:, 1])
        image[trace_row, trace_col] = TRACE
    return image


# ---------------------------------------------------------------------------------------------------
# The student env.
# ---------------------------------------------------------------------------------------------------
class WalkerEnv:
    """The walker UPOMDP over `num_envs` copies, all stepped in this process (`WalkerGroup`).

    Observation: {"state": float32 [N, 24]}, gymnasium's (hull angle, angular velocity, x/y velocity,
    hip/knee angles and speeds, leg contacts, 10 lidar fractions). Action: [N, 4] in [-1, 1] (clipped:
    the Gaussian sample may leave the box). Reward, termination (hull contact or falling: -100; reaching
    the end of the course) are gymnasium's; at max_steps (2000 in training) the episode is truncated.
    Either way the copy restarts its level at once (same terrain, same initial push). `info` holds
    "hull_position" [N, 2], the hull's (x, y) after the step (before any restart), for drawing runs.
    """

    def __init__(self, num_envs: int = 16, seed: int = 0):
        if num_envs < 1:
            raise ValueError(f"the walker env needs at least one copy, got num_envs={num_envs}")
        self.num_envs = num_envs
        self.rng = np.random.default_rng(seed)
        self.single_observation_space = gym.spaces.Dict({"state": gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)})
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)
        self.Levels = WalkerLevels
        self.Student = WalkerStudent
        self.Teacher = WalkerTeacher
        self.solved_threshold = 230.0  # solved = return > 230
        self.validation_levels = ("BipedalWalker-v3", "Stairs", "PitGap")
        self.level_metric_names = LEVEL_METRIC_NAMES
        self.level_generators = {"random": self.random_levels, "easy": self.easy_levels}
        self.training = True  # no training-only reward shaping for the walker; kept for the interface
        self.walkers: WalkerGroup | None = None  # made at the first reset
        self._renderer: DesignedBipedalWalker | None = None

    def close(self) -> None:
        """Nothing to release: the copies run in this process (the common interface of every env)."""

    # --- the student env -------------------------------------------------------------------------------
    def reset(self, levels: WalkerLevels, max_steps: int | None = None) -> dict:
        """Copy i now plays levels[i]; -> the first observations."""
        if len(levels) != self.num_envs:
            raise ValueError(f"reset got {len(levels)} levels for {self.num_envs} env copies")
        check_levels(levels)
        max_steps = TRAIN_MAX_STEPS if max_steps is None else int(max_steps)
        if max_steps < 1:
            raise ValueError(f"max_steps must be positive, got {max_steps}")
        if self.walkers is None:
            self.walkers = WalkerGroup(self.num_envs)
        obs = self.walkers.reset(np.asarray(levels.params, dtype=np.float64), np.asarray(levels.course), np.asarray(levels.seed), max_steps)
        return {"state": obs}

    def step(self, actions: np.ndarray):
        """Step every copy with actions [N, 4] (clipped to [-1, 1]); -> obs, reward, terminated,
        truncated, info (see the class docstring)."""
        if self.walkers is None:
            raise RuntimeError("WalkerEnv.step called before reset")
        actions = np.clip(np.asarray(actions, dtype=np.float32).reshape(self.num_envs, ACTION_DIM), -1.0, 1.0)
        obs, reward, terminated, truncated, hull_position = self.walkers.step(actions)
        return {"state": obs}, reward, terminated, truncated, {"hull_position": hull_position}

    # --- level generators, teacher, held-out set, mutation, metrics, rendering -------------------------
    def random_levels(self, n: int, rng: np.random.Generator) -> WalkerLevels:
        """The DR generator: every parameter uniform over its full range, pairs ordered, fresh seeds."""
        params = order_pairs(PARAM_LOW + rng.random((n, NUM_PARAMS)) * (PARAM_HIGH - PARAM_LOW))
        return WalkerLevels(params, rng.integers(0, SEED_BOUND, n), np.full(n, CUSTOM, np.int8))

    def easy_levels(self, n: int, rng: np.random.Generator) -> WalkerLevels:
        """ACCEL's "easy" generator: roughness U[0, 0.6]; pit [0, 0.8], stump [0, 0.4],
        stair [0, 0.4], steps 1; fresh seeds."""
        params = np.tile(EASY_PARAMS, (n, 1))
        params[:, ROUGHNESS] = rng.uniform(0.0, EASY_ROUGHNESS_HIGH, n)
        return WalkerLevels(params, rng.integers(0, SEED_BOUND, n), np.full(n, CUSTOM, np.int8))

    def teacher(self) -> WalkerTeacherMDP:
        """PAIRED's adversary MDP, its noise drawn from the env's rng."""
        return WalkerTeacherMDP(self.rng)

    def optimal_returns(self, levels: WalkerLevels) -> None:
        """None: this env has no solver for a level's best return (the maze has one)."""
        return None

    def draw_starts(self, levels: WalkerLevels) -> WalkerLevels:
        """The levels unchanged: their start has no random part (the maze draws a start direction)."""
        return levels

    def mutate(self, levels: WalkerLevels, rng: np.random.Generator, num_edits: int = NUM_EDITS) -> WalkerLevels:
        """ACCEL's walker editor: `num_edits` edits per level, each picking a parameter and a
        direction in {-1, 0, +1} and moving it by its edit size (roughness: U(0, 0.6)); clipped to the
        full ranges, pairs kept ordered, a new terrain seed. The child is a CUSTOM course."""
        params = np.array(levels.params, dtype=np.float64)
        n = len(params)
        rows = np.arange(n)
        for _ in range(num_edits):
            which = rng.integers(0, NUM_PARAMS, n)
            direction = rng.integers(-1, 2, n)
            size = np.where(which == ROUGHNESS, rng.uniform(0.0, MUTATION_SIZE[ROUGHNESS], n), MUTATION_SIZE[which])
            params[rows, which] = np.clip(params[rows, which] + direction * size, PARAM_LOW[which], PARAM_HIGH[which])
        return WalkerLevels(order_pairs(params), rng.integers(0, SEED_BOUND, n), np.full(n, CUSTOM, np.int8))

    def test_levels(self) -> HeldOutLevels:
        """The held-out courses (`held_out_levels`)."""
        return held_out_levels()

    level_metrics = staticmethod(level_metrics)

    def render(self, levels: WalkerLevels) -> np.ndarray:
        """Terrain profiles, uint8 RGB [B, 96, 256, 3] (the whole 200-step course of each level)."""
        return np.stack([self._course_image(levels[i], None) for i in range(len(levels))])

    def render_trajectory(self, level: WalkerLevels, positions: np.ndarray) -> np.ndarray:
        """One level's profile [96, 256, 3] (level: a batch of one) with a walker's run drawn over it in
        red: positions [T, 2] is the hull's (x, y) trace, e.g. agent_positions() collected over an episode."""
        return self._course_image(level, np.asarray(positions, dtype=np.float64).reshape(-1, 2))

    def agent_positions(self) -> np.ndarray:
        """The hull's (x, y) of every copy [N, 2], in Box2D world units."""
        return np.array([tuple(walker.hull.position) for walker in self.walkers.walkers])

    def _course_image(self, level: WalkerLevels, trace: np.ndarray | None) -> np.ndarray:
        check_levels(level)
        if self._renderer is None:
            self._renderer = DesignedBipedalWalker()
        self._renderer.play(level.params[0], level.course[0], level.seed[0])
        return _draw_course(self._renderer, trace)


# ---------------------------------------------------------------------------------------------------
# The held-out courses.
# ---------------------------------------------------------------------------------------------------
def _course_params(**values) -> np.ndarray:
    """A parameter vector: roughness 0, every obstacle off, stair_steps 1, except the given values."""
    params = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    for name, value in values.items():
        params[PARAM_NAMES.index(name)] = value
    return params


# The held-out courses: name -> (params, course kind, max_steps). The gymnasium courses' params only
# describe them (for the metrics): gymnasium's grass has roughness 1; its hardcore pits are 3-4 steps
# (gap 2-3), stumps 1-2 steps high, stairs 1 step high with 3-4 steps. Custom test courses as the
# reference's test envs.
HELD_OUT_COURSES = {
    "BipedalWalker-v3": (_course_params(roughness=1.0), GYM_FLAT, 1600),
    "BipedalWalkerHardcore-v3": (
        _course_params(roughness=1.0, pit_gap_low=2.0, pit_gap_high=3.0, stump_height_low=1.0, stump_height_high=2.0,
                       stair_height_low=1.0, stair_height_high=1.0, stair_steps=5.0),
        GYM_HARDCORE,
        2000,
    ),
    "Stairs": (_course_params(stair_height_low=2.0, stair_height_high=2.0, stair_steps=5.0), CUSTOM, 2000),
    "PitGap": (_course_params(pit_gap_low=5.0, pit_gap_high=5.0), CUSTOM, 2000),
    "Stump": (_course_params(stump_height_low=2.0, stump_height_high=2.0), CUSTOM, 2000),
    "Roughness": (_course_params(roughness=5.0), CUSTOM, 2000),
}


def held_out_levels() -> HeldOutLevels:
    """The held-out courses by name (HELD_OUT_COURSES), each a fresh terrain seed per generated level."""
    return HeldOutLevels(
        {name: HeldOutLevel(_course_generator(params, course), max_steps) for name, (params, course, max_steps) in HELD_OUT_COURSES.items()}
    )


def _course_generator(params: np.ndarray, course: int):
    """generate(n, rng) for a held-out course: its parameters repeated, a fresh terrain seed each."""

    def generate(n: int, rng: np.random.Generator) -> WalkerLevels:
        return WalkerLevels(np.tile(params, (n, 1)), rng.integers(0, SEED_BOUND, n), np.full(n, course, np.int8))

    return generate


# ---------------------------------------------------------------------------------------------------
# Networks: the paper's, with the calling convention of envs/nets.py.
# ---------------------------------------------------------------------------------------------------
def _mlp(inputs: int, outputs: int, gain: float, hidden: int = 64) -> nn.Sequential:
    """inputs -> 64 -> 64 (tanh) -> outputs, orthogonal init (sqrt(2) hidden, `gain` for the head)."""
    return nn.Sequential(
        layer_init(nn.Linear(inputs, hidden)), nn.Tanh(), layer_init(nn.Linear(hidden, hidden)), nn.Tanh(), layer_init(nn.Linear(hidden, outputs), gain=gain)
    )


class WalkerStudent(FeedForwardActorCritic):
    """Separate tanh MLPs 64-64 for the actor (24 -> 4 means) and the critic (24 -> 1); a diagonal
    Gaussian with a state-free log-std parameter (init 0)."""

    def __init__(self):
        super().__init__()
        self.actor_mean = _mlp(OBS_DIM, ACTION_DIM, gain=0.01)
        self.actor_logstd = nn.Parameter(torch.zeros(ACTION_DIM))
        self.critic = _mlp(OBS_DIM, 1, gain=1.0)

    def dist_and_value(self, obs: dict, state=None, done=None):
        x = obs["state"].float()
        mean = self.actor_mean(x)
        dist = Independent(Normal(mean, self.actor_logstd.exp().expand_as(mean)), 1)
        return dist, self.critic(x).squeeze(-1)


class WalkerTeacher(FeedForwardActorCritic):
    """PAIRED's walker adversary: params (8) + noise (10) + time one-hot (num_steps) -> separate tanh
    MLPs 64-64 for the actor (-> 1 mean, state-free log-std, init 0) and the critic (-> 1)."""

    def __init__(self, num_steps: int = NUM_PARAMS):
        super().__init__()
        self.num_steps = num_steps
        inputs = NUM_PARAMS + NOISE_DIM + num_steps
        self.actor_mean = _mlp(inputs, 1, gain=0.01)
        self.actor_logstd = nn.Parameter(torch.zeros(1))
        self.critic = _mlp(inputs, 1, gain=1.0)

    def dist_and_value(self, obs: dict, state=None, done=None):
        time = nn.functional.one_hot(obs["time"].long(), self.num_steps).float()
        x = torch.cat([obs["params"].float(), obs["noise"].float(), time], dim=1)
        mean = self.actor_mean(x)
        dist = Independent(Normal(mean, self.actor_logstd.exp().expand_as(mean)), 1)
        return dist, self.critic(x).squeeze(-1)
