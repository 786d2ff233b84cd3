"""The walker UPOMDP (ACCEL's eight-parameter BipedalWalker, as the paper uses it) checked against
hand-worked cases and gymnasium's own walker.

Levels are written as parameter vectors in PARAM_NAMES order: roughness, pit gap (low, high), stump
height (low, high), stair height (low, high), stair steps.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gymnasium.envs.box2d.bipedal_walker import LIDAR_RANGE, BipedalWalker, BipedalWalkerHeuristics

import envs
from envs.walker.env import TRAIN_MAX_STEPS, WalkerEnv, WalkerStudent, WalkerTeacher
from envs.walker.stepping import DesignedBipedalWalker, TerrainLidar, WalkerGroup
from envs.walker.terrain import (
    CUSTOM,
    GYM_FLAT,
    GYM_HARDCORE,
    MUTATION_SIZE,
    NUM_PARAMS,
    PARAM_HIGH,
    PARAM_LOW,
    PARAM_NAMES,
    TERRAIN_HEIGHT,
    TERRAIN_STEP,
    WalkerLevels,
)

FLAT = [0, 0, 0, 0, 0, 0, 0, 1]


def levels(*param_rows, seeds=None, course=CUSTOM) -> WalkerLevels:
    """A level batch from parameter rows (terrain seeds 0, 1, ... unless given)."""
    params = np.array(param_rows, dtype=np.float64)
    seeds = np.arange(len(params)) if seeds is None else np.asarray(seeds)
    return WalkerLevels(params, seeds.astype(np.int64), np.full(len(params), course, np.int8))


def build(params, seed: int = 0, course: int = CUSTOM) -> DesignedBipedalWalker:
    """A walker reset onto one level, its terrain ready to inspect."""
    walker = DesignedBipedalWalker()
    walker.play(np.array(params, dtype=np.float64), course, seed)
    return walker


def kinds(walker: DesignedBipedalWalker) -> set[str]:
    return {f.kind for f in walker.features}


@pytest.fixture(scope="module")
def walker_env():
    env = WalkerEnv(2, seed=0, )
    yield env
    env.close()


# --- terrain ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "params, expected",
    [
        (FLAT, set()),
        ([0, 0, 0.8, 0, 0, 0, 0, 1], {"pit"}),  # pit threshold 0.8 on the high end
        ([0, 0, 0.79, 0, 0, 0, 0, 1], set()),
        ([0, 0, 0, 0, 0.2, 0, 0, 1], {"stump"}),  # stump threshold 0.2
        ([0, 0, 0, 0.1, 0.19, 0, 0, 1], set()),
        ([0, 0, 0, 0, 0, 0.2, 0.2, 9], {"stairs"}),  # stair threshold 0.2
        ([0, 0, 0, 0, 0, 0, 0.19, 9], set()),
        ([0, 3, 3, 1, 1, 1, 1, 9], {"pit", "stump", "stairs"}),
    ],
)
def test_each_obstacle_appears_exactly_when_enabled(params, expected):
    walker = build(params, seed=3)
    assert kinds(walker) == expected
    # every obstacle polygon belongs to a recorded feature: 2 pit walls, 1 stump, one block per stair step
    blocks = sum({"pit": 2, "stump": 1, "stairs": f.count}[f.kind] for f in walker.features)
    assert len(walker.obstacle_boxes()) == blocks


def box_at(boxes: np.ndarray, step: float) -> np.ndarray:
    """The obstacle box whose left edge is at terrain step `step` (Box2D keeps float32 vertices)."""
    nearest = np.argmin(np.abs(boxes[:, 0] - step * TERRAIN_STEP))
    assert boxes[nearest, 0] == pytest.approx(step * TERRAIN_STEP, abs=1e-4)
    return boxes[nearest]


def test_obstacle_sizes_within_the_level_ranges():
    walker = build([0, 2, 3, 1, 1.5, 0.5, 1, 4], seed=5)
    boxes = walker.obstacle_boxes()
    assert {"pit", "stump", "stairs"} <= kinds(walker)
    for f in walker.features:
        if f.kind == "pit":
            assert 2 <= f.size <= 3
            near, far = box_at(boxes, f.step), box_at(boxes, f.step + 1 + f.size)  # 1 + gap steps apart
            assert near[2] - near[0] == pytest.approx(TERRAIN_STEP, abs=1e-4)
            assert near[3] - near[1] == far[3] - far[1] == pytest.approx(4 * TERRAIN_STEP, abs=1e-4)  # 4 deep
        elif f.kind == "stump":
            assert 1 <= f.size <= 1.5
            box = box_at(boxes, f.step)
            assert (box[2] - box[0], box[3] - box[1]) == pytest.approx((TERRAIN_STEP, f.size * TERRAIN_STEP), abs=1e-4)
        else:
            assert 0.5 <= f.size <= 1 and 1 <= f.count <= 3 and f.direction in (-1, 1)  # randint(4): 0..3
            steps = [box_at(boxes, f.step + 4 * s) for s in range(f.count)]  # each 4 terrain steps wide
            assert np.diff([b[3] for b in steps]) == pytest.approx(np.full(f.count - 1, f.direction * f.size * TERRAIN_STEP), abs=1e-4)
            assert all(b[3] - b[1] == pytest.approx(f.size * TERRAIN_STEP, abs=1e-4) for b in steps)


def test_one_stair_step_setting_means_no_stairs():
    """stair_steps 1: randint(1) = 0 steps, as in the reference (ACCEL's easy levels)."""
    assert "stairs" not in kinds(build([0, 0, 0, 0, 0, 1, 2, 1], seed=2))


def test_terrain_is_deterministic_given_level_and_seed():
    params = [3, 1, 4, 0.5, 2, 0.5, 2, 6]
    a, b, c = build(params, seed=11), build(params, seed=11), build(params, seed=12)
    assert a.terrain_y == b.terrain_y and a.terrain_x == b.terrain_x and a.features == b.features
    assert np.array_equal(a.obstacle_boxes(), b.obstacle_boxes())
    assert a.terrain_y != c.terrain_y


def test_roughness_scales_the_grass_profile():
    """Zero roughness is flat; roughness r bends the ground r times as much as roughness 1, which is
    exactly gymnasium's BipedalWalker-v3 terrain for the same seed."""
    flat = build(FLAT, seed=4)
    assert np.all(np.array(flat.terrain_y) == TERRAIN_HEIGHT)
    one = build([1, 0, 0, 0, 0, 0, 0, 1], seed=4)
    three = build([3, 0, 0, 0, 0, 0, 0, 1], seed=4)
    gym_walker = BipedalWalker()
    gym_walker.reset(seed=4)
    assert one.terrain_y == gym_walker.terrain_y
    deviation = np.array(one.terrain_y) - TERRAIN_HEIGHT
    assert np.abs(deviation).max() > 0.1
    assert np.array(three.terrain_y) - TERRAIN_HEIGHT == pytest.approx(3 * deviation, abs=1e-9)


@pytest.mark.parametrize("course, hardcore", [(GYM_FLAT, False), (GYM_HARDCORE, True)])
def test_gymnasium_courses_use_gymnasium_terrain(course, hardcore):
    ours = build(FLAT, seed=8, course=course)
    theirs = BipedalWalker(hardcore=hardcore)
    theirs.reset(seed=8)
    assert ours.terrain_y == theirs.terrain_y and ours.terrain_x == theirs.terrain_x
    boxes = ours.obstacle_boxes()
    assert (len(boxes) > 0) == hardcore


# --- stepping --------------------------------------------------------------------------------------
def test_rewards_equal_gymnasium_for_the_same_motion():
    """Roughness 1 and no obstacles is gymnasium's v3 course: standing still, then flailing until the
    hull hits the ground, gives gymnasium's observations and rewards exactly (the -100 fall included),
    and the copy then restarts the same level."""
    env = WalkerEnv(1, seed=0, )
    obs = env.reset(levels([1, 0, 0, 0, 0, 0, 0, 1], seeds=[21]))
    gym_walker = BipedalWalker()
    gym_obs, _ = gym_walker.reset(seed=21)
    first = gym_obs.copy()
    assert np.array_equal(obs["state"][0], gym_obs)
    rng = np.random.default_rng(0)
    actions = np.concatenate([np.zeros((30, 4)), rng.uniform(-1, 1, (1500, 4))]).astype(np.float32)
    for t, action in enumerate(actions):
        obs, reward, terminated, truncated, info = env.step(action[None])
        gym_obs, gym_reward, gym_terminated, _, _ = gym_walker.step(action)
        assert reward[0] == np.float32(gym_reward) and terminated[0] == gym_terminated and not truncated[0]
        if gym_terminated:
            break
        assert np.array_equal(obs["state"][0], gym_obs)
        assert info["hull_position"][0] == pytest.approx(tuple(gym_walker.hull.position), abs=1e-5)
    assert gym_terminated and gym_reward == -100 and t > 30
    assert np.array_equal(obs["state"][0], first)  # restarted: the same level's first observation
    env.close()


# Levels whose first obstacle comes right after the start pad (within the lidar's reach from the start):
# stumps, pits, stairs, all of them on rough ground, gymnasium's hardcore and flat courses.
OBSTACLE_LEVELS = [
    ([0, 0, 0, 1, 1.5, 0, 0, 1], CUSTOM, 3),
    ([0, 1.5, 2.5, 0, 0, 0, 0, 1], CUSTOM, 4),
    ([0, 0, 0, 0, 0, 0.6, 1, 5], CUSTOM, 5),
    ([2, 1, 2, 0.5, 1, 0.5, 1, 4], CUSTOM, 6),
    (FLAT, GYM_HARDCORE, 7),
    (FLAT, GYM_FLAT, 8),
]


def play_with_gymnasium_contacts(walker: DesignedBipedalWalker, params, course: int, seed: int) -> np.ndarray:
    """walker.play, then gymnasium's own contact detector back in place of GroundContacts: with
    gymnasium's step, the reference the fast path is checked against; -> the first observation."""
    obs = walker.play(np.array(params, dtype=np.float64), course, seed)
    walker.world.contactListener = walker.world.contactListener_bug_workaround
    return obs


def test_fast_step_equals_gymnasium_step():
    """WalkerGroup's step (motors and world step per copy, lidar, observation and reward for all copies at
    once) gives exactly what gymnasium's BipedalWalker.step gives for the same level and actions: the
    walkers walk with gymnasium's heuristic plus noise into stumps, pits and stairs, fall (-100) and
    restart, or are cut at the time limit."""
    max_steps, n = 300, len(OBSTACLE_LEVELS)
    params, course, seeds = (np.array(column) for column in zip(*OBSTACLE_LEVELS))
    group = WalkerGroup(n)
    obs = group.reset(params.astype(np.float64), course, seeds, max_steps)
    references = [DesignedBipedalWalker() for _ in range(n)]
    expected = [play_with_gymnasium_contacts(walker, *level) for walker, level in zip(references, OBSTACLE_LEVELS)]
    assert np.array_equal(obs, np.array(expected))
    pilots = [BipedalWalkerHeuristics() for _ in range(n)]
    rng = np.random.default_rng(0)
    steps, ends, furthest = np.zeros(n, int), np.zeros(n, int), np.zeros(n)
    for _ in range(700):
        heuristic = np.array([pilot.step_heuristic(o.copy()) for pilot, o in zip(pilots, obs)])
        actions = np.clip(heuristic + rng.normal(0, 0.3, (n, 4)), -1, 1).astype(np.float32)
        obs, reward, terminated, truncated, hull = group.step(actions)
        steps += 1
        for i, walker in enumerate(references):
            expected_obs, expected_reward, expected_end, _, _ = walker.step(actions[i])
            assert reward[i] == np.float32(expected_reward) and terminated[i] == expected_end
            assert truncated[i] == (not expected_end and steps[i] == max_steps)
            assert np.array_equal(hull[i], np.array(tuple(walker.hull.position), dtype=np.float32))
            furthest[i] = max(furthest[i], hull[i, 0])
            if terminated[i] or truncated[i]:
                expected_obs = play_with_gymnasium_contacts(walker, *OBSTACLE_LEVELS[i])
                pilots[i], steps[i] = BipedalWalkerHeuristics(), 0
                ends[i] += 1
            assert np.array_equal(obs[i], expected_obs)
    assert np.all(ends >= 2) and np.all(furthest > 6)  # the lidar reaches the first obstacle (x > 9.3) from x > 4.1


@pytest.mark.parametrize("params, course, seed", OBSTACLE_LEVELS)
def test_lidar_equals_box2d_raycasts(params, course, seed):
    """TerrainLidar's fractions equal gymnasium's lidar (Box2D's world.RayCast with gymnasium's callback)
    bit for bit, from hulls all over the course: above, near and inside the ground and obstacles."""
    walker = DesignedBipedalWalker()
    walker.play(np.array(params, dtype=np.float64), course, seed)
    lidar = TerrainLidar([walker.lidar_targets()])
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 95, 1500).astype(np.float32).astype(np.float64)
    y = (np.interp(x, walker.terrain_x, walker.terrain_y) + rng.uniform(-1, 3, len(x))).astype(np.float32).astype(np.float64)
    expected = np.ones((len(x), 10))
    for k in range(len(x)):
        for i, ray in enumerate(walker.lidar):  # gymnasium's step, from a hull at (x, y)
            ray.fraction = 1.0
            ray.p1 = (x[k], y[k])
            ray.p2 = (x[k] + math.sin(1.5 * i / 10.0) * LIDAR_RANGE, y[k] - math.cos(1.5 * i / 10.0) * LIDAR_RANGE)
            walker.world.RayCast(ray, ray.p1, ray.p2)
            expected[k, i] = ray.fraction
    fractions = np.concatenate([lidar.scan(x[j : j + 16], y[j : j + 16]) for j in range(0, len(x), 16)])
    assert np.array_equal(fractions, expected.astype(np.float32))
    assert (expected < 1).mean() > 0.3 and (expected == 1).mean() > 0.1  # hits and misses both common


