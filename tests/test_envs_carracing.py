"""CarRacing UPOMDP (envs/carracing*.py): tracks, F1 loader, rewards, renderer, teacher, mutation, nets."""

import json
import math
import os

import numpy as np
import pytest
import torch

import envs.carracing.env as cr
from envs.carracing.env import VANILLA, CarRacingEnv, CarRacingStudent, CarRacingTeacher, CarRacingTeacherMDP, designed_levels, fixed_levels
from envs.carracing.render import (
    ABS_FRONT,
    ABS_REAR,
    BACKGROUND,
    BAR_TOP,
    CAR_COLUMNS,
    CAR_ROWS,
    GRASS,
    HULL,
    PALETTE,
    ROAD,
    SPEED,
    WHEEL,
    WHEEL_HALF_LENGTH,
    WHEEL_HALF_WIDTH,
    WHEEL_STRIPE,
    ViewRenderer,
    _inside_convex,
    class_map,
)
from envs.carracing.tracks import (
    PLAYFIELD,
    SKETCH_RATIO,
    bezier_loop,
    cell_points,
    convert_formula1,
    load_f1_tracks,
    make_track,
    track_from_cells,
    track_from_centreline,
    track_metrics,
    vanilla_track,
)

from conftest import shared_f1_track_file

F1_FILE = shared_f1_track_file()
CELLS = np.array([2, 5, 8, 29, 59, 89, 97, 94, 91, 70, 40, 10])  # a ring around the sketch's border


@pytest.fixture(autouse=True)
def no_f1_file(monkeypatch):
    monkeypatch.setenv(cr.F1_ENV_VAR, cr.NO_F1_TRACKS)


def make_env(n=1, training=False, seed=0):
    env = CarRacingEnv(n, seed)
    env.training = training
    return env


def still(n=1):
    """No steering, no gas, no brake."""
    return np.tile([0.5, 0.0, 0.0], (n, 1))


def circle(radius, count=400):
    angle = np.arange(count) * 2 * math.pi / count
    return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)


# --- tracks ---------------------------------------------------------------------------------------
def test_designed_track_is_a_closed_loop_of_480_tiles():
    track = track_from_cells(CELLS)
    assert len(track) == 12 * 40
    steps = np.linalg.norm(np.roll(track.xy, -1, axis=0) - track.xy, axis=1)  # includes last -> first
    assert steps.min() > 1e-3 and steps.max() < 20
    assert np.allclose((track.xy.min(axis=0) + track.xy.max(axis=0)) / 2, 0.0)  # centred on the box
    assert np.abs(track.xy).max() < PLAYFIELD
    with pytest.raises(ValueError, match="at least 3"):
        track_from_cells(np.array([0] * 12))


def test_track_does_not_depend_on_the_teachers_order():
    rng = np.random.default_rng(0)
    for _ in range(5):
        cells = rng.choice(100, 12, replace=False)
        reference = track_from_cells(cells).xy
        for _ in range(3):
            assert np.array_equal(track_from_cells(rng.permutation(cells)).xy, reference)


def test_cell_convention_matches_sketch_and_track():
    # cell a -> column i = a % 10, row j = a // 10 -> world ((i + 1) * 33.33, (j + 1) * 33.33)
    assert np.allclose(cell_points(np.array([0, 9, 90, 37])), np.array([[1, 1], [10, 1], [1, 10], [8, 4]]) * SKETCH_RATIO)
    mdp = CarRacingTeacherMDP(np.random.default_rng(0))
    mdp.reset(1)
    for a in CELLS:
        obs, done = mdp.step(np.array([a]))
    assert done
    assert obs["sketch"][0, 3, 7] == 0 and obs["sketch"][0, 2, 9] == 1  # cell 29: row 2, column 9
    assert np.array_equal(np.nonzero(obs["sketch"][0].reshape(-1))[0], np.sort(CELLS))
    assert np.array_equal(mdp.levels().cells[0], CELLS)
    # The Bezier loop passes through every control point; centring shifts them all by one vector.
    track = track_from_cells(mdp.levels().cells[0])
    points = cell_points(CELLS)

    def all_on_track(shift):
        return np.linalg.norm((points - shift)[:, None] - track.xy[None], axis=2).min(axis=1).max() < 1e-9

    assert any(all_on_track(shift) for shift in points[0] - track.xy)


