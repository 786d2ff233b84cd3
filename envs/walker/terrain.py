"""The walker's levels and their terrain: what a teacher designs, and the course it becomes.

A level is 8 numbers (POET's parameters, `PARAM_NAMES`), a terrain seed and a course kind: `CUSTOM`
courses are built from the parameters by `build_designed_terrain`, POET's generator in the structure of
gymnasium's hardcore one; `GYM_FLAT` and `GYM_HARDCORE` are gymnasium's own BipedalWalker-v3 /
BipedalWalkerHardcore-v3 generators, unchanged (held-out set). envs/walker/stepping.py plays them.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from gymnasium.envs.box2d import bipedal_walker as gym_walker

from envs.levels import LevelBatch

# --- the level parameters -------------------------------------------------------------------
PARAM_NAMES = (
    "roughness",
    "pit_gap_low",
    "pit_gap_high",
    "stump_height_low",
    "stump_height_high",
    "stair_height_low",
    "stair_height_high",
    "stair_steps",
)
NUM_PARAMS = len(PARAM_NAMES)
ROUGHNESS, PIT_LOW, PIT_HIGH, STUMP_LOW, STUMP_HIGH, STAIR_LOW, STAIR_HIGH, STAIR_STEPS = range(NUM_PARAMS)
RANGE_PAIRS = ((PIT_LOW, PIT_HIGH), (STUMP_LOW, STUMP_HIGH), (STAIR_LOW, STAIR_HIGH))
PARAM_LOW = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
PARAM_HIGH = np.array([10.0, 10.0, 10.0, 5.0, 5.0, 5.0, 5.0, 9.0])
# An obstacle is enabled when the high end of its range reaches its threshold.
PIT_THRESHOLD, STUMP_THRESHOLD, STAIR_THRESHOLD = 0.8, 0.2, 0.2
# ACCEL's "easy" generator: roughness U[0, 0.6], the other ranges fixed.
EASY_ROUGHNESS_HIGH = 0.6
EASY_PARAMS = np.array([0.0, 0.0, 0.8, 0.0, 0.4, 0.0, 0.4, 1.0])
# ACCEL's mutation: the size of one edit of each parameter (roughness: U(0, 0.6)).
NUM_EDITS = 3
MUTATION_SIZE = np.array([0.6, 0.4, 0.4, 0.2, 0.2, 0.2, 0.2, 1.0])
SEED_BOUND = 2**31

CUSTOM, GYM_FLAT, GYM_HARDCORE = 0, 1, 2  # course kinds

# --- the terrain generator's constants (gymnasium's, and the reference's stairs) ----------------------
TERRAIN_STEP = gym_walker.TERRAIN_STEP
TERRAIN_LENGTH = gym_walker.TERRAIN_LENGTH
TERRAIN_HEIGHT = gym_walker.TERRAIN_HEIGHT
TERRAIN_GRASS = gym_walker.TERRAIN_GRASS
TERRAIN_STARTPAD = gym_walker.TERRAIN_STARTPAD
PIT_DEPTH = 4  # in terrain steps
STAIR_WIDTH = 4  # in terrain steps
# Stumps and stair steps lower than this (in terrain steps) are left out: Box2D rejects a flat
# polygon (the reference's STAIR_HEIGHT_EPS; for stumps the reference retried other seeds).
MIN_BLOCK_HEIGHT = 1e-2
GRASS, STUMP, STAIRS, PIT = range(4)  # the generator's states


@dataclasses.dataclass
class WalkerLevels(LevelBatch):
    """A batch of walker levels: params [B, 8] float64 (PARAM_NAMES order; stair_steps is a real number
    in [1, 9], rounded when the terrain is built, as in the reference), the terrain seed [B] int64 and
    the course kind [B] int8 (CUSTOM, GYM_FLAT, GYM_HARDCORE). For the gymnasium courses the params only
    describe the course (for metrics); their terrain is gymnasium's."""

    params: np.ndarray
    seed: np.ndarray
    course: np.ndarray