def run_episode(env: WalkerEnv, actions: np.ndarray) -> list:
    """(obs, reward) of copy 0 for the actions, up to the end of its episode."""
    run = []
    for action in actions:
        obs, reward, terminated, truncated, _ = env.step(action)
        run.append((obs["state"].copy(), reward.copy()))
        if terminated[0] or truncated[0]:
            break
    return run


def test_a_level_plays_the_same_whatever_was_played_before():
    """Each episode runs in a fresh Box2D world: a level replays exactly after a restart, and after
    other levels (a reused world would drift: it remembers the order of its past bodies)."""
    rng = np.random.default_rng(0)
    level_a, level_b = levels([3, 1, 2, 0.5, 1, 0.5, 1, 4], seeds=[7]), levels([1, 0, 0, 0, 0, 0, 0, 1], seeds=[3])
    actions = rng.uniform(-0.3, 0.3, (120, 1, 4))
    fresh = WalkerEnv(1, seed=0, )
    fresh.reset(level_b, max_steps=120)
    expected = run_episode(fresh, actions)
    replay = run_episode(fresh, actions)
    used = WalkerEnv(1, seed=0, )
    used.reset(level_a)
    run_episode(used, rng.uniform(-1, 1, (300, 1, 4)))
    used.reset(level_b, max_steps=120)
    after_other_levels = run_episode(used, actions)
    assert len(expected) > 60
    for run in (replay, after_other_levels):
        assert len(run) == len(expected)
        assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(run, expected))