def test_bezier_segments_start_at_the_control_points():
    points = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0], [0.0, 100.0]])
    curve = bezier_loop(points)
    assert curve.shape == (160, 2)
    assert np.allclose(curve[::40], points)


def test_metrics_of_circles():
    big = make_track(circle(150.0), PLAYFIELD)
    length, curvature, sharp = track_metrics(big)
    assert length == pytest.approx(2 * 150 * math.pi, rel=1e-3)
    assert curvature == pytest.approx(2 * math.pi, rel=1e-6)
    assert sharp == 0  # turning 3.5/150 rad per gymnasium step: below its kerb threshold 0.062
    small = make_track(circle(30.0), PLAYFIELD)  # 3.5/30 = 0.117 rad per step: kerbs all round
    assert small.kerb.all() and track_metrics(small)[2] == 1
    assert np.all(small.kerb_side == -1)  # counter-clockwise = left turns: kerb on the inside (left)


# --- F1 tracks and held-out levels -------------------------------------------------------------------
def test_f1_loader_reads_the_benchmark_file():
    tracks = load_f1_tracks(F1_FILE)
    assert len(tracks) == 21 and "LagunaSeca" in tracks
    points, limit = tracks["Italy"]
    assert points.shape == (5000, 2) and limit == 1500
    assert tracks["Mexico"][1] == 3000
    track = track_from_centreline(points)
    assert np.allclose((track.xy.min(axis=0) + track.xy.max(axis=0)) / 2, 0.0)
    assert track.playfield == 500.0 and len(track) == 5000


def test_held_out_levels_with_and_without_the_f1_file(monkeypatch, capsys):
    without = make_env().test_levels()
    assert list(without) == ["vanilla", "Hairpins", "Chicanes", "LongStraights"]
    monkeypatch.setenv(cr.F1_ENV_VAR, F1_FILE)
    env = make_env()
    held_out = env.test_levels()
    assert len(held_out) == 21 and "LagunaSeca" not in held_out and "vanilla" in held_out
    assert held_out["Italy"].max_steps == 188 and held_out["Mexico"].max_steps == 375 and held_out["vanilla"].max_steps == 125
    assert env.validation_levels == ("vanilla", "Italy", "Singapore", "Germany")
    with pytest.raises(ValueError, match="Nowhere"):
        held_out["Nowhere"]
    vanilla = held_out["vanilla"].generate(3, np.random.default_rng(0))
    assert len(set(vanilla.seed.tolist())) == 3  # a fresh gymnasium track per episode


