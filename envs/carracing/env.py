"""The CarRacing UPOMDP: gymnasium's car on tracks a teacher sketches.

Everything an algorithm script needs: the level batch, the student env (one Box2D world per copy, the
physics stepped in a loop over copies, the views rendered for all copies at once by
envs/carracing/render.py), the teacher's MDP, the level generators (DR's and PLR's), mutation, level
metrics, level images, the held-out tracks (F1 file, vanilla, built-ins; geometry in
envs/carracing/tracks.py) and the paper's networks.

Student observation: {"image": uint8 [N, 12, 96, 96]}, channels first: four RGB frames stacked oldest
first (channels 3k..3k+2 are frame k, frame 3 the newest); an episode's first observation repeats its
first frame four times (as the reference's frame stack). Action: Box(0, 1, (3,)), the Beta sample,
mapped to steer = 2 a0 - 1, gas = a1, brake = a2, held for 8 physics frames (action repeat 8).

    python -m envs.carracing.tracks convert formula1.py out.npz   # the reference's track file to our format
"""

from __future__ import annotations

import dataclasses
import math
import os

import Box2D
import gymnasium as gym
import numpy as np
import torch
from Box2D.b2 import contactListener
from gymnasium.envs.box2d.car_dynamics import Car
from torch import nn
from torch.distributions import Beta, Categorical, Independent

from envs.carracing.render import STATE_SIZE, ViewRenderer, class_map, draw_trajectory, level_image, track_quads
from envs.carracing.tracks import (
    BUILTIN_FRAME_LIMITS,
    BUILTIN_TRACKS,
    FPS,
    NUM_CONTROL_POINTS,
    SKETCH_SIZE,
    TRACK_WIDTH,
    VANILLA_FRAME_LIMIT,
    Track,
    load_f1_tracks,
    random_control_points,
    track_from_cells,
    track_from_centreline,
    track_from_control_points,
    track_from_unordered_points,
    track_metrics,
    vanilla_track,
)
from envs.levels import HeldOutLevel, HeldOutLevels, LevelBatch
from envs.nets import FeedForwardActorCritic, layer_init

ACTION_REPEAT = 8
FRAME_STACK = 4
TRAIN_MAX_STEPS = 1000 // ACTION_REPEAT  # 1000 frames = 125 agent steps
NUM_CELLS = SKETCH_SIZE * SKETCH_SIZE
NOISE_DIM = 4
DT = 1.0 / FPS
VELOCITY_ITERATIONS, POSITION_ITERATIONS = 6 * 30, 2 * 30  # gymnasium's world.Step arguments
FRAME_PENALTY = 0.1
OUTSIDE_REWARD = -100.0
# Training-only shaping (the reference implementation's CarRacingWrapper.step).
DONE_BONUS = 100.0
GRASS_PENALTY = 0.05
GRASS_GREEN_MEAN = 185.0  # "on grass": the frame's mean green channel exceeds this
EARLY_STOP_WINDOW = 100
EARLY_STOP_MEAN = -0.1
F1_ENV_VAR = "CLEANUED_F1_TRACKS"
# The paper's 20 held-out Formula-1 circuits (and LagunaSeca), from the reference implementation: their
# licence (CC BY-NC 4.0) is in envs/carracing/data/LICENSE.md.
SHIPPED_F1_TRACKS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "f1_tracks.npz")
NO_F1_TRACKS = "none"  # as the track file: evaluate on vanilla and the built-in tracks only (quick runs)

# Level.track values: -1 = built from the cells; -2 = built from the continuous control points (DR's
# tracks); then a registry of fixed tracks whose indices never move: vanilla (the level's seed draws
# the track), the built-ins, then the F1 file's tracks by name.
DESIGNED = -1
CONTINUOUS = -2
VANILLA = 0
BUILTIN_NAMES = tuple(BUILTIN_TRACKS)
FIRST_F1 = 1 + len(BUILTIN_NAMES)
EXCLUDED_F1 = ("LagunaSeca",)  # in the reference's file, not in the paper's benchmark


@dataclasses.dataclass
class CarRacingLevels(LevelBatch):
    """A batch of tracks: cells int64 [B, 12] (the sketch cells of a designed track, any order),
    points float64 [B, 12, 2] (the world control points of a continuous track, any order), track
    int64 [B] (-1: designed from the cells; -2: continuous, from the points; >= 0: a fixed track of
    the registry above) and seed int64 [B] (vanilla's track seed). Unused fields are zeros."""

    cells: np.ndarray
    points: np.ndarray
    track: np.ndarray
    seed: np.ndarray