def test_time_limit_truncates_and_restarts_the_level():
    env = WalkerEnv(2, seed=0, )
    first = env.reset(levels(FLAT, FLAT, seeds=[1, 2]), max_steps=3)["state"]
    zero = np.zeros((2, 4), dtype=np.float32)
    for _ in range(2):
        _, _, terminated, truncated, _ = env.step(zero)
        assert not truncated.any() and not terminated.any()
    obs, _, terminated, truncated, _ = env.step(zero)
    assert truncated.all() and not terminated.any()
    assert np.array_equal(obs["state"], first)
    assert env.reset(levels(FLAT, FLAT))["state"].shape == (2, 24)
    env.close()


def test_actions_are_clipped_to_the_box():
    env = WalkerEnv(1, seed=0, )
    env.reset(levels(FLAT))
    _, wild, _, _, _ = env.step(np.array([[5.0, -7.0, 3.0, -2.0]]))
    env.reset(levels(FLAT))
    _, clipped, _, _, _ = env.step(np.array([[1.0, -1.0, 1.0, -1.0]]))
    assert wild[0] == clipped[0]
    env.close()


def test_returned_arrays_are_the_callers():
    """A step's arrays are new ones: the next step does not overwrite them."""
    env = WalkerEnv(3, seed=0)
    env.reset(env.random_levels(3, np.random.default_rng(1)), max_steps=25)
    actions = np.random.default_rng(2).uniform(-1, 1, (2, 3, 4))
    obs, reward, terminated, truncated, info = env.step(actions[0])
    kept = [a.copy() for a in (obs["state"], reward, terminated, truncated, info["hull_position"])]
    env.step(actions[1])
    assert all(np.array_equal(a, b) for a, b in zip(kept, (obs["state"], reward, terminated, truncated, info["hull_position"])))