def test_bad_track_files_raise_value_error(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_f1_tracks(str(tmp_path / "missing.npz"))
    garbage = tmp_path / "garbage.npz"
    garbage.write_text("not an npz")
    with pytest.raises(ValueError, match="not a readable"):
        load_f1_tracks(str(garbage))
    wrong_shape = tmp_path / "wrong.npz"
    np.savez(wrong_shape, Italy=np.zeros((10, 3)))
    with pytest.raises(ValueError, match="Italy"):
        load_f1_tracks(str(wrong_shape))
    good = tmp_path / "good.npz"
    np.savez(good, Ring=circle(100.0))
    assert load_f1_tracks(str(good))["Ring"][1] == 2000  # no meta json: the default limit
    (tmp_path / "good_meta.json").write_text("{not json")
    os.utime(good)  # a new modification time: not served from the loader's cache
    with pytest.raises(ValueError, match="malformed"):
        load_f1_tracks(str(tmp_path / "good.npz"))


def test_converter_from_reference_format(tmp_path):
    source = tmp_path / "formula1.py"
    ring = circle(100.0, 50).round(3).tolist()
    source.write_text(
        f"from .racetrack import RaceTrack\nRing = RaceTrack(name='Ring', xy={ring}, bounds=3000, full_zoom=0.2, max_episode_steps=1234)\nOval = RaceTrack(name='Oval', xy={ring}, bounds=3000)\n"
    )
    assert convert_formula1(str(source), str(tmp_path / "mine.npz")) == ["Oval", "Ring"]
    tracks = load_f1_tracks(str(tmp_path / "mine.npz"))
    assert tracks["Ring"][1] == 1234 and tracks["Oval"][1] == 2000
    assert np.allclose(tracks["Ring"][0], ring, atol=1e-3)
    with open(tmp_path / "mine_meta.json") as f:
        assert json.load(f)["Ring"]["n_points"] == 50


# --- rewards and episode ends ----------------------------------------------------------------------
def test_standing_still_pays_the_start_tiles_then_minus_point_eight():
    env = make_env()
    env.reset(designed_levels(CELLS[None]))
    start_tiles = int(env.visited_count[0])
    assert start_tiles >= 1  # the wheels touch tiles in gymnasium's action-free reset frame
    _, reward, terminated, truncated, _ = env.step(still())
    assert reward[0] == pytest.approx(start_tiles * 1000 / 480 - 8 * 0.1, abs=1e-4)
    for _ in range(3):
        _, reward, terminated, truncated, _ = env.step(still())
        assert reward[0] == pytest.approx(-0.8, abs=1e-5) and not terminated[0] and not truncated[0]


def test_driving_pays_1000_over_n_per_new_tile():
    env = make_env()
    env.reset(designed_levels(CELLS[None]))
    seen = 0  # the start tiles (touched in the reset frame) are paid with the first step
    total_new = 0
    for _ in range(15):
        _, reward, terminated, _, _ = env.step(np.array([[0.5, 0.4, 0.0]]))
        new = int(env.visited_count[0]) - seen
        seen += new
        total_new += new
        assert reward[0] == pytest.approx(new * 1000 / 480 - 0.8, abs=1e-4)
        assert not terminated[0]
    assert total_new > 20


def test_leaving_the_playfield_costs_100_and_terminates():
    env = make_env()
    env.reset(designed_levels(CELLS[None]))
    car = env.cars[0]
    shift = 400.0 - car.hull.position[0]  # the car to x = 400, beyond the playfield's 333.3
    for body in [car.hull] + car.wheels:
        body.position = (body.position[0] + shift, body.position[1])
    obs, reward, terminated, truncated, _ = env.step(still())
    assert reward[0] == pytest.approx(-100.0) and terminated[0] and not truncated[0]
    # The copy restarted its level: the car is back on the start point, the stack holds one frame.
    assert np.allclose(env.agent_positions()[0], env.tracks[0].xy[0], atol=0.1)
    assert np.array_equal(obs["image"][0, :3], obs["image"][0, 9:])


def test_leaving_the_playfield_in_training_gets_the_done_bonus():
    env = make_env(training=True)
    env.reset(designed_levels(CELLS[None]))
    car = env.cars[0]
    shift = 400.0 - car.hull.position[0]  # the car to x = 400, beyond the playfield's 333.3
    for body in [car.hull] + car.wheels:
        body.position = (body.position[0] + shift, body.position[1])
    _, reward, terminated, _, _ = env.step(still())
    # No grass penalty: the view beyond the playfield is mostly black, its mean green far below 185.
    assert reward[0] == pytest.approx(-100.0 + 100.0) and terminated[0]


def test_episode_is_truncated_at_max_steps():
    env = make_env()
    env.reset(designed_levels(CELLS[None]), max_steps=3)
    for t in range(1, 4):
        _, _, terminated, truncated, _ = env.step(still())
        assert not terminated[0] and truncated[0] == (t == 3)
    assert env.steps[0] == 0 and env.visited_count[0] >= 1  # restarted (and its reset frame ran)


def test_training_early_stop_after_100_frames_without_progress():
    env = make_env(training=True)
    env.reset(designed_levels(CELLS[None]))
    # Frame 1 earns the start tiles; frames 2.. earn -0.1 on the road. The window of the last 100
    # frames holds only -0.1 first at frame 101 = step 13, frame 5: the episode stops there.
    for t in range(1, 13):
        _, reward, terminated, truncated, _ = env.step(still())
        assert not terminated[0]
    _, reward, terminated, truncated, _ = env.step(still())
    assert terminated[0] and not truncated[0]
    assert reward[0] == pytest.approx(-0.5, abs=1e-6)


def test_visiting_the_last_tiles_terminates():
    env = make_env()
    env.reset(designed_levels(CELLS[None]))
    env.visited[0][:] = True  # pretend the lap is done but for three tiles just ahead of the car
    env.visited[0][6:9] = False
    env.visited_count[0] = 477
    for _ in range(5):
        _, reward, terminated, _, _ = env.step(np.array([[0.5, 0.4, 0.0]]))
        if terminated[0]:
            break
    assert terminated[0]
    assert reward[0] >= 1000 / 480 - 0.8 - 1e-4  # at least the last tile, ending the step early
    assert env.visited_count[0] < 477  # the level restarted


# --- rendering -------------------------------------------------------------------------------------
def render_on_ring(x, y, angle):
    """Class image [96, 96] of a car at (x, y, angle) next to a ring road of radius 150."""
    track = make_track(circle(150.0, 600), PLAYFIELD)
    renderer = ViewRenderer()
    renderer.set_maps([class_map(track)], np.array([PLAYFIELD]))
    car = {
        "x": np.array([x]),
        "y": np.array([y]),
        "angle": np.array([angle]),
        "velocity": np.zeros((1, 2)),
        "wheel_xy": np.array([[[-1.1, 1.6], [1.1, 1.6], [-1.1, -1.64], [1.1, -1.64]]]),
        "wheel_angle": np.zeros((1, 4)),
        "wheel_phase": np.zeros((1, 4)),
        "speed": np.zeros(1),
        "wheel_omega": np.zeros((1, 4)),
        "steering": np.zeros(1),
        "angular_velocity": np.zeros(1),
    }
    view = renderer.render(car)[0].transpose(1, 2, 0)  # [96, 96, 3]
    classes = np.argmin(np.abs(view[:, :, None, :].astype(int) - PALETTE[None, None].astype(int)).sum(axis=3), axis=2)
    return view, classes


def test_view_shows_road_ahead_grass_beside_and_the_car():
    # On the ring at (150, 0) facing +y (hull angle 0): the road runs up the image through the car.
    view, classes = render_on_ring(150.0, 0.0, 0.0)
    assert classes[40, 48] == ROAD  # 16.5 units ahead
    assert classes[72, 10] in (GRASS, BACKGROUND)  # 24 units to the left: inside the ring, grass
    assert tuple(view[71, 47]) == (204, 0, 0)  # the hull, at the car's fixed place in the image
    assert classes[71, 47] == HULL
    assert np.all(view[84:, 90] == 0)  # the black indicator bar
    # Turned to face +x (across the road): the road now crosses the image left to right.
    _, turned = render_on_ring(150.0, 0.0, -math.pi / 2)
    assert turned[40, 48] != ROAD and turned[72, 10] == ROAD


def test_view_rotates_with_the_car():
    # A quarter of the way round the ring, facing along it: the same road picture.
    _, here = render_on_ring(150.0, 0.0, 0.0)
    _, there = render_on_ring(0.0, 150.0, math.pi / 2)
    assert np.mean((here == ROAD) == (there == ROAD)) > 0.99


def random_car_states(env, rng, n):
    """(copies [n], car states as ViewRenderer.classes takes them) of n random cars on env's tracks:
    on and near the road, anywhere on the grass, about the playfield's edge; turned any way, sliding,
    steering and spinning hard; wheels in every phase, some so fast that their indicator rises above
    the bar."""
    copies = rng.integers(0, env.num_envs, n)
    playfield = env.playfield[copies][:, None]
    on_road = np.stack([env.tracks[c].xy[rng.integers(len(env.tracks[c]))] for c in copies]) + rng.normal(0, 8, (n, 2))
    anywhere = rng.uniform(-1, 1, (n, 2)) * playfield
    about_the_edge = np.sign(anywhere) * (playfield + rng.uniform(-4, 4, (n, 2)))
    xy = np.choose(rng.integers(0, 3, (n, 1)), [on_road, anywhere, about_the_edge])
    upright = np.array([[-1.1, 1.6], [1.1, 1.6], [-1.1, -1.64], [1.1, -1.64]])
    car = {
        "x": xy[:, 0],
        "y": xy[:, 1],
        "angle": rng.uniform(-10, 10, n),
        "velocity": rng.normal(0, 1, (n, 2)) * rng.choice([0.2, 2.0, 40.0], (n, 1)),  # camera on the hull or the velocity
        "wheel_xy": upright + rng.normal(0, 0.05, (n, 4, 2)),
        "wheel_angle": rng.uniform(-0.6, 0.6, (n, 4)),
        "wheel_phase": rng.uniform(-50, 50, (n, 4)),
        "speed": rng.uniform(0, 120, n),
        "wheel_omega": rng.normal(0, 100, (n, 4)) * rng.choice([1.0, 8.0], (n, 1), p=[0.8, 0.2]),
        "steering": rng.uniform(-0.45, 0.45, n),
        "angular_velocity": rng.normal(0, 3, n) * rng.choice([1.0, 10.0], n),
    }
    return copies, car


def test_green_means_of_views_equal_those_of_whole_views():
    # The grass test of training's intermediate frames, bit for bit the mean of the whole rendered view.
    rng = np.random.default_rng(0)
    env = make_env(4)
    means, indicator_above_bar = [], []
    for levels in (env.random_levels(4, rng), env.random_sketch_levels(4, rng)):
        env.reset(levels)
        for _ in range(20):
            copies, car = random_car_states(env, rng, 16)
            classes = env.renderer.classes(car, copies)
            whole = env.renderer.green_means(classes)
            assert np.array_equal(env.renderer.green_means_of_views(car, copies), whole)
            means.append(whole)
            indicator_above_bar.append(np.isin(classes[:, :BAR_TOP], [SPEED, ABS_FRONT, ABS_REAR]).any(axis=(1, 2)))
    means, indicator_above_bar = np.concatenate(means), np.concatenate(indicator_above_bar)
    on_grass = means > cr.GRASS_GREEN_MEAN
    assert on_grass.sum() >= 5 and (~on_grass).sum() >= 5 and np.sum(np.abs(means - cr.GRASS_GREEN_MEAN) < 1) >= 5  # both sides, close by
    assert 0 < np.mean(indicator_above_bar) < 0.5


def test_the_hull_is_inside_the_cars_window_however_turned():
    # The hull is drawn into the car's window only: turned any way, none of it lies outside.
    renderer = ViewRenderer()
    for tilt in np.linspace(-math.pi, math.pi, 97):
        u = math.cos(tilt) * renderer.across + math.sin(tilt) * renderer.along  # the whole view, in the hull's frame
        v = -math.sin(tilt) * renderer.across + math.cos(tilt) * renderer.along
        hull = np.any([_inside_convex(u, v, edges) for edges in renderer.hull_edges], axis=0)
        in_window = np.zeros_like(hull)
        in_window[CAR_ROWS, CAR_COLUMNS] = True
        assert hull.sum() > 10 and not np.any(hull & ~in_window)


def test_wheels_tested_in_their_blocks_are_those_of_the_whole_window():
    # The renderer tests only a block of pixels around each wheel; by definition every pixel of the
    # car's window whose centre is inside a wheel is drawn. Wheels anywhere, some beyond the window.
    rng = np.random.default_rng(2)
    renderer = ViewRenderer()
    n = 200
    upright = np.array([[-1.1, 1.6], [1.1, 1.6], [-1.1, -1.64], [1.1, -1.64]])
    car = {
        "wheel_xy": upright * rng.uniform(0.5, 3, (n, 1, 1)) + rng.normal(0, 0.5, (n, 4, 2)),
        "wheel_angle": rng.uniform(-1, 1, (n, 4)),
        "wheel_phase": rng.uniform(-50, 50, (n, 4)),
    }
    tilt = rng.uniform(-4, 4, n)
    drawn = np.zeros((n,) + renderer.car_across.shape, dtype=np.uint8)
    renderer._draw_wheels(drawn, car, tilt)
    cos_tilt, sin_tilt = np.cos(tilt)[:, None], np.sin(tilt)[:, None]
    x, y = car["wheel_xy"][..., 0], car["wheel_xy"][..., 1]
    dx = renderer.car_across - (cos_tilt * x - sin_tilt * y)[..., None, None]  # [n, 4, rows, columns]
    dy = renderer.car_along - (sin_tilt * x + cos_tilt * y)[..., None, None]
    angle = car["wheel_angle"] + tilt[:, None]
    cos, sin = np.cos(angle)[..., None, None], np.sin(angle)[..., None, None]
    inside = (np.abs(dx * cos + dy * sin) <= WHEEL_HALF_WIDTH) & (np.abs(dy * cos - dx * sin) <= WHEEL_HALF_LENGTH)
    assert np.array_equal(np.isin(drawn, [WHEEL, WHEEL_STRIPE]), inside.any(axis=1))
    assert np.mean(inside.any(axis=1)) > 0.01 and np.any(drawn == WHEEL_STRIPE)


def test_training_rewards_equal_those_of_whole_rendered_frames():
    # Training tests intermediate frames for grass without rendering them: the rewards, ends and
    # observations are those of an env that renders every frame whole (the grass made lighter, so
    # that views off the road are "on grass").
    levels = designed_levels(np.stack([CELLS, np.roll(CELLS, 4), np.roll(CELLS, 8)]))
    cheap, whole = make_env(3, training=True), make_env(3, training=True)
    seen = []

    def whole_views(car, copies):
        means = whole.renderer.green_means(whole.renderer.classes(car, copies))
        seen.append(means)
        return means

    whole.renderer.green_means_of_views = whole_views
    for env in (cheap, whole):
        env.reset(levels)
        env.renderer.set_maps([np.where(m == BACKGROUND, GRASS, m) for m in env.maps], env.playfield)
    rng = np.random.default_rng(1)
    ended = 0
    for _ in range(40):
        action = np.column_stack([rng.random(3), rng.uniform(0.3, 1, 3), rng.uniform(0, 0.2, 3)])
        first, second = cheap.step(action), whole.step(action)
        for a, b in zip(first[:4], second[:4]):
            assert np.array_equal(a["image"] if isinstance(a, dict) else a, b["image"] if isinstance(b, dict) else b)
        ended += first[2].sum()
    seen = np.concatenate(seen)
    assert 0.05 < np.mean(seen > cr.GRASS_GREEN_MEAN) < 0.95 and ended > 0


def test_env_observation_layout_and_determinism():
    levels = designed_levels(np.stack([CELLS, np.roll(CELLS, 3)]))
    first, second = make_env(2, seed=3), make_env(2, seed=3)
    obs_a, obs_b = first.reset(levels), second.reset(levels)
    assert obs_a["image"].shape == (2, 12, 96, 96) and obs_a["image"].dtype == np.uint8
    assert first.single_observation_space.contains({"image": obs_a["image"][0]})
    assert np.array_equal(obs_a["image"][:, :3], obs_a["image"][:, 9:])  # first frame repeated
    actions = np.random.default_rng(0).random((5, 2, 3))
    for a in actions:
        obs_a, reward_a, *_ = first.step(a)
        obs_b, reward_b, *_ = second.step(a)
        assert np.array_equal(obs_a["image"], obs_b["image"]) and np.array_equal(reward_a, reward_b)
    assert not np.array_equal(obs_a["image"][:, :3], obs_a["image"][:, 9:])  # the stack moves on
    with pytest.raises(ValueError):
        first.reset(designed_levels(CELLS[None]))


def test_level_images_have_one_size():
    env = make_env()
    levels = designed_levels(np.stack([CELLS, np.roll(CELLS, 1)]))
    images = env.render(levels)
    assert images.shape == (2, 128, 128, 3) and images.dtype == np.uint8
    path = env.render_trajectory(levels[0], np.array([[0.0, 0.0], [10.0, 10.0]]))
    assert path.shape == (128, 128, 3) and not np.array_equal(path, images[0])


def test_vanilla_track_and_view_match_gymnasium():
    import gymnasium as gym

    game = gym.make("CarRacing-v3")
    game.reset(seed=5)
    theirs = game.unwrapped
    ours = vanilla_track(np.random.default_rng(5))  # the port draws gymnasium's track for its seed
    assert np.allclose(np.array(theirs.track)[:, 1:4], np.column_stack([ours.beta, ours.xy]))
    for k in range(55):  # past gymnasium's zoom animation of the first second
        picture, *_ = game.step(np.array([0.0, 0.5 if k < 30 else 0.0, 0.0]))
    env = make_env()
    env.reset(fixed_levels(VANILLA, np.array([5])))
    for source, target in zip([theirs.car.hull] + theirs.car.wheels, [env.cars[0].hull] + env.cars[0].wheels):
        target.position, target.angle = source.position, source.angle
        target.linearVelocity, target.angularVelocity = source.linearVelocity, source.angularVelocity
    for source, target in zip(theirs.car.wheels, env.cars[0].wheels):
        target.phase, target.omega = source.phase, source.omega
    mine = env.renderer.render(env._car_states())[0].transpose(1, 2, 0)
    game.close()
    different = np.abs(mine.astype(int) - picture.astype(int)).sum(axis=2) > 60
    assert different.mean() < 0.03  # anti-aliased edges and gymnasium's score digits only


# --- teacher ---------------------------------------------------------------------------------------
def test_teacher_never_picks_a_used_cell():
    torch.manual_seed(0)
    mdp = CarRacingTeacherMDP(np.random.default_rng(0))
    obs = mdp.reset(2)
    for a in ([27, 3], [72, 99], [0, 50]):
        obs, _ = mdp.step(np.array(a))
    teacher = CarRacingTeacher(12)
    batch = {k: torch.as_tensor(v).repeat_interleave(500, dim=0) for k, v in obs.items()}
    with torch.no_grad():
        action, logprob, entropy, value, _ = teacher.get_action_and_value(batch)
        probs = teacher.dist(batch).probs
    used = [{27, 72, 0}, {3, 99, 50}]
    for copy in range(2):
        chosen = set(action[copy * 500 : (copy + 1) * 500].tolist())
        assert not chosen & used[copy]
        assert all(float(probs[copy * 500, a]) == 0.0 for a in used[copy])
    assert torch.isfinite(logprob).all() and torch.isfinite(entropy).all() and value.shape == (1000,)
    with pytest.raises(ValueError, match="already used"):
        mdp.step(np.array([27, 4]))


def test_mask_is_not_transposed():
    teacher = CarRacingTeacher(12)
    sketch = torch.zeros(1, 10, 10)
    sketch[0, 2, 7] = 1.0  # row 2, column 7: cell 27
    obs = {"sketch": sketch, "time": torch.tensor([1]), "noise": torch.zeros(1, 4)}
    probs = teacher.dist(obs).probs[0]
    assert probs[27] == 0.0 and probs[72] > 0.0


# --- generators and mutation --------------------------------------------------------------------
def test_sketch_levels_and_mutation_move_cells_to_free_neighbours():
    env = make_env()
    rng = np.random.default_rng(0)
    levels = env.random_sketch_levels(300, rng)
    distinct = np.array([len(set(row)) for row in levels.cells.tolist()])
    child = env.mutate(levels, rng)
    assert child.cells.min() >= 0 and child.cells.max() < 100
    assert np.all([len(set(row)) for row in child.cells.tolist()] >= distinct)  # no cell newly repeats
    moved = (child.cells != levels.cells).sum(axis=1)
    assert moved.max() <= 3 and moved.mean() > 1.5
    changed = child.cells != levels.cells
    old, new = levels.cells[changed], child.cells[changed]
    assert np.all(np.maximum(np.abs(old % 10 - new % 10), np.abs(old // 10 - new // 10)) <= 3)
    fixed = env.test_levels()["Hairpins"].generate(2, rng)
    assert np.array_equal(env.mutate(fixed, rng).cells, fixed.cells)
    dr = env.random_levels(2, rng)
    assert np.array_equal(env.mutate(dr, rng).points, dr.points)  # DR's continuous tracks stay
    metrics = env.level_metrics(levels[:3])
    assert list(metrics) == ["track_length", "total_curvature", "sharp_turns"] and metrics["track_length"].shape == (3,)


# --- networks --------------------------------------------------------------------------------------
def test_student_net_shapes_and_beta_samples():
    torch.manual_seed(0)
    student = CarRacingStudent()
    obs = {"image": torch.randint(0, 256, (5, 12, 96, 96), dtype=torch.uint8)}
    action, logprob, entropy, value, state = student.get_action_and_value(obs)
    assert action.shape == (5, 3) and logprob.shape == (5,) and entropy.shape == (5,) and value.shape == (5,)
    assert state is None
    assert (action > 0).all() and (action < 1).all() and torch.isfinite(logprob).all()
    dist = student.dist(obs)
    extreme = torch.tensor([[0.0, 1.0, 0.5]] * 5)
    assert torch.isfinite(dist.log_prob(student.sample(dist))).all()
    assert torch.isfinite(dist.log_prob(extreme.clamp(1e-6, 1 - 1e-6))).all()
    assert dist.batch_shape == (5,) and dist.event_shape == (3,)  # KL / entropy summed over the 3 dims


def test_student_fast_conv_path_equals_the_definition(monkeypatch):
    """CarRacingStudent's faster conv path (centred pixels, the 1/128 folded into the first conv,
    channels-last) gives the plain definition's outputs, log-probabilities, entropies, values and
    parameter gradients, on a batch of real views and saturated pixels (0 and 255)."""
    monkeypatch.delenv("CLEANUED_PLAIN_NETS", raising=False)  # the first run takes the faster path
    torch.manual_seed(0)
    student = CarRacingStudent()
    env = make_env(3, training=True)
    rng = np.random.default_rng(0)
    images = [env.reset(env.random_levels(3, rng))["image"]]
    for _ in range(4):
        images.append(env.step(rng.random((3, 3)))[0]["image"])
    image = torch.from_numpy(np.concatenate(images))
    image[0] = 0
    image[1] = 255
    actions = torch.rand(len(image), 3).clamp(1e-6, 1 - 1e-6)

    def run():
        student.zero_grad()
        dist, value = student.dist_and_value({"image": image})
        logprob, entropy = dist.log_prob(actions), dist.entropy()
        (logprob.sum() + entropy.sum() + (value**2).sum()).backward()
        return [dist.base_dist.concentration1, dist.base_dist.concentration0, logprob, entropy, value] + [p.grad.clone() for p in student.parameters()]

    fast = run()
    monkeypatch.setenv("CLEANUED_PLAIN_NETS", "1")
    plain = run()
    for a, b in zip(fast, plain):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5 * b.abs().max().item())
    assert torch.equal(student.conv_features(image[:2]), student.conv(image[:2].float() / 128 - 1))  # plain: the definition


def test_the_shipped_f1_tracks_are_the_default(monkeypatch):
    """Without a track file named, CarRacing is evaluated on the paper's 20 circuits shipped with
    cleanued; "none" keeps quick runs on vanilla and the built-in tracks."""
    monkeypatch.delenv(cr.F1_ENV_VAR)
    held_out = make_env().test_levels()
    assert len(held_out) == 21 and "Italy" in held_out and "LagunaSeca" not in held_out
    assert os.path.isfile(os.path.join(os.path.dirname(cr.SHIPPED_F1_TRACKS), "LICENSE.md"))
