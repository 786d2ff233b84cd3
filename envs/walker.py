"""The BipedalWalker UPOMDP: gymnasium's walker on terrain a teacher designs.

The walker, its motors, lidar, 24-d observation, 4-d action and reward are gymnasium's own
(`gymnasium.envs.box2d.bipedal_walker.BipedalWalker`); `DesignedBipedalWalker` subclasses it and
replaces only the terrain generator. A level is 8 numbers (POET's parameters, `PARAM_NAMES`), a terrain
seed and a course kind: `CUSTOM` courses are built from the parameters; `GYM_FLAT` and `GYM_HARDCORE`
are gymnasium's own BipedalWalker-v3 / BipedalWalkerHardcore-v3 generators, unchanged (held-out set).

Everything random in an episode (terrain, clouds, the initial push of the hull) is drawn from the
level's terrain seed (gymnasium's `reset(seed=...)`) and every episode starts in a fresh Box2D world,
so a level replays identically at every restart, in any process.

Stepping is gymnasium's step with the same results, made cheaper (`WalkerGroup`): per copy only the
motors and the Box2D world step run in Python; the lidar (`TerrainLidar`: Box2D's raycast arithmetic,
vectorized), the observation and the reward are computed for all copies at once. The copies are stepped
in this process by default; worker processes can step shares of them side by side (`WalkerEnv`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import mmap
import multiprocessing
import os
import signal
import weakref

import Box2D
import gymnasium as gym
import numpy as np
import torch
from gymnasium.envs.box2d import bipedal_walker as gym_walker
from torch import nn
from torch.distributions import Independent, Normal

from envs.levels import HeldOutLevel, LevelBatch
from envs.nets import FeedForwardActorCritic, layer_init

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
TRAIN_MAX_STEPS = 2000
NOISE_DIM = 10
OBS_DIM, ACTION_DIM = 24, 4

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
# gymnasium's walker with a designed terrain: _generate_terrain is replaced, parts of step added.
# ---------------------------------------------------------------------------------------------------
class DesignedBipedalWalker(gym_walker.BipedalWalker):
    """gymnasium's BipedalWalker whose terrain comes from a level: `play(params, course, seed)` resets
    it onto that level. CUSTOM courses use POET's generator below (recording the obstacles it placed in
    `features`); GYM_FLAT and GYM_HARDCORE call gymnasium's own generator. gymnasium's `step` works as
    ever; `WalkerGroup` steps walkers with `advance` and `lidar_targets` instead (the same results)."""

    def __init__(self):
        super().__init__()
        self.params = EASY_PARAMS.copy()
        self.course = CUSTOM
        self.features: list[Feature] = []

    def play(self, params: np.ndarray, course: int, seed: int) -> np.ndarray:
        """Reset onto the level (terrain, clouds and initial push all from `seed`) in a fresh Box2D
        world, as the reference does: a reused world remembers its past (the order of its bodies'
        proxies), and the same actions then give a slightly different run; -> first obs. From then on
        the contacts are watched by a `GroundContacts` (gymnasium's detector, quicker)."""
        self.params = np.asarray(params, dtype=np.float64)
        self.course = int(course)
        self._destroy()
        self.world = Box2D.b2World()
        obs = self.reset(seed=int(seed))[0]
        self.contact_detector = GroundContacts(self)
        self.world.contactListener = self.contact_detector
        return obs

    def advance(self, action: list[float]) -> tuple:
        """gymnasium's step up to its readings: the motors set from `action` (4 floats in [-1, 1]) as
        gymnasium sets them (speed: the action's sign; torque: its size), one world step; -> 17 floats:
        the hull's x, y, angle, angular velocity, x and y velocity; per leg its hip's angle and speed,
        its knee's angle and speed and the lower leg's ground contact; game_over. The rest of the step
        (lidar, observation, reward) is done for many walkers at once by `WalkerGroup.step`, which keeps
        the reward's `prev_shaping` itself."""
        for joint, speed, a in zip(self.joints, MOTOR_SPEEDS, action):
            joint.motorSpeed = speed * ((a > 0) - (a < 0))
            joint.maxMotorTorque = gym_walker.MOTORS_TORQUE * min(abs(a), 1.0)
        self.world.Step(1.0 / gym_walker.FPS, 6 * 30, 2 * 30)
        hull, legs, (hip_a, knee_a, hip_b, knee_b) = self.hull, self.legs, self.joints
        position, velocity = hull.position, hull.linearVelocity
        return (
            position.x, position.y, hull.angle, hull.angularVelocity, velocity.x, velocity.y,
            hip_a.angle, hip_a.speed, knee_a.angle, knee_a.speed, legs[1].ground_contact,
            hip_b.angle, hip_b.speed, knee_b.angle, knee_b.speed, legs[3].ground_contact,
            self.game_over,
        )

    def lidar_targets(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """What gymnasium's lidar can hit (fixtures of category 1: the terrain) as Box2D holds it, in
        float32: the ground edges [E, 2, 2] (their two vertices) and, per obstacle polygon, its vertices
        and outward normals [2, m, 2] (Box2D's order)."""
        edges, polygons = [], []
        for body in self.terrain:
            for fixture in body.fixtures:
                if fixture.filterData.categoryBits & 1:
                    shape = fixture.shape
                    if isinstance(shape, Box2D.b2EdgeShape):
                        edges.append(shape.vertices)
                    else:
                        polygons.append(np.array([shape.vertices, shape.normals], dtype=np.float32))
        return np.array(edges, dtype=np.float32).reshape(-1, 2, 2), polygons

    def _generate_terrain(self, hardcore):
        self.features = []
        if self.course != CUSTOM:
            super()._generate_terrain(self.course == GYM_HARDCORE)
            return
        self._generate_designed_terrain()

    def _add_block(self, vertices) -> None:
        """A static obstacle polygon (pit wall, stump, stair step), coloured as gymnasium's."""
        self.fd_polygon.shape.vertices = vertices
        body = self.world.CreateStaticBody(fixtures=self.fd_polygon)
        body.color1, body.color2 = (255, 255, 255), (153, 153, 153)
        self.terrain.append(body)

    def _generate_designed_terrain(self) -> None:
        """POET's terrain from the level's parameters, in the structure of gymnasium's hardcore generator,
        as in the paper's reference implementation: 200 steps, a 20-step start pad, grass
        stretches of 5-9 steps, after each of which one enabled obstacle is drawn uniformly. Roughness
        scales the grass slope; a pit is 1 + U(gap) steps wide and 4 deep; a stump 1 step wide and
        U(height) high (the rest of its stretch stays flat, as in the reference); stairs U(height) per
        step, 4 steps wide, randint(steps) steps (0 .. steps-1), up or down."""
        params, rng, step = self.params, self.np_random, TERRAIN_STEP
        pit_low, pit_high = sorted(params[[PIT_LOW, PIT_HIGH]])
        stump_low, stump_high = sorted(params[[STUMP_LOW, STUMP_HIGH]])
        stair_low, stair_high = sorted(params[[STAIR_LOW, STAIR_HIGH]])
        stair_steps = int(round(params[STAIR_STEPS]))
        obstacles = enabled_obstacles(params)

        state, velocity, y, counter, oneshot = GRASS, 0.0, TERRAIN_HEIGHT, TERRAIN_STARTPAD, False
        original_y = pit_shortfall = stair_height = 0.0
        stair_count = stair_direction = 0
        self.terrain, self.terrain_x, self.terrain_y = [], [], []
        for i in range(TERRAIN_LENGTH):
            x = i * step
            self.terrain_x.append(x)
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
                self._add_block(wall)
                self._add_block([(px + pit_width * step, py) for px, py in wall])
                self.features.append(Feature("pit", i, gap))
                counter += 2
                original_y = y
            elif state == PIT:
                y = original_y
                if counter > 1:
                    y -= PIT_DEPTH * step
                if counter == 1:  # the ground climbs back at the far wall's outer edge
                    self.terrain_x[-1] -= pit_shortfall * step
            elif state == STUMP and oneshot:
                height = rng.uniform(stump_low, stump_high)
                if height >= MIN_BLOCK_HEIGHT:
                    self._add_block([(x, y), (x + step, y), (x + step, y + height * step), (x, y + height * step)])
                    self.features.append(Feature("stump", i, height))
            elif state == STAIRS and oneshot:
                stair_height = rng.uniform(stair_low, stair_high)
                stair_direction = 1 if rng.random() > 0.5 else -1
                stair_count = int(rng.integers(stair_steps)) if stair_height >= MIN_BLOCK_HEIGHT else 0
                original_y = y
                for s in range(stair_count):
                    top = y + s * stair_height * stair_direction * step
                    left, right = x + s * STAIR_WIDTH * step, x + (s + 1) * STAIR_WIDTH * step
                    self._add_block([(left, top), (right, top), (right, top - stair_height * step), (left, top - stair_height * step)])
                if stair_count:
                    self.features.append(Feature("stairs", i, stair_height, stair_count, stair_direction))
                counter = stair_count * STAIR_WIDTH + 1
            elif state == STAIRS:
                n = (stair_count * STAIR_WIDTH - counter) // STAIR_WIDTH
                y = original_y + n * stair_height * stair_direction * step - (stair_height * step if stair_direction < 0 else 0.0)
            oneshot = False
            self.terrain_y.append(y)
            counter -= 1
            if counter == 0:
                counter = rng.integers(TERRAIN_GRASS // 2, TERRAIN_GRASS)
                if state == GRASS and obstacles:
                    state = obstacles[rng.integers(len(obstacles))]
                else:
                    state = GRASS
                oneshot = True
        self._add_ground_edges()

    def _add_ground_edges(self) -> None:
        """The ground line as edge bodies, plus its fill polygons for drawing (gymnasium's code)."""
        self.terrain_poly = []
        for i in range(TERRAIN_LENGTH - 1):
            poly = [(self.terrain_x[i], self.terrain_y[i]), (self.terrain_x[i + 1], self.terrain_y[i + 1])]
            self.fd_edge.shape.vertices = poly
            body = self.world.CreateStaticBody(fixtures=self.fd_edge)
            color = (76, 255 if i % 2 == 0 else 204, 76)
            body.color1 = body.color2 = color
            self.terrain.append(body)
            poly += [(poly[1][0], 0), (poly[0][0], 0)]
            self.terrain_poly.append((poly, (102, 153, 76)))
        self.terrain.reverse()

    def obstacle_boxes(self) -> np.ndarray:
        """Bounding boxes [K, 4] (x0, y0, x1, y1) of the terrain's obstacle polygons (all axis-aligned)."""
        boxes = [
            (min(v[0] for v in vs), min(v[1] for v in vs), max(v[0] for v in vs), max(v[1] for v in vs))
            for body in self.terrain
            for fixture in body.fixtures
            if len(vs := fixture.shape.vertices) > 2
        ]
        return np.array(boxes, dtype=np.float64).reshape(-1, 4)


# ---------------------------------------------------------------------------------------------------
# Stepping: a group of walkers in one process, gymnasium's step done for all of them at once.
# ---------------------------------------------------------------------------------------------------
MOTOR_SPEEDS = (float(gym_walker.SPEED_HIP), float(gym_walker.SPEED_KNEE)) * 2  # the joints: hip, knee, hip, knee
LIDAR_RAYS = 10
# gymnasium's ray i leaves the hull 1.5 * i / 10 radians from straight down and is LIDAR_RANGE long; its
# end is the hull's position plus these offsets, computed in double precision as gymnasium does.
LIDAR_REACH_X = np.array([math.sin(1.5 * i / 10.0) * gym_walker.LIDAR_RANGE for i in range(LIDAR_RAYS)])
LIDAR_REACH_Y = np.array([-math.cos(1.5 * i / 10.0) * gym_walker.LIDAR_RANGE for i in range(LIDAR_RAYS)])
HULL_TAG = "hull"  # the hull's fixture userData for GroundContacts; the lower legs' is their index in legs
# gymnasium subtracts each joint's cost, a Python float times numpy's float32 |action|, from a Python
# float: float32 arithmetic under numpy 2's promotion rules (NEP 50), float64 under numpy 1's.
REWARD_DTYPE = (0.0 - np.float32(1.0) * 1.0).dtype


class GroundContacts(Box2D.b2.contactListener):
    """gymnasium's ContactDetector, quicker: the same flags, set at the same moments (walker.game_over
    when a hull contact begins; leg.ground_contact of the lower legs legs[1] and legs[3], set when one
    of their contacts begins and cleared when one ends). The parts are told apart by tags in their
    fixtures' userData instead of comparing Box2D bodies, and PreSolve and PostSolve, which Box2D calls
    for every touching contact at every step, do nothing in Python instead of calling back into C++."""

    def __init__(self, walker: DesignedBipedalWalker):
        super().__init__()
        self.walker = walker
        walker.hull.fixtures[0].userData = HULL_TAG
        for index in (1, 3):
            walker.legs[index].fixtures[0].userData = index

    def BeginContact(self, contact):
        for tag in (contact.fixtureA.userData, contact.fixtureB.userData):
            if tag == HULL_TAG:
                self.walker.game_over = True
            elif tag is not None:
                self.walker.legs[tag].ground_contact = True

    def EndContact(self, contact):
        for tag in (contact.fixtureA.userData, contact.fixtureB.userData):
            if tag is not None and tag != HULL_TAG:
                self.walker.legs[tag].ground_contact = False

    def PreSolve(self, contact, old_manifold):
        """Nothing to record before a contact is solved (defined so that no base-class call is made)."""

    def PostSolve(self, contact, impulse):
        """Nothing to record after a contact is solved (defined so that no base-class call is made)."""


class TerrainLidar:
    """gymnasium's lidar for a group of walkers at once. gymnasium casts each ray with Box2D's
    world.RayCast and a callback that keeps the nearest hit among fixtures of category 1 (the terrain),
    fraction 1 when there is none. Here each ray meets every terrain edge and obstacle polygon near it
    with the arithmetic of Box2D's b2EdgeShape::RayCast and b2PolygonShape::RayCast (float32, the same
    operations in the same order; the terrain is static, so its transform is the identity), vectorized
    over walkers, rays and fixtures, and the nearest hit is kept: the same fractions, bit for bit.

    `targets` holds each walker's `lidar_targets()`. The fixtures near a walker's rays are found by their
    x extent: the fixtures of all walkers are sorted by (walker, left end), walker w's x coordinates
    shifted by w * KEY_SPAN, so one searchsorted finds every walker's window. Windows are padded to the
    widest with a last all-NaN fixture that no ray hits; extra candidates cost only time."""

    KEY_SPAN = 1e4  # walker w's terrain lies in w * KEY_SPAN + [0, 100]; its searches stay within +-KEY_SPAN / 4
    MARGIN = 0.01  # widens the rays' x extent, against rounding

    def __init__(self, targets: list[tuple[np.ndarray, list[np.ndarray]]]):
        edges = np.concatenate([edges for edges, _ in targets])
        v1, v2 = edges[:, 0], edges[:, 1]
        r = v2 - v1
        # b2EdgeShape::RayCast's normal: (r.y, -r.x) normalized by b2Vec2::Normalize (unchanged if shorter
        # than b2_epsilon)
        normal = np.stack([r[:, 1], -r[:, 0]], axis=1)
        length = np.sqrt(normal[:, 0] * normal[:, 0] + normal[:, 1] * normal[:, 1])
        long_enough = length >= np.finfo(np.float32).eps
        normal[long_enough] *= (np.float32(1) / length[long_enough])[:, None]
        rr = r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1]
        table = np.column_stack([v1, normal, r, rr])  # per edge: v1.x, v1.y, n.x, n.y, r.x, r.y, dot(r, r)
        owner = np.repeat(np.arange(len(targets)), [len(e) for e, _ in targets])
        self.edge_keys, order = self._keys(owner, np.minimum(v1[:, 0], v2[:, 0]), np.maximum(v1[:, 0], v2[:, 0]))
        self.edges = self._with_sentinel(table[order]).T.copy()  # [7, edges + 1]

        polygons = [polygon for _, walker_polygons in targets for polygon in walker_polygons]
        width = max((polygon.shape[1] for polygon in polygons), default=1)
        # per polygon and vertex slot: vertex x, y, normal x, y; unused slots zero, which changes no raycast
        table = np.zeros((len(polygons), width, 4), dtype=np.float32)
        for row, (vertices, normals) in zip(table, polygons):
            row[: len(vertices)] = np.concatenate([vertices, normals], axis=1)
        owner = np.repeat(np.arange(len(targets)), [len(p) for _, p in targets])
        x = [vertices[:, 0] for vertices, _ in polygons]
        self.polygon_keys, order = self._keys(owner, np.array([v.min() for v in x]), np.array([v.max() for v in x]))
        self.polygons = self._with_sentinel(table[order]).transpose(2, 1, 0).copy()  # [4, m, polygons + 1]
        self.shift = np.arange(len(targets)) * self.KEY_SPAN

    @classmethod
    def _keys(cls, owner: np.ndarray, low: np.ndarray, high: np.ndarray):
        """Search keys of fixtures owned by walker `owner` spanning x in [low, high]: (sorted left ends,
        the running maximum of right ends in that order), and that order."""
        order = np.lexsort((low, owner))
        shift = owner[order] * cls.KEY_SPAN
        return (low[order] + shift, np.maximum.accumulate(high[order] + shift)), order

    @staticmethod
    def _with_sentinel(table: np.ndarray) -> np.ndarray:
        """The table with an all-NaN last row: every comparison with it fails, so no ray hits it."""
        return np.concatenate([table, np.full((1,) + table.shape[1:], np.nan, dtype=np.float32)])

    def _near(self, keys, low: np.ndarray, high: np.ndarray) -> np.ndarray | None:
        """Rows [W, k] of the fixtures whose x extent may meet [low, high] of each walker (the sentinel
        row where a walker has fewer than W); None when no walker has any."""
        left_ends, reach = keys
        first = np.searchsorted(reach, low + self.shift, "left")
        count = np.searchsorted(left_ends, high + self.shift, "right") - first
        width = count.max(initial=0)
        if width <= 0:
            return None
        slots = np.arange(width)[:, None]
        return np.where(slots < count, first + slots, len(left_ends))

    def scan(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The 10 lidar fractions [k, 10] float32 of walkers whose hulls are at (x, y) [k] (float64
        holding Box2D's float32 positions)."""
        p1x, p1y = x.astype(np.float32), y.astype(np.float32)
        dx = (x[:, None] + LIDAR_REACH_X).astype(np.float32) - p1x[:, None]
        dy = (y[:, None] + LIDAR_REACH_Y).astype(np.float32) - p1y[:, None]
        bound = self.KEY_SPAN / 4
        low = np.minimum(np.maximum(x - self.MARGIN, -bound), bound)
        high = np.minimum(np.maximum(x + (LIDAR_REACH_X.max() + self.MARGIN), -bound), bound)
        fractions = np.ones((len(x), LIDAR_RAYS), dtype=np.float32)
        ray = (p1x[:, None], p1y[:, None], dx, dy)  # [k, 1], [k, 10]: against fixtures [W, k, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            rows = self._near(self.edge_keys, low, high)
            if rows is not None:
                np.minimum(fractions, self._edge_fractions(self.edges[:, rows, None], *ray), out=fractions)
            rows = self._near(self.polygon_keys, low, high)
            if rows is not None:
                np.minimum(fractions, self._polygon_fractions(self.polygons[:, :, rows, None], *ray), out=fractions)
        return fractions

    @staticmethod
    def _edge_fractions(edges, p1x, p1y, dx, dy) -> np.ndarray:
        """b2EdgeShape::RayCast of rays [k, 10] against edges [7, W, k, 1] (the table's columns); -> the
        nearest hit of each ray (1: none)."""
        v1x, v1y, nx, ny, rx, ry, rr = edges
        numerator = nx * (v1x - p1x) + ny * (v1y - p1y)
        t = numerator / (nx * dx + ny * dy)
        s = ((p1x + t * dx - v1x) * rx + (p1y + t * dy - v1y) * ry) / rr
        # a zero denominator or dot(r, r) makes t or s infinite or NaN, which fails these tests as it
        # fails Box2D's
        hit = (t >= 0) & (t <= 1) & (s >= 0) & (s <= 1)
        return np.minimum.reduce(np.where(hit, t, 1), axis=0)

    @staticmethod
    def _polygon_fractions(polygons, p1x, p1y, dx, dy) -> np.ndarray:
        """b2PolygonShape::RayCast of rays [k, 10] against polygons [4, m, W, k, 1] (the table's columns);
        -> the nearest hit of each ray (1: none). Box2D walks the polygon's sides keeping the interval
        [lower, upper] of the ray inside it, and gives up once it is empty; the parts that do not depend
        on that walk are computed for all sides at once. Box2D starts `upper` at the ray's current
        maximum fraction (the nearest hit so far); starting it at 1 changes only hits farther than
        that, which the minimum drops anyway."""
        vx, vy, nx, ny = polygons
        numerator = nx * (vx - p1x) + ny * (vy - p1y)
        denominator = nx * dx + ny * dy  # [m, W, k, 10]
        ratio = numerator / denominator
        gone = np.logical_or.reduce((denominator == 0) & (numerator < 0), axis=0)  # parallel to a side, outside it
        lower = np.zeros(gone.shape, dtype=np.float32)
        upper = np.ones(gone.shape, dtype=np.float32)
        entered = np.zeros(gone.shape, dtype=bool)
        for side in range(len(numerator)):
            num, den = numerator[side], denominator[side]
            enters = (den < 0) & (num < lower * den)
            leaves = (den > 0) & (num < upper * den)
            lower = np.where(enters, ratio[side], lower)
            upper = np.where(leaves, ratio[side], upper)
            entered |= enters
            gone |= upper < lower
        return np.minimum.reduce(np.where(entered & ~gone, lower, 1), axis=0)


class WalkerGroup:
    """Some env copies stepped in this process. An ended episode (terminated, or truncated at max_steps)
    restarts the copy's level at once; the returned observation is then the new episode's.

    A step is gymnasium's BipedalWalker.step for every copy, with the same results: each copy's motors and
    world step (`DesignedBipedalWalker.advance`), then for all copies at once the lidar (`TerrainLidar`),
    the observation and the reward, in gymnasium's arithmetic (the reward's float32 steps included: the
    actions are float32, as WalkerEnv passes them). A restart replays the copy's level in a fresh world
    with the same terrain (it comes from the level), so the lidar's targets are only read at reset."""

    def __init__(self, count: int):
        self.walkers = [DesignedBipedalWalker() for _ in range(count)]
        self.steps = np.zeros(count, dtype=np.int64)
        self.prev_shaping = np.zeros(count)

    def reset(self, params: np.ndarray, course: np.ndarray, seed: np.ndarray, max_steps: int) -> np.ndarray:
        """Put walker i on level (params[i], course[i], seed[i]); -> first observations [k, 24]."""
        self.params, self.course, self.seed, self.max_steps = params, course, seed, max_steps
        self.steps[:] = 0
        obs = np.stack([self._restart(i) for i in range(len(self.walkers))]).astype(np.float32)
        self.lidar = TerrainLidar([walker.lidar_targets() for walker in self.walkers])
        return obs

    def _restart(self, i: int) -> np.ndarray:
        """Start a new episode of copy i on its level; -> its first observation."""
        walker = self.walkers[i]
        obs = walker.play(self.params[i], self.course[i], self.seed[i])
        self.prev_shaping[i] = walker.prev_shaping
        self.steps[i] = 0
        return obs

    def step(self, actions: np.ndarray):
        """-> obs [k, 24] float32, reward [k] float32, terminated, truncated [k] bool, hull [k, 2] (the hull
        position after the step, before any restart)."""
        actions = np.asarray(actions, dtype=np.float32)
        physics = np.array([walker.advance(action) for walker, action in zip(self.walkers, actions.tolist())])
        x, y, angle, angular_velocity, vx, vy = physics[:, :6].T
        # gymnasium's state: Python floats (double precision) in this order and arithmetic, then float32
        fps, scale = gym_walker.FPS, gym_walker.SCALE
        obs = np.empty((len(physics), OBS_DIM))
        obs[:, 0] = angle
        obs[:, 1] = 2.0 * angular_velocity / fps
        obs[:, 2] = 0.3 * vx * (gym_walker.VIEWPORT_W / scale) / fps
        obs[:, 3] = 0.3 * vy * (gym_walker.VIEWPORT_H / scale) / fps
        legs, leg_obs = physics[:, 6:16].reshape(-1, 2, 5), obs[:, 4:14].reshape(-1, 2, 5)
        leg_obs[..., 0] = legs[..., 0]
        leg_obs[..., 1] = legs[..., 1] / gym_walker.SPEED_HIP
        leg_obs[..., 2] = legs[..., 2] + 1.0
        leg_obs[..., 3] = legs[..., 3] / gym_walker.SPEED_KNEE
        leg_obs[..., 4] = legs[..., 4]
        obs[:, 14:] = self.lidar.scan(x, y)
        obs = obs.astype(np.float32)

        # gymnasium's reward: the change of the shaping (double precision), minus a torque cost per joint
        # in numpy's arithmetic for float32 actions (REWARD_DTYPE)
        shaping = 130 * x / scale - 5.0 * np.abs(angle)
        reward = (shaping - self.prev_shaping).astype(REWARD_DTYPE)
        self.prev_shaping = shaping
        torque_cost = REWARD_DTYPE.type(0.00035 * gym_walker.MOTORS_TORQUE) * np.minimum(np.abs(actions), 1).astype(REWARD_DTYPE)
        for joint in range(ACTION_DIM):  # one at a time, in gymnasium's order
            reward -= torque_cost[:, joint]
        reward = reward.astype(np.float32)
        fallen = (physics[:, 16] > 0) | (x < 0)  # the hull touched the ground, or the walker left the course
        reward[fallen] = -100
        terminated = fallen | (x > (TERRAIN_LENGTH - TERRAIN_GRASS) * TERRAIN_STEP)  # reached the end

        self.steps += 1
        truncated = (self.steps >= self.max_steps) & ~terminated
        for i in np.flatnonzero(terminated | truncated):
            obs[i] = self._restart(i)
        return obs, reward, terminated, truncated, physics[:, :2].astype(np.float32)


class StepArrays:
    """The actions and results of a step for all copies, in memory shared with the worker processes
    (an anonymous shared mapping, made before they are forked): each process reads the actions of its
    share and writes its results there, so a step sends no arrays through the pipes."""

    FIELDS = (
        ("actions", np.float32, (ACTION_DIM,)),
        ("obs", np.float32, (OBS_DIM,)),
        ("reward", np.float32, ()),
        ("terminated", np.bool_, ()),
        ("truncated", np.bool_, ()),
        ("hull", np.float32, (2,)),
    )

    def __init__(self, num_envs: int):
        shapes = [(num_envs,) + shape for _, _, shape in self.FIELDS]
        sizes = [int(np.prod(shape)) * np.dtype(dtype).itemsize for (_, dtype, _), shape in zip(self.FIELDS, shapes)]
        self.buffer = mmap.mmap(-1, sum(sizes))
        for (name, dtype, _), shape, offset in zip(self.FIELDS, shapes, np.cumsum([0] + sizes[:-1]).tolist()):
            setattr(self, name, np.ndarray(shape, dtype, self.buffer, offset))

    def store(self, rows: slice, results: tuple) -> None:
        """Write a WalkerGroup.step's results for copies `rows`."""
        for array, value in zip((self.obs, self.reward, self.terminated, self.truncated, self.hull), results):
            array[rows] = value


def _worker_loop(conn, rows: slice, arrays: StepArrays, inherited) -> None:
    """A worker process: runs the WalkerGroup of copies `rows`, answering (method name, args) messages
    until "close", a closed pipe, or the parent's death. "step" takes its actions from `arrays` and
    stores its results there (the answer is None); other methods answer with their result."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle; it closes us
    for other in inherited:
        other.close()
    parent = os.getppid()
    group = WalkerGroup(rows.stop - rows.start)
    while True:
        while not conn.poll(1.0):
            if os.getppid() != parent:
                return
        try:
            command, args = conn.recv()
        except EOFError:
            return
        if command == "close":
            return
        try:
            if command == "step":
                arrays.store(rows, group.step(arrays.actions[rows]))
                conn.send(None)
            else:
                conn.send(getattr(group, command)(*args))
        except Exception as error:  # handed to the parent, which raises it
            conn.send(error)


def _stop_workers(processes, conns) -> None:
    """Ask the workers to finish, then make sure they did (a weakref finalizer: runs once)."""
    for conn in conns:
        with contextlib.suppress(OSError, ValueError):  # a worker that already ended has closed its pipe
            conn.send(("close", ()))
            conn.close()
    for process in processes:
        process.join(timeout=2)
        if process.is_alive():
            process.terminate()
            process.join(timeout=1)


def default_num_workers() -> int:
    """Worker processes of a WalkerEnv: $CLEANUED_WALKER_WORKERS if set, else none (see WalkerEnv)."""
    value = os.environ.get("CLEANUED_WALKER_WORKERS", "")
    if not value:
        return 0
    if not value.isdigit():
        raise ValueError(f"CLEANUED_WALKER_WORKERS must be a whole number >= 0, got {value!r}")
    return int(value)


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
SKY, GROUND, OBSTACLE, TRACE, START = (np.array(c, dtype=np.uint8) for c in ([215, 215, 255], [102, 153, 76], [110, 110, 110], [220, 30, 30], [230, 51, 0]))
WORLD_WIDTH = TERRAIN_LENGTH * TERRAIN_STEP
VERTICAL_EXAGGERATION = 3.0  # heights drawn up to 3x the horizontal scale, so small obstacles show


def _draw_course(walker: DesignedBipedalWalker, trace: np.ndarray | None) -> np.ndarray:
    """One RGB image [96, 256, 3] of the course the walker is on: sky, ground below the terrain line,
    obstacles in grey, the start flag, and an optional hull trace [T, 2] (world x, y) in red. The
    horizontal scale is fixed (the whole course); the vertical one is 3x larger unless the course is
    too high to fit, and the view is centred on the terrain's height range."""
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
        inside = (
            (columns[None, None, :] >= boxes[:, 0, None, None])
            & (columns[None, None, :] <= boxes[:, 2, None, None])
            & (rows[None, :, None] >= boxes[:, 1, None, None])
            & (rows[None, :, None] <= boxes[:, 3, None, None])
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
    """The walker UPOMDP over `num_envs` copies.

    Observation: {"state": float32 [N, 24]}, gymnasium's (hull angle, angular velocity, x/y velocity,
    hip/knee angles and speeds, leg contacts, 10 lidar fractions). Action: [N, 4] in [-1, 1] (clipped:
    the Gaussian sample may leave the box). Reward, termination (hull contact or falling: -100; reaching
    the end of the course) are gymnasium's; at max_steps (2000 in training) the episode is truncated.
    Either way the copy restarts its level at once (same terrain, same initial push). `info` holds
    "hull_position" [N, 2], the hull's (x, y) after the step (before any restart), for drawing runs.

    With num_workers > 0 the copies are split into num_workers + 1 nearly equal shares: this process
    steps the first while each worker process (started at the first reset) steps another; a step sends
    each worker a short message, and the actions and results pass through shared memory (`StepArrays`).
    Default: $CLEANUED_WALKER_WORKERS (scripts build the env through envs.make, which has no such
    argument), else none: every copy in this process. Every split gives identical results. On the
    2-core machine of benchmarks/walker_env.py one worker made the env ~15% faster when nothing else
    ran, but 15-25% slower beside another CPU-bound job (the two processes wait on each other at every
    step, and the kernel tends to let the woken worker preempt the parent), hence the default.
    """

    def __init__(self, num_envs: int = 16, seed: int = 0, num_workers: int | None = None):
        if num_envs < 1:
            raise ValueError(f"the walker env needs at least one copy, got num_envs={num_envs}")
        self.num_envs = num_envs
        self.rng = np.random.default_rng(seed)
        if num_workers is None:
            num_workers = default_num_workers() if num_envs > 1 else 0
        if num_workers < 0:
            raise ValueError(f"num_workers must be >= 0, got {num_workers}")
        self.num_workers = min(num_workers, num_envs - 1)
        self.single_observation_space = gym.spaces.Dict({"state": gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)})
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)
        self.Levels = WalkerLevels
        self.Student = WalkerStudent
        self.Teacher = WalkerTeacher
        self.solved_threshold = 230.0  # solved = return > 230
        self.validation_levels = ("BipedalWalker-v3", "Stairs", "PitGap")
        self.level_metric_names = LEVEL_METRIC_NAMES
        self.training = True  # no training-only reward shaping for the walker; kept for the interface
        # equal shares but for rounding; this process steps the first, one of the smallest
        sizes = [len(share) for share in np.array_split(np.arange(num_envs), self.num_workers + 1)][::-1]
        bounds = np.cumsum([0] + sizes).tolist()
        self.shares = [slice(start, stop) for start, stop in zip(bounds[:-1], bounds[1:])]
        self._conns: list = []
        self._local: WalkerGroup | None = None
        self._arrays: StepArrays | None = None
        self._renderer: DesignedBipedalWalker | None = None
        self._finalizer = None

    @property
    def level_generators(self) -> dict:
        """name -> generator(n, rng) (a property: bound methods stored on the env would form a cycle
        that delays closing the workers of a discarded env)."""
        return {"random": self.random_levels, "easy": self.easy_levels}

    # --- processes -----------------------------------------------------------------------------------
    def _start(self) -> None:
        """Make this process's group of walkers and start the worker processes, on first use."""
        if self._local is not None:
            return
        self._local = WalkerGroup(self.shares[0].stop - self.shares[0].start)
        self._arrays = StepArrays(self.num_envs)
        # fork: the worker starts at once, shares the step arrays and never touches torch (spawn would
        # re-import it).
        context = multiprocessing.get_context("fork")
        processes, parent_ends = [], []
        for rows in self.shares[1:]:
            parent_end, child_end = context.Pipe()
            process = context.Process(target=_worker_loop, args=(child_end, rows, self._arrays, parent_ends + [parent_end]), daemon=True)
            process.start()
            child_end.close()
            processes.append(process)
            parent_ends.append(parent_end)
        self._conns = parent_ends
        self._finalizer = weakref.finalize(self, _stop_workers, processes, parent_ends)

    def _call(self, command: str, share_args: list[tuple]) -> list:
        """Run a WalkerGroup method on every share with its args (share_args[k] for share k), this
        process's share while the workers run theirs; -> the results in share order (None for the
        workers' steps: theirs are in the step arrays). Raises the first error once every share is done."""
        for conn, args in zip(self._conns, share_args[1:]):
            conn.send((command, args))
        try:
            results = [getattr(self._local, command)(*share_args[0])]
        except Exception as error:
            results = [error]
        results += [conn.recv() for conn in self._conns]
        for result in results:
            if isinstance(result, Exception):
                raise result
        return results

    def close(self) -> None:
        """End the worker processes (safe to call twice; also done when the env is garbage-collected
        or the interpreter exits)."""
        if self._finalizer is not None:
            self._finalizer()
        self._conns = []
        self._local = None

    # --- the student env -------------------------------------------------------------------------------
    def reset(self, levels: WalkerLevels, max_steps: int | None = None) -> dict:
        """Copy i now plays levels[i]; -> the first observations."""
        if len(levels) != self.num_envs:
            raise ValueError(f"reset got {len(levels)} levels for {self.num_envs} env copies")
        check_levels(levels)
        max_steps = TRAIN_MAX_STEPS if max_steps is None else int(max_steps)
        if max_steps < 1:
            raise ValueError(f"max_steps must be positive, got {max_steps}")
        self._start()
        params = np.asarray(levels.params, dtype=np.float64)
        course, seed = np.asarray(levels.course), np.asarray(levels.seed)
        obs = self._call("reset", [(params[rows], course[rows], seed[rows], max_steps) for rows in self.shares])
        return {"state": np.concatenate(obs)}

    def step(self, actions: np.ndarray):
        """Step every copy with actions [N, 4] (clipped to [-1, 1]); -> obs, reward, terminated,
        truncated, info (see the class docstring)."""
        if self._local is None:
            raise RuntimeError("WalkerEnv.step called before reset")
        arrays = self._arrays
        np.clip(np.asarray(actions, dtype=np.float32).reshape(self.num_envs, ACTION_DIM), -1.0, 1.0, out=arrays.actions)
        mine = self.shares[0]
        arrays.store(mine, self._call("step", [(arrays.actions[mine],)] + [()] * self.num_workers)[0])
        return ({"state": arrays.obs.copy()}, arrays.reward.copy(), arrays.terminated.copy(), arrays.truncated.copy(),
                {"hull_position": arrays.hull.copy()})

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

    def test_levels(self) -> HeldOutCourses:
        """The held-out courses, each a fresh terrain seed per generated level."""
        return HeldOutCourses(
            {name: HeldOutLevel(_course_generator(params, course), max_steps) for name, (params, course, max_steps) in HELD_OUT_COURSES.items()}
        )

    level_metrics = staticmethod(level_metrics)

    def render(self, levels: WalkerLevels) -> np.ndarray:
        """Terrain profiles, uint8 RGB [B, 96, 256, 3] (the whole 200-step course of each level)."""
        return np.stack([self.render_run(levels[i], None) for i in range(len(levels))])

    def render_run(self, level: WalkerLevels, hull_positions: np.ndarray | None) -> np.ndarray:
        """One level's profile [96, 256, 3] with a walker's run drawn over it: hull_positions [T, 2] is
        the (x, y) trace, e.g. the "hull_position" entries of step's info."""
        check_levels(level)
        if self._renderer is None:
            self._renderer = DesignedBipedalWalker()
        self._renderer.play(level.params[0], level.course[0], level.seed[0])
        trace = None if hull_positions is None else np.asarray(hull_positions, dtype=np.float64).reshape(-1, 2)
        return _draw_course(self._renderer, trace)


def _course_params(**values) -> np.ndarray:
    """A parameter vector: roughness 0, every obstacle off, stair_steps 1, except the given values."""
    params = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
    for name, value in values.items():
        params[PARAM_NAMES.index(name)] = value
    return params


# name -> (params, course kind, max_steps). The gymnasium courses' params only describe them (for the
# metrics): gymnasium's grass has roughness 1; its hardcore pits are 3-4 steps (gap 2-3), stumps 1-2
# steps high, stairs 1 step high with 3-4 steps. Custom test courses as the reference's test envs.
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


class HeldOutCourses(dict):
    """name -> HeldOutLevel; looking up an unknown course name raises ValueError (one clear line)."""

    def __missing__(self, name):
        raise ValueError(f"unknown walker course {name!r}: expected one of {', '.join(self)}")


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