def test_bad_input_raises_value_error(walker_env):
    good = [1, 0, 1, 0, 1, 0, 1, 2]
    for name, value in [("roughness", 10.5), ("pit_gap_low", -0.1), ("stump_height_high", 5.2), ("stair_steps", 0), ("stair_steps", np.nan)]:
        bad = list(good)
        bad[PARAM_NAMES.index(name)] = value
        with pytest.raises(ValueError, match=name):
            walker_env.reset(levels(good, bad))
    with pytest.raises(ValueError, match="2 env copies"):
        walker_env.reset(levels(good))
    with pytest.raises(ValueError, match="course"):
        walker_env.reset(levels(good, good, course=7))
    with pytest.raises(ValueError, match="unknown held-out level 'Mountains'"):
        walker_env.test_levels()["Mountains"]


# --- generators, mutation, held-out courses ------------------------------------------------------------
def test_generators(walker_env):
    rng = np.random.default_rng(0)
    batch = walker_env.random_levels(500, rng)
    assert batch.params.shape == (500, NUM_PARAMS) and np.all(batch.course == CUSTOM)
    assert np.all(batch.params >= PARAM_LOW) and np.all(batch.params <= PARAM_HIGH)
    for low, high in ((1, 2), (3, 4), (5, 6)):
        assert np.all(batch.params[:, low] <= batch.params[:, high])
    assert batch.params[:, 0].max() > 9 and len(np.unique(batch.seed)) == 500
    easy = walker_env.easy_levels(200, rng)
    assert np.all(easy.params[:, 0] <= 0.6) and np.ptp(easy.params[:, 0]) > 0.4
    assert np.array_equal(easy.params[:, 1:], np.tile([0, 0.8, 0, 0.4, 0, 0.4, 1], (200, 1)))
    assert set(walker_env.level_generators) == {"random", "easy"}