def _levels(track: np.ndarray, cells=None, points=None, seeds=None) -> CarRacingLevels:
    """A level batch of the given track kinds, the fields not given zeros."""
    n = len(track)
    return CarRacingLevels(
        np.zeros((n, NUM_CONTROL_POINTS), np.int64) if cells is None else np.asarray(cells, dtype=np.int64),
        np.zeros((n, NUM_CONTROL_POINTS, 2)) if points is None else np.asarray(points, dtype=np.float64),
        np.asarray(track, dtype=np.int64),
        np.zeros(n, np.int64) if seeds is None else np.asarray(seeds, dtype=np.int64),
    )


def designed_levels(cells: np.ndarray) -> CarRacingLevels:
    """Levels of designed tracks from sketch cells [B, 12]."""
    return _levels(np.full(len(cells), DESIGNED), cells=cells)


def continuous_levels(points: np.ndarray) -> CarRacingLevels:
    """Levels of tracks through continuous world control points [B, 12, 2]."""
    return _levels(np.full(len(points), CONTINUOUS), points=points)


def fixed_levels(track: int, seeds: np.ndarray) -> CarRacingLevels:
    """Levels of one registry track, one per seed (the seed only matters for vanilla)."""
    return _levels(np.full(len(seeds), track), seeds=seeds)


_NOTICE_SHOWN = False


def _f1_tracks_from_environment() -> dict | None:
    """The F1 tracks of the file named by CLEANUED_F1_TRACKS (default: the 20 circuits shipped with
    cleanued, SHIPPED_F1_TRACKS); None for "none" (quick runs: vanilla and the built-in tracks), or if
    the shipped file is missing (with a one-time notice)."""
    global _NOTICE_SHOWN
    path = os.environ.get(F1_ENV_VAR) or SHIPPED_F1_TRACKS
    if path == NO_F1_TRACKS:
        return None
    if path != SHIPPED_F1_TRACKS or os.path.isfile(path):
        return load_f1_tracks(path)
    if not _NOTICE_SHOWN:
        print(f"note: no F1 track file ({path} is missing): held-out CarRacing tracks are vanilla, {', '.join(BUILTIN_NAMES)}")
        _NOTICE_SHOWN = True
    return None