@dataclasses.dataclass(frozen=True)
class Feature:
    """One obstacle the generator placed: kind ("pit", "stump", "stairs"), the terrain step it starts
    at, its drawn size (pit: the gap U(lo, hi), the pit being 1 + gap steps wide; stump and stairs: the
    height in terrain steps), the number of stair steps and the stairs' direction (+1 up, -1 down)."""

    kind: str
    step: int
    size: float
    count: int = 0
    direction: int = 0


def enabled_obstacles(params: np.ndarray) -> tuple[int, ...]:
    """The obstacle kinds a level's parameters enable (thresholds on the high end)."""
    kinds = []
    if max(params[STUMP_LOW], params[STUMP_HIGH]) >= STUMP_THRESHOLD:
        kinds.append(STUMP)
    if max(params[STAIR_LOW], params[STAIR_HIGH]) >= STAIR_THRESHOLD:
        kinds.append(STAIRS)
    if max(params[PIT_LOW], params[PIT_HIGH]) >= PIT_THRESHOLD:
        kinds.append(PIT)
    return tuple(kinds)


def order_pairs(params: np.ndarray) -> np.ndarray:
    """Params [B, 8] with every (low, high) pair sorted so low <= high (in place; returned)."""
    for low, high in RANGE_PAIRS:
        pair = np.sort(params[:, [low, high]], axis=1)
        params[:, low], params[:, high] = pair[:, 0], pair[:, 1]
    return params


def check_levels(levels: WalkerLevels) -> None:
    """Raise ValueError (one line) unless every level's parameters lie in their full ranges."""
    params = np.asarray(levels.params, dtype=np.float64)
    if params.ndim != 2 or params.shape[1] != NUM_PARAMS:
        raise ValueError(f"walker levels need params of shape [B, {NUM_PARAMS}], got {params.shape}")
    bad = ~np.isfinite(params) | (params < PARAM_LOW) | (params > PARAM_HIGH)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise ValueError(f"walker level {i}: {PARAM_NAMES[j]} = {params[i, j]} is outside its range [{PARAM_LOW[j]:g}, {PARAM_HIGH[j]:g}]")
    unknown = ~np.isin(levels.course, (CUSTOM, GYM_FLAT, GYM_HARDCORE))
    if unknown.any():
        raise ValueError(f"walker level {np.argmax(unknown)}: unknown course kind {levels.course[np.argmax(unknown)]}")
    if np.any(np.asarray(levels.seed) < 0):
        raise ValueError("walker terrain seeds must be non-negative")