def test_mutation_makes_at_most_three_clipped_edits_with_new_seeds(walker_env):
    rng = np.random.default_rng(0)
    parents = walker_env.random_levels(300, rng)
    parents.params[:100] = PARAM_HIGH
    parents.params[100:200] = PARAM_LOW
    children = walker_env.mutate(parents, rng)
    assert np.all(children.params >= PARAM_LOW) and np.all(children.params <= PARAM_HIGH)
    for low, high in ((1, 2), (3, 4), (5, 6)):
        assert np.all(children.params[:, low] <= children.params[:, high])
    edits = np.abs(children.params - parents.params) / MUTATION_SIZE
    assert np.all(edits.sum(axis=1) <= 3 + 1e-9)
    assert np.any(edits.sum(axis=1) > 0)
    moved = np.abs(children.params[:200, 7] - parents.params[:200, 7])  # whole steps from 1 or 9
    assert np.all(np.isin(moved, (0, 1, 2, 3))) and np.any(moved > 0)
    assert np.all(children.seed != parents.seed) and np.all(children.course == CUSTOM)
    assert np.array_equal(parents.params[:100], np.tile(PARAM_HIGH, (100, 1)))  # parents untouched


def test_held_out_courses(walker_env):
    courses = walker_env.test_levels()
    assert list(courses) == ["BipedalWalker-v3", "BipedalWalkerHardcore-v3", "Stairs", "PitGap", "Stump", "Roughness"]
    assert {name: c.max_steps for name, c in courses.items()} == {
        "BipedalWalker-v3": 1600, "BipedalWalkerHardcore-v3": 2000, "Stairs": 2000, "PitGap": 2000, "Stump": 2000, "Roughness": 2000
    }
    expected = {
        "Stairs": [0, 0, 0, 0, 0, 2, 2, 5],
        "PitGap": [0, 5, 5, 0, 0, 0, 0, 1],
        "Stump": [0, 0, 0, 2, 2, 0, 0, 1],
        "Roughness": [5, 0, 0, 0, 0, 0, 0, 1],
    }
    rng = np.random.default_rng(0)
    for name, params in expected.items():
        batch = courses[name].generate(3, rng)
        assert np.array_equal(batch.params, np.tile(params, (3, 1))) and np.all(batch.course == CUSTOM)
        assert len(np.unique(batch.seed)) == 3
    assert courses["BipedalWalker-v3"].generate(1, rng).course[0] == GYM_FLAT
    assert courses["BipedalWalkerHardcore-v3"].generate(1, rng).course[0] == GYM_HARDCORE
    assert set(walker_env.validation_levels) <= set(courses)
    walker = build(courses["PitGap"].generate(1, rng).params[0], seed=1)
    assert kinds(walker) == {"pit"} and all(f.size == 5 for f in walker.features)