def held_out_levels(f1_tracks: dict | None) -> HeldOutLevels:
    """Held out: vanilla (a fresh gymnasium track per episode) plus the 20 F1 tracks of `f1_tracks`
    (name -> (centreline, frame limit), as `load_f1_tracks` gives them; max_steps = the track's frame
    limit / 8, rounded up), or, without F1 tracks, the built-in Hairpins, Chicanes and LongStraights."""

    def vanilla(n, rng):
        """n gymnasium tracks, their seeds drawn from rng."""
        return fixed_levels(VANILLA, rng.integers(0, 2**31 - 1, n))

    def fixed(track):
        """The generator of one fixed track."""
        return lambda n, rng: fixed_levels(track, np.zeros(n, np.int64))

    held_out = HeldOutLevels(vanilla=HeldOutLevel(vanilla, VANILLA_FRAME_LIMIT // ACTION_REPEAT))
    if f1_tracks:
        for k, name in enumerate(sorted(f1_tracks)):  # track kinds FIRST_F1 + k, as CarRacingEnv.f1_names
            if name not in EXCLUDED_F1:
                held_out[name] = HeldOutLevel(fixed(FIRST_F1 + k), math.ceil(f1_tracks[name][1] / ACTION_REPEAT))
    else:
        for k, name in enumerate(BUILTIN_NAMES):
            held_out[name] = HeldOutLevel(fixed(1 + k), math.ceil(BUILTIN_FRAME_LIMITS[name] / ACTION_REPEAT))
    return held_out


# ---------------------------------------------------------------------------------------------------
# The teacher's MDP: 12 steps, each one cell of the 10x10 sketch.
# ---------------------------------------------------------------------------------------------------
class CarRacingTeacherMDP:
    """PAIRED's adversary for CarRacing over n tracks at once. Action a in [0, 100) is sketch cell
    (i, j) = (a % 10, a // 10), stored at sketch[j, i], so the flattened sketch is indexed by a (the
    same convention as envs.carracing.tracks.cell_points). A used cell may not be chosen again (the
    Teacher network masks them): choosing one raises ValueError. Observation: sketch float32
    [n, 10, 10] (1 where a point was placed), time int64 [n] (0..12) and noise float32 [n, 4] U[0, 1)
    drawn afresh from env.rng at every step."""

    num_steps = NUM_CONTROL_POINTS
    action_space = gym.spaces.Discrete(NUM_CELLS)
    observation_space = gym.spaces.Dict(
        {
            "sketch": gym.spaces.Box(0, 1, (SKETCH_SIZE, SKETCH_SIZE), np.float32),
            "time": gym.spaces.Discrete(NUM_CONTROL_POINTS + 1),
            "noise": gym.spaces.Box(0, 1, (NOISE_DIM,), np.float32),
        }
    )

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def reset(self, n: int) -> dict:
        """Start n empty sketches; returns the first observation."""
        self.n = n
        self.t = 0
        self.cells = np.zeros((n, NUM_CONTROL_POINTS), dtype=np.int64)
        self.sketch = np.zeros((n, NUM_CELLS), dtype=np.float32)
        return self._observation()

    def step(self, actions) -> tuple[dict, bool]:
        """Place one cell per teacher; returns (observation, done), done after the 12th cell."""
        a = np.asarray(actions, dtype=np.int64).reshape(self.n)
        if self.t >= self.num_steps:
            raise ValueError("the teacher's episode is over: call reset")
        if np.any((a < 0) | (a >= NUM_CELLS)):
            raise ValueError(f"teacher actions must be cells in [0, {NUM_CELLS})")
        if np.any(self.sketch[np.arange(self.n), a] > 0):
            raise ValueError("a teacher chose a sketch cell it had already used")
        self.cells[:, self.t] = a
        self.sketch[np.arange(self.n), a] = 1.0
        self.t += 1
        return self._observation(), self.t >= self.num_steps

    def levels(self) -> CarRacingLevels:
        """The designed tracks (cells in the order the teachers placed them)."""
        return designed_levels(self.cells.copy())

    def _observation(self) -> dict:
        return {
            "sketch": self.sketch.reshape(self.n, SKETCH_SIZE, SKETCH_SIZE).copy(),
            "time": np.full(self.n, self.t, dtype=np.int64),
            "noise": self.rng.random((self.n, NOISE_DIM), dtype=np.float32),
        }


# ---------------------------------------------------------------------------------------------------
# Box2D plumbing: road tiles as sensor fixtures, a contact listener per world (gymnasium's rules).
# ---------------------------------------------------------------------------------------------------
class RoadTile:
    """What a wheel's `tiles` set holds (gymnasium's Car.step reads `road_friction`)."""

    __slots__ = ("index", "road_friction")

    def __init__(self, index: int):
        self.index = index
        self.road_friction = 1.0


_ROAD_TILES: list[RoadTile] = []


def road_tiles(count: int) -> list[RoadTile]:
    """Shared, stateless tile objects 0..count-1 (visits are recorded in the env's arrays)."""
    while len(_ROAD_TILES) < count:
        _ROAD_TILES.append(RoadTile(len(_ROAD_TILES)))
    return _ROAD_TILES[:count]


class TileContacts(contactListener):
    """Gymnasium's FrictionDetector for one copy: a wheel touching a tile adds it to the wheel's set
    (road friction); the first touch of a tile records the visit and its reward, 1000 / N."""

    def __init__(self, env: CarRacingEnv, copy: int):
        contactListener.__init__(self)
        self.env = env
        self.copy = copy

    def BeginContact(self, contact):
        self._contact(contact, True)

    def EndContact(self, contact):
        self._contact(contact, False)

    def _contact(self, contact, begin: bool) -> None:
        tile, wheel = contact.fixtureA.userData, contact.fixtureB.body.userData
        if not isinstance(tile, RoadTile):
            tile, wheel = contact.fixtureB.userData, contact.fixtureA.body.userData
        if not isinstance(tile, RoadTile) or wheel is None or not hasattr(wheel, "tiles"):
            return
        if not begin:
            wheel.tiles.discard(tile)
            return
        wheel.tiles.add(tile)
        visited = self.env.visited[self.copy]
        if not visited[tile.index]:
            visited[tile.index] = True
            self.env.tile_gain[self.copy] += self.env.reward_per_tile[self.copy]
            self.env.visited_count[self.copy] += 1


def build_world(env: CarRacingEnv, copy: int, track: Track) -> Box2D.b2World:
    """A Box2D world holding the track's tiles: one static body, one sensor quad per tile, colliding
    with wheels only (category 1, mask 0x20; gymnasium's hull contacts with tiles are ignored anyway).
    One fixture definition is reused with new vertices per tile (as gymnasium does): several times
    faster than building a definition per tile."""
    world = Box2D.b2World((0, 0), contactListener=TileContacts(env, copy))
    road = world.CreateStaticBody()
    definition = Box2D.b2FixtureDef(shape=Box2D.b2PolygonShape(box=(1, 1)), isSensor=True)
    definition.filter.categoryBits = 0x0001
    definition.filter.maskBits = 0x0020
    shape = definition.shape
    for quad, tile in zip(track_quads(track, -TRACK_WIDTH, TRACK_WIDTH).tolist(), road_tiles(len(track))):
        shape.vertices = quad
        road.CreateFixture(definition).userData = tile
    return world


# ---------------------------------------------------------------------------------------------------
# The student env.
# ---------------------------------------------------------------------------------------------------
class CarRacingEnv:
    """The CarRacing UPOMDP over `num_envs` copies. See the module docstring for the observation and
    action. Reward per frame: +1000/N per newly visited tile, -0.1; leaving the playfield: -100 (that
    frame's whole reward) and terminated; all tiles visited: terminated; max_steps agent steps:
    truncated. With `training` True the reference's shaping is added per frame: +100 on the frame an
    episode ends by itself (lap, playfield, time limit), -0.05 on grass, and termination once the mean
    of the last 100 frame rewards (shaped, zeros before the episode's first frame) is <= -0.1. "On
    grass" is the reference's test on the view rendered after each physics frame: the mean of its
    green channel over the whole 96x96 frame (indicator bar and car included) exceeds 185."""

    def __init__(self, num_envs: int = 16, seed: int = 0):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.num_envs = num_envs
        self.rng = np.random.default_rng(seed)
        self.single_observation_space = gym.spaces.Dict({"image": gym.spaces.Box(0, 255, (3 * FRAME_STACK, STATE_SIZE, STATE_SIZE), np.uint8)})
        self.single_action_space = gym.spaces.Box(0.0, 1.0, (3,), np.float32)
        self.Levels = CarRacingLevels
        self.Student = CarRacingStudent
        self.Teacher = CarRacingTeacher
        self.solved_threshold = 900.0  # gymnasium's "solved" score
        self.level_metric_names = ("track_length", "total_curvature", "sharp_turns")
        self.level_generators = {"random": self.random_levels, "sketch": self.random_sketch_levels}
        self.training = True
        self.f1_tracks = _f1_tracks_from_environment()
        self.f1_names = tuple(sorted(self.f1_tracks)) if self.f1_tracks else ()
        if self.f1_tracks:  # the paper's validation tracks, or the file's first three if it lacks them
            paper = tuple(name for name in ("Italy", "Singapore", "Germany") if name in self.f1_tracks)
            others = tuple(name for name in self.f1_names if name not in EXCLUDED_F1)
            self.validation_levels = ("vanilla",) + (paper or others[:3])
        else:
            self.validation_levels = ("vanilla", "Hairpins", "Chicanes")
        self._fixed_track_cache: dict[int, Track] = {}
        self.renderer = ViewRenderer()
        self.keys: list = [None] * num_envs
        self.tracks: list = [None] * num_envs
        self.maps: list = [None] * num_envs
        self.worlds: list = [None] * num_envs
        self.cars: list = [None] * num_envs

    def close(self) -> None:
        """Drop the Box2D worlds (everything runs in this process). Safe to call twice."""
        for i in range(self.num_envs):
            if self.cars[i] is not None:
                self.cars[i].destroy()
        self.cars = [None] * self.num_envs
        self.worlds = [None] * self.num_envs

    # --- tracks of levels ------------------------------------------------------------------------
    def track_of(self, levels: CarRacingLevels, i: int) -> Track:
        """The Track of level i of a batch."""
        kind = int(levels.track[i])
        if kind == DESIGNED:
            return track_from_cells(levels.cells[i])
        if kind == CONTINUOUS:
            return track_from_unordered_points(levels.points[i])
        if kind == VANILLA:
            return vanilla_track(np.random.default_rng(int(levels.seed[i])))
        if kind not in self._fixed_track_cache:
            if 1 <= kind < FIRST_F1:
                track = track_from_control_points(BUILTIN_TRACKS[BUILTIN_NAMES[kind - 1]])
            elif FIRST_F1 <= kind < FIRST_F1 + len(self.f1_names):
                track = track_from_centreline(self.f1_tracks[self.f1_names[kind - FIRST_F1]][0])
            else:
                raise ValueError(f"level track index {kind} is not a known track (F1 tracks need {F1_ENV_VAR})")
            self._fixed_track_cache[kind] = track
        return self._fixed_track_cache[kind]

    @staticmethod
    def level_key(levels: CarRacingLevels, i: int) -> tuple:
        """What identifies a level's track (for reusing worlds and class maps across resets)."""
        kind = int(levels.track[i])
        if kind == DESIGNED:
            return (kind,) + tuple(sorted(levels.cells[i].tolist()))
        if kind == CONTINUOUS:
            return (kind,) + tuple(levels.points[i].reshape(-1).tolist())
        return (kind, int(levels.seed[i])) if kind == VANILLA else (kind,)

    # --- level generators, teacher, held-out set, mutation, metrics, rendering -------------------
    def teacher(self) -> CarRacingTeacherMDP:
        """PAIRED's adversary MDP, its noise drawn from env.rng."""
        return CarRacingTeacherMDP(self.rng)

    def random_levels(self, n: int, rng: np.random.Generator) -> CarRacingLevels:
        """The DR generator, the reference implementation's (dcd) random track (CarRacingBezier.reset
        without control points): 12 continuous control points uniform in [0, 333.3)^2, redrawn while
        crowded (envs.carracing.tracks.random_control_points), through which the Bezier loop runs."""
        return continuous_levels(random_control_points(n, rng))

    def random_sketch_levels(self, n: int, rng: np.random.Generator) -> CarRacingLevels:
        """PLR's (and Robust PLR's) new levels, as the reference implementation (dcd) makes them for PLR:
        a uniformly random teacher (the adversary's act_random) picks each of the 12 sketch cells
        uniformly from the 100, with replacement: a cell may repeat (one control point placed twice)."""
        return designed_levels(rng.integers(0, NUM_CELLS, (n, NUM_CONTROL_POINTS)))

    def optimal_returns(self, levels: CarRacingLevels) -> None:
        """None: this env has no solver for a level's best return (the maze has one)."""
        return None

    def draw_starts(self, levels: CarRacingLevels) -> CarRacingLevels:
        """The levels unchanged: their start has no random part (the maze draws a start direction)."""
        return levels

    def mutate(self, levels: CarRacingLevels, rng: np.random.Generator, num_edits: int = 3) -> CarRacingLevels:
        """Edited copies: `num_edits` times, one random control point of each designed track moves to a
        random one of its up to 8 neighbouring cells that is on the grid and not in use (it stays if
        none is), so no cell newly repeats. Continuous (DR) and fixed tracks are returned unchanged."""
        child = levels.copy()
        n = len(child)
        steps = np.array([(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)])
        index = np.arange(n)
        designed = child.track == DESIGNED
        for _ in range(num_edits):
            which = rng.integers(0, NUM_CONTROL_POINTS, n)
            cell = child.cells[index, which]
            i, j = cell[:, None] % SKETCH_SIZE + steps[None, :, 0], cell[:, None] // SKETCH_SIZE + steps[None, :, 1]
            on_grid = (i >= 0) & (i < SKETCH_SIZE) & (j >= 0) & (j < SKETCH_SIZE)
            target = np.where(on_grid, j * SKETCH_SIZE + i, -1)
            free = on_grid & ~np.any(target[:, :, None] == child.cells[:, None, :], axis=2)
            score = np.where(free, rng.random(free.shape), -1.0)
            choice = score.argmax(axis=1)
            move = designed & free[index, choice]
            child.cells[index[move], which[move]] = target[index[move], choice[move]]
        return child

    def test_levels(self) -> HeldOutLevels:
        """The held-out tracks (`held_out_levels`) with this env's F1 tracks: the 20 shipped with
        cleanued, or the file named by CLEANUED_F1_TRACKS, or none ("none", or the file missing)."""
        return held_out_levels(self.f1_tracks)

    def level_metrics(self, levels: CarRacingLevels) -> dict[str, np.ndarray]:
        """Track length (world units), total curvature (sum of absolute turning angles, radians) and
        the number of sharp turns (stretches with kerbs), per level."""
        values = np.array([track_metrics(self.track_of(levels, i)) for i in range(len(levels))], dtype=np.float64).reshape(-1, 3)
        return dict(zip(self.level_metric_names, values.T))

    def render(self, levels: CarRacingLevels) -> np.ndarray:
        """Top-down images [B, 128, 128, 3] of the whole playfield of each level (start in red)."""
        return np.stack([level_image(self.track_of(levels, i)) for i in range(len(levels))])

    def render_trajectory(self, level: CarRacingLevels, positions: np.ndarray) -> np.ndarray:
        """One level's top-down image [128, 128, 3] (level: a batch of one) with a driven path drawn
        in blue: positions [T, 2] in world units, e.g. agent_positions() collected over an episode."""
        track = self.track_of(level, 0)
        return draw_trajectory(level_image(track), positions, track.playfield)

    def agent_positions(self) -> np.ndarray:
        """The car's hull position (x, y) of every copy [N, 2], in world units."""
        return np.array([tuple(car.hull.position) for car in self.cars])

    # --- the vectorized student env ------------------------------------------------------------
    def reset(self, levels: CarRacingLevels, max_steps: int | None = None) -> dict:
        """Copy i now plays levels[i] from its start; returns the first observations. Worlds and class
        maps of copies whose track is unchanged are kept."""
        if len(levels) != self.num_envs:
            raise ValueError(f"reset got {len(levels)} levels for {self.num_envs} env copies")
        self.max_steps = TRAIN_MAX_STEPS if max_steps is None else int(max_steps)
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        keys = [self.level_key(levels, i) for i in range(self.num_envs)]
        known = {key: (self.tracks[i], self.maps[i]) for i, key in enumerate(self.keys) if key is not None}
        n = self.num_envs
        self.tile_gain = np.zeros(n)
        self.visited_count = np.zeros(n, dtype=np.int64)
        for i, key in enumerate(keys):
            if key != self.keys[i] or self.worlds[i] is None:
                if key not in known:
                    track = self.track_of(levels, i)
                    known[key] = (track, class_map(track))
                self.tracks[i], self.maps[i] = known[key]
                if self.cars[i] is not None:
                    self.cars[i].destroy()
                    self.cars[i] = None
                self.worlds[i] = build_world(self, i, self.tracks[i])
        self.keys = keys
        self.tile_count = np.array([len(t) for t in self.tracks], dtype=np.int64)
        self.reward_per_tile = 1000.0 / self.tile_count
        self.playfield = np.array([t.playfield for t in self.tracks])
        self.visited = [np.zeros(len(t), dtype=bool) for t in self.tracks]
        self.renderer.set_maps(self.maps, self.playfield)
        self.steps = np.zeros(n, dtype=np.int64)
        self.history = np.zeros((n, EARLY_STOP_WINDOW))
        self.history_pos = np.zeros(n, dtype=np.int64)
        self.frames = np.zeros((n, 3 * FRAME_STACK, STATE_SIZE, STATE_SIZE), dtype=np.uint8)
        self.classes = np.zeros((n, STATE_SIZE, STATE_SIZE), dtype=np.uint8)  # each copy's latest view
        everyone = np.ones(n, dtype=bool)
        self._restart(everyone)
        self._observe(everyone, everyone)
        return {"image": self.frames.copy()}

    def step(self, actions: np.ndarray):
        """Hold each copy's action for 8 physics frames (a copy whose episode ends stops there), then
        render. Returns obs, reward float32 [N], terminated, truncated, {}; ended episodes restart
        their level at once and the returned observation is the new episode's first."""
        a = np.clip(np.asarray(actions, dtype=np.float64).reshape(self.num_envs, 3), 0.0, 1.0)
        steer, gas, brake = 2.0 * a[:, 0] - 1.0, a[:, 1], a[:, 2]
        n = self.num_envs
        reward = np.zeros(n)
        terminated = np.zeros(n, dtype=bool)
        running = np.ones(n, dtype=bool)
        x, y = np.zeros(n), np.zeros(n)
        for frame in range(ACTION_REPEAT):
            active = np.nonzero(running)[0]
            if len(active) == 0:
                break
            for i in active.tolist():
                car = self.cars[i]
                car.steer(-steer[i])  # gymnasium: car.steer(-action[0])
                car.gas(gas[i])
                car.brake(brake[i])
                car.step(DT)
                self.worlds[i].Step(DT, VELOCITY_ITERATIONS, POSITION_ITERATIONS)
                x[i], y[i] = car.hull.position
            frame_reward = self.tile_gain[active] - FRAME_PENALTY
            self.tile_gain[active] = 0.0
            outside = (np.abs(x[active]) > self.playfield[active]) | (np.abs(y[active]) > self.playfield[active])
            lap = self.visited_count[active] == self.tile_count[active]
            frame_reward = np.where(outside, OUTSIDE_REWARD, frame_reward)
            ended = outside | lap
            if self.training:
                frame_reward += DONE_BONUS * ended
                # The reference renders the view after every physics frame and tests it for grass. The
                # last frame's view is the observation, so it is rendered whole; the others' green
                # means come cheaper, without their images.
                car = self._car_states(active)
                if frame == ACTION_REPEAT - 1:
                    self.classes[active] = self.renderer.classes(car, active)
                    green_means = self.renderer.green_means(self.classes[active])
                else:
                    green_means = self.renderer.green_means_of_views(car, active)
                on_grass = green_means > GRASS_GREEN_MEAN
                frame_reward -= GRASS_PENALTY * on_grass
                slot = self.history_pos[active]
                self.history[active, slot] = frame_reward
                self.history_pos[active] = (slot + 1) % EARLY_STOP_WINDOW
                # The reference stops at mean <= -0.1; the tolerance keeps float rounding of 100
                # frames of exactly -0.1 from deciding it.
                ended |= self.history[active].mean(axis=1) <= EARLY_STOP_MEAN + 1e-9
            reward[active] += frame_reward
            terminated[active] = ended
            running[active] = ~ended
        self.steps += 1
        truncated = (self.steps >= self.max_steps) & ~terminated
        if self.training:
            reward += DONE_BONUS * truncated  # the reference's time limit ends the episode as a done
        done = terminated | truncated
        if done.any():
            self._restart(done)
        # Training rendered every copy's last frame already: only restarted copies need a new view.
        self._observe(done if self.training else np.ones(n, dtype=bool), done)
        return {"image": self.frames.copy()}, reward.astype(np.float32), terminated, truncated, {}

    def _restart(self, which: np.ndarray) -> None:
        """Start the episodes of the chosen copies: fresh car on the start point, no tile visited, and
        the one action-free physics frame gymnasium's reset runs (its tile rewards count in the first
        step's reward, as in gymnasium)."""
        for i in np.nonzero(which)[0].tolist():
            if self.cars[i] is not None:
                self.cars[i].destroy()
            self.visited[i][:] = False
            self.visited_count[i] = 0
            self.tile_gain[i] = 0.0
            track = self.tracks[i]
            self.cars[i] = Car(self.worlds[i], float(track.beta[0]), float(track.xy[0, 0]), float(track.xy[0, 1]))
            self.cars[i].step(DT)
            self.worlds[i].Step(DT, VELOCITY_ITERATIONS, POSITION_ITERATIONS)
        self.steps[which] = 0
        self.history[which] = 0.0
        self.history_pos[which] = 0

    def _car_states(self, copies: np.ndarray | None = None) -> dict:
        """The car quantities the view shows, one row per copy of `copies` (indices; all copies by
        default), wheel poses in the hull's frame."""
        copies = np.arange(self.num_envs) if copies is None else copies
        # One row per copy (numbers gathered in a list, one array made at the end): x, y, angle, speed,
        # angular velocity, steering, velocity (2), then per wheel x, y, angle, phase, omega.
        rows = []
        for i in copies.tolist():
            car = self.cars[i]
            hull = car.hull
            hx, hy = hull.position
            angle = hull.angle
            cos, sin = math.cos(angle), math.sin(angle)
            vx, vy = hull.linearVelocity
            row = [hx, hy, angle, math.hypot(vx, vy), hull.angularVelocity, car.wheels[0].joint.angle, vx, vy]
            for wheel in car.wheels:
                wx, wy = wheel.position
                dx, dy = wx - hx, wy - hy
                row += (cos * dx + sin * dy, -sin * dx + cos * dy, wheel.angle - angle, wheel.phase, wheel.omega)
            rows.append(row)
        values = np.array(rows, dtype=np.float64).reshape(len(copies), 8 + 4 * 5)
        wheels = values[:, 8:].reshape(len(copies), 4, 5)
        state = dict(zip(("x", "y", "angle", "speed", "angular_velocity", "steering"), values[:, :6].T))
        state.update(velocity=values[:, 6:8], wheel_xy=wheels[:, :, :2], wheel_angle=wheels[:, :, 2])
        state.update(wheel_phase=wheels[:, :, 3], wheel_omega=wheels[:, :, 4])
        return state

    def _observe(self, stale: np.ndarray, fresh: np.ndarray) -> None:
        """Render the views of the `stale` copies (the others' latest views are current) and push every
        copy's view on its frame stack; copies starting an episode (`fresh`) get their first frame in
        all four slots."""
        copies = np.nonzero(stale)[0]
        if len(copies):
            self.classes[copies] = self.renderer.classes(self._car_states(copies), copies)
        view = self.renderer.colours(self.classes)
        self.frames[:, :-3] = self.frames[:, 3:]
        self.frames[:, -3:] = view
        if fresh.any():
            self.frames[fresh] = np.tile(view[fresh], (1, FRAME_STACK, 1, 1))


# ---------------------------------------------------------------------------------------------------
# Networks, with the calling convention of envs/nets.py.
# ---------------------------------------------------------------------------------------------------
class BetaPolicy(Independent):
    """The student's policy: independent Betas over the action dims (build it as BetaPolicy(Beta(alpha,
    beta), 1)). log_prob and a KL (behaviour cloning) sum over the dims, as any Independent; entropy()
    is their mean, the entropy the reference implementation's (dcd) PPO loss weighs with the entropy
    coefficient (CarRacingNetwork.evaluate_actions: Beta.entropy().mean())."""

    def entropy(self) -> torch.Tensor:
        return self.base_dist.entropy().mean(-1)


class CarRacingStudent(FeedForwardActorCritic):
    """Conv 12->8 (4, s2) -> 16 (3, s2) -> 32 (3, s2) -> 64 (3, s2) -> 128 (3, s1) -> 256 (3, s1), ReLU,
    on the 96x96 stack (pixels x/128 - 1) -> 256 features; actor FC 100 -> alpha, beta = 1 + softplus
    (a BetaPolicy over the 3 action dims); critic FC 100 -> 1."""

    def __init__(self):
        super().__init__()
        channels = [3 * FRAME_STACK, 8, 16, 32, 64, 128, 256]
        kernels, strides = [4, 3, 3, 3, 3, 3], [2, 2, 2, 2, 1, 1]
        layers = []
        for k in range(6):
            layers += [layer_init(nn.Conv2d(channels[k], channels[k + 1], kernels[k], strides[k])), nn.ReLU()]
        self.conv = nn.Sequential(*layers, nn.Flatten())
        self.actor = nn.Sequential(layer_init(nn.Linear(256, 100)), nn.ReLU())
        self.alpha = layer_init(nn.Linear(100, 3), gain=0.01)
        self.beta = layer_init(nn.Linear(100, 3), gain=0.01)
        self.critic = nn.Sequential(layer_init(nn.Linear(256, 100)), nn.ReLU(), layer_init(nn.Linear(100, 1), gain=1.0))

    def dist_and_value(self, obs: dict, state=None, done=None):
        """-> BetaPolicy over the 3 action dims, value [B]."""
        features = self.conv_features(obs["image"])
        hidden = self.actor(features)
        alpha = 1.0 + nn.functional.softplus(self.alpha(hidden))
        beta = 1.0 + nn.functional.softplus(self.beta(hidden))
        return BetaPolicy(Beta(alpha, beta), 1), self.critic(features).squeeze(-1)

    def sample(self, dist):
        """A Beta sample kept strictly inside (0, 1), so its log-probability stays finite."""
        return dist.sample().clamp(1e-6, 1 - 1e-6)

    def conv_features(self, image: torch.Tensor) -> torch.Tensor:
        """The conv stack's features [B, 256] of uint8 stacks [B, 12, 96, 96]: by definition
        self.conv(image.float() / 128 - 1), as computed for a subclass or with CLEANUED_PLAIN_NETS=1.

        This class computes the same faster on CPU (tests check it against the definition, gradients
        included). The pixels enter centred, x - 128 (exact in float32), and the 1/128 moves
        into the first conv's weight: a power of two, so every product is the one the definition
        forms. The float pixels are laid out channels-last, which oneDNN's convs run faster than
        channels-first (its weight gradient above all), and the layers after it keep that layout."""
        if type(self) is not CarRacingStudent or os.environ.get("CLEANUED_PLAIN_NETS") == "1":
            return self.conv(image.float().mul_(1.0 / 128.0).sub_(1.0))  # in place: one float copy, not three
        pixels = torch.empty(image.shape, device=image.device, memory_format=torch.channels_last).copy_(image).sub_(128.0)
        first = self.conv[0]
        hidden = nn.functional.conv2d(pixels, first.weight * (1.0 / 128.0), first.bias, first.stride)
        return self.conv[1:](hidden)


class CarRacingTeacher(FeedForwardActorCritic):
    """Conv 1->8 (2x2) -> Conv 8->16 (2x2), ReLU, on the 10x10 sketch -> 1024; time one-hot (13) ->
    Linear 8; noise (4); concat -> Linear 256, ReLU -> 100 logits (used cells masked) and a value."""

    def __init__(self, num_steps: int = NUM_CONTROL_POINTS):
        super().__init__()
        self.num_steps = num_steps
        self.conv = nn.Sequential(layer_init(nn.Conv2d(1, 8, 2)), nn.ReLU(), layer_init(nn.Conv2d(8, 16, 2)), nn.ReLU(), nn.Flatten())
        self.time_embed = layer_init(nn.Linear(num_steps + 1, 8))
        self.hidden = nn.Sequential(layer_init(nn.Linear(16 * 8 * 8 + 8 + NOISE_DIM, 256)), nn.ReLU())
        self.actor = layer_init(nn.Linear(256, NUM_CELLS), gain=0.01)
        self.critic = layer_init(nn.Linear(256, 1), gain=1.0)

    def dist_and_value(self, obs: dict, state=None, done=None):
        """-> Categorical over the 100 cells (used ones masked), value [B]."""
        sketch = obs["sketch"].float()
        time = nn.functional.one_hot(obs["time"].long(), self.num_steps + 1).float()
        hidden = self.hidden(torch.cat([self.conv(sketch.unsqueeze(1)), self.time_embed(time), obs["noise"].float()], dim=1))
        # Used cells can never be chosen again. Logit a belongs to cell a, which the MDP stores at
        # sketch[a // 10, a % 10], so the mask is the row-major flattened sketch. (The reference
        # flattened a transposed sketch here, masking the wrong cells: a bug, not reproduced.)
        used = sketch.reshape(len(sketch), NUM_CELLS) > 0.5
        logits = self.actor(hidden).masked_fill(used, torch.finfo(torch.float32).min)
        return Categorical(logits=logits), self.critic(hidden).squeeze(-1)