# ---------------------------------------------------------------------------------------------------
# POET's terrain generator, building into a gymnasium walker's Box2D world.
# ---------------------------------------------------------------------------------------------------
def build_designed_terrain(walker: gym_walker.BipedalWalker, params: np.ndarray, rng: np.random.Generator) -> list[Feature]:
    """POET's terrain from the level's parameters, in the structure of gymnasium's hardcore generator,
    as in the paper's reference implementation: 200 steps, a 20-step start pad, grass
    stretches of 5-9 steps, after each of which one enabled obstacle is drawn uniformly. Roughness
    scales the grass slope; a pit is 1 + U(gap) steps wide and 4 deep; a stump 1 step wide and
    U(height) high (the rest of its stretch stays flat, as in the reference); stairs U(height) per
    step, 4 steps wide, randint(steps) steps (0 .. steps-1), up or down. It stands in for gymnasium's
    `_generate_terrain`: it fills the same attributes of the walker (terrain: the Box2D bodies in its
    world; terrain_x, terrain_y: the ground line; terrain_poly: its fill, for drawing), drawing from
    `rng`; -> the obstacles it placed."""
    step = TERRAIN_STEP
    features = []
    pit_low, pit_high = sorted(params[[PIT_LOW, PIT_HIGH]])
    stump_low, stump_high = sorted(params[[STUMP_LOW, STUMP_HIGH]])
    stair_low, stair_high = sorted(params[[STAIR_LOW, STAIR_HIGH]])
    stair_steps = int(round(params[STAIR_STEPS]))
    obstacles = enabled_obstacles(params)

    state, velocity, y, counter, oneshot = GRASS, 0.0, TERRAIN_HEIGHT, TERRAIN_STARTPAD, False
    original_y = pit_shortfall = stair_height = 0.0
    stair_count = stair_direction = 0
    walker.terrain, walker.terrain_x, walker.terrain_y = [], [], []
    for i in range(TERRAIN_LENGTH):
        x = i * step
        walker.terrain_x.append(x)
        if state == GRASS and not oneshot:
            velocity = 0.8 * velocity + 0.01 * np.sign(TERRAIN_HEIGHT - y)
            if i > TERRAIN_STARTPAD:
                velocity += rng.uniform(-1, 1) / gym_walker.SCALE
            y += params[ROUGHNESS] * velocity
        elif state == PIT and oneshot:
            gap = rng.uniform(pit_low, pit_high)
            pit_width = 1.0 + gap
            counter = int(np.ceil(pit_width))
            pit_shortfall = counter - pit_width
            wall = [(x, y), (x + step, y), (x + step, y - PIT_DEPTH * step), (x, y - PIT_DEPTH * step)]
            _add_block(walker, wall)
            _add_block(walker, [(px + pit_width * step, py) for px, py in wall])
            features.append(Feature("pit", i, gap))
            counter += 2
            original_y = y
        elif state == PIT:
            y = original_y
            if counter > 1:
                y -= PIT_DEPTH * step
            if counter == 1:  # the ground climbs back at the far wall's outer edge
                walker.terrain_x[-1] -= pit_shortfall * step
        elif state == STUMP and oneshot:
            height = rng.uniform(stump_low, stump_high)
            if height >= MIN_BLOCK_HEIGHT:
                _add_block(walker, [(x, y), (x + step, y), (x + step, y + height * step), (x, y + height * step)])
                features.append(Feature("stump", i, height))
        elif state == STAIRS and oneshot:
            stair_height = rng.uniform(stair_low, stair_high)
            stair_direction = 1 if rng.random() > 0.5 else -1
            stair_count = int(rng.integers(stair_steps)) if stair_height >= MIN_BLOCK_HEIGHT else 0
            original_y = y
            for s in range(stair_count):
                top = y + s * stair_height * stair_direction * step
                left, right = x + s * STAIR_WIDTH * step, x + (s + 1) * STAIR_WIDTH * step
                _add_block(walker, [(left, top), (right, top), (right, top - stair_height * step), (left, top - stair_height * step)])
            if stair_count:
                features.append(Feature("stairs", i, stair_height, stair_count, stair_direction))
            counter = stair_count * STAIR_WIDTH + 1
        elif state == STAIRS:
            n = (stair_count * STAIR_WIDTH - counter) // STAIR_WIDTH
            y = original_y + n * stair_height * stair_direction * step - (stair_height * step if stair_direction < 0 else 0.0)
        oneshot = False
        walker.terrain_y.append(y)
        counter -= 1
        if counter == 0:
            counter = rng.integers(TERRAIN_GRASS // 2, TERRAIN_GRASS)
            if state == GRASS and obstacles:
                state = obstacles[rng.integers(len(obstacles))]
            else:
                state = GRASS
            oneshot = True
    _add_ground_edges(walker)
    return features


def _add_ground_edges(walker: gym_walker.BipedalWalker) -> None:
    """The ground line as edge bodies, plus its fill polygons for drawing (gymnasium's code)."""
    walker.terrain_poly = []
    for i in range(TERRAIN_LENGTH - 1):
        poly = [(walker.terrain_x[i], walker.terrain_y[i]), (walker.terrain_x[i + 1], walker.terrain_y[i + 1])]
        walker.fd_edge.shape.vertices = poly
        body = walker.world.CreateStaticBody(fixtures=walker.fd_edge)
        color = (76, 255 if i % 2 == 0 else 204, 76)
        body.color1 = body.color2 = color
        walker.terrain.append(body)
        poly += [(poly[1][0], 0), (poly[0][0], 0)]
        walker.terrain_poly.append((poly, (102, 153, 76)))
    walker.terrain.reverse()


def _add_block(walker: gym_walker.BipedalWalker, vertices) -> None:
    """A static obstacle polygon (pit wall, stump, stair step), coloured as gymnasium's."""
    walker.fd_polygon.shape.vertices = vertices
    body = walker.world.CreateStaticBody(fixtures=walker.fd_polygon)
    body.color1, body.color2 = (255, 255, 255), (153, 153, 153)
    walker.terrain.append(body)