# --- teacher MDP -----------------------------------------------------------------------------------
def test_teacher_maps_actions_onto_the_full_ranges():
    env = WalkerEnv(3, seed=0, )
    mdp = env.teacher()
    obs = mdp.reset(3)
    assert mdp.num_steps == 8 and mdp.action_space.shape == (1,)
    assert np.array_equal(obs["params"], np.zeros((3, 8))) and obs["time"].tolist() == [0, 0, 0]
    actions = np.array([[-1, 1, 0], [1, -1, 0.5], [-1, 1, 3.0], [1, -1, -1], [-1, 0.5, 1], [1, 0.5, 1], [0, -1, -2], [1, 1, 0]])
    noises = []
    for t, a in enumerate(actions):
        obs, done = mdp.step(a[:, None])
        noises.append(obs["noise"])
        assert done == (t == 7) and obs["time"].tolist() == [min(t + 1, 7)] * 3
        assert obs["params"][:, t] == pytest.approx(np.clip((a + 1) / 2, 0, 1))
        assert obs["noise"].shape == (3, 10) and np.all((obs["noise"] >= 0) & (obs["noise"] < 1))
    assert not np.array_equal(noises[0], noises[1])
    made = mdp.levels()
    # -1 -> the range's low end, +1 -> its high end, 0 -> the middle; actions outside [-1, 1] clipped;
    # a pair set (high, low) is swapped back (copy 0: pits and stumps, copy 1 and 2: stairs)
    assert made.params[0] == pytest.approx([0, 0, 10, 0, 5, 2.5, 5, 9])
    assert made.params[1] == pytest.approx([10, 0, 10, 0, 3.75, 0, 3.75, 9])
    assert made.params[2] == pytest.approx([5, 7.5, 10, 0, 5, 0, 5, 5])
    assert np.all(made.course == CUSTOM) and len(np.unique(made.seed)) == 3
    env.reset(made)  # a valid level batch


