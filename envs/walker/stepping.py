"""Stepping the walker: gymnasium's BipedalWalker on a designed course, many copies at once.

The walker, its motors, lidar, 24-d observation, 4-d action and reward are gymnasium's own
(`gymnasium.envs.box2d.bipedal_walker.BipedalWalker`); `DesignedBipedalWalker` subclasses it and
replaces only the terrain generator (envs/walker/terrain.py builds the course of a CUSTOM level).
Everything random in an episode (terrain, clouds, the initial push of the hull) is drawn from the
level's terrain seed (gymnasium's `reset(seed=...)`) and every episode starts in a fresh Box2D world,
so a level replays identically at every restart.

Stepping is gymnasium's step with the same results, made cheaper (`WalkerGroup`): per copy only the
motors and the Box2D world step run in Python; the lidar (`TerrainLidar`: Box2D's raycast arithmetic,
vectorized), the observation and the reward are computed for all copies at once.
"""

from __future__ import annotations

import math

import Box2D
import numpy as np
from gymnasium.envs.box2d import bipedal_walker as gym_walker

from envs.walker.terrain import CUSTOM, EASY_PARAMS, GYM_HARDCORE, TERRAIN_GRASS, TERRAIN_LENGTH, TERRAIN_STEP, Feature, build_designed_terrain

OBS_DIM, ACTION_DIM = 24, 4


# ---------------------------------------------------------------------------------------------------
# gymnasium's walker with a designed terrain: _generate_terrain is replaced, parts of step added.
# ---------------------------------------------------------------------------------------------------
class DesignedBipedalWalker(gym_walker.BipedalWalker):
    """gymnasium's BipedalWalker whose terrain comes from a level: `play(params, course, seed)` resets
    it onto that level. CUSTOM courses use POET's generator (`build_designed_terrain`) (recording the obstacles it placed in
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
        if self.course == CUSTOM:
            self.features = build_designed_terrain(self, self.params, self.np_random)
        else:
            self.features = []
            super()._generate_terrain(self.course == GYM_HARDCORE)

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