# --- metrics, rendering, networks, the env interface -------------------------------------------------
def test_metrics_and_rendering(walker_env):
    batch = levels(PARAM_LOW, PARAM_HIGH, [5, 5, 5, 2.5, 2.5, 2.5, 2.5, 5])
    metrics = walker_env.level_metrics(batch)
    assert tuple(metrics) == walker_env.level_metric_names == PARAM_NAMES + ("difficulty",)
    assert metrics["difficulty"] == pytest.approx([0, 1, 0.5])
    assert metrics["stair_steps"].tolist() == [1, 9, 5]
    images = walker_env.render(batch)
    assert images.dtype == np.uint8 and images.shape == (3, 96, 256, 3)
    trace = np.stack([np.linspace(5, 40, 50), np.full(50, TERRAIN_HEIGHT + 1.5)], axis=1)
    run = walker_env.render_trajectory(batch[0], trace)
    assert run.shape == (96, 256, 3)
    assert np.sum(np.all(run == [220, 30, 30], axis=-1)) > 20 and not np.any(np.all(images[0] == [220, 30, 30], axis=-1))


def test_thumbnails_show_every_stump_thick_and_dark(walker_env):
    """A stump is one terrain step (1.3 pixels) wide: drawn to scale it vanishes from a grid of level
    thumbnails. Each is drawn as a dark block at least 4 pixels wide and high."""
    batch = levels([0, 0, 0, 0.5, 0.5, 0, 0, 1], seeds=[4])
    stumps = [f for f in build(batch.params[0], seed=4).features if f.kind == "stump"]
    image = walker_env.render(batch)[0].astype(int)
    dark = image.sum(axis=-1) < 150  # sky and ground sum to 685 and 331
    columns = np.flatnonzero(dark.any(axis=0))
    runs = np.split(columns, np.flatnonzero(np.diff(columns) > 1) + 1)
    assert len(stumps) > 5 and len(runs) == len(stumps)
    assert all(len(run) >= 4 and dark[:, run].sum(axis=0).min() >= 4 for run in runs)


def test_networks():
    torch.manual_seed(0)
    student = WalkerStudent()
    obs = {"state": torch.randn(5, 24)}
    action, logprob, entropy, value, state = student.get_action_and_value(obs)
    assert action.shape == (5, 4) and logprob.shape == entropy.shape == value.shape == (5,) and state is None
    assert torch.all(student.actor_logstd == 0)
    assert student.dist(obs).mean.abs().max() < 0.1  # small policy head (gain 0.01)
    teacher = WalkerTeacher(8)
    env = WalkerEnv(4, seed=0, )
    tobs = {k: torch.as_tensor(v) for k, v in env.teacher().reset(4).items()}
    action, logprob, _, value, _ = teacher.get_action_and_value(tobs)
    assert action.shape == (4, 1) and logprob.shape == value.shape == (4,)


def test_make_gives_the_walker_interface():
    env = envs.make("walker", 2, 0)
    assert env.Student is WalkerStudent and env.Teacher is WalkerTeacher and env.Levels is WalkerLevels
    assert env.solved_threshold == 230 and env.single_action_space.shape == (4,)
    assert env.single_observation_space["state"].shape == (24,)
    assert TRAIN_MAX_STEPS == 2000 and env.training
    env.close()
