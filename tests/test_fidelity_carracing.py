"""CarRacing rules checked against the reference implementation (dcd) on worked examples: the grass
penalty's frame test, the camera, DR's and PLR's level generators, the student's entropy."""

import math

import numpy as np
import pytest
import torch
from torch.distributions import Beta, Normal, kl_divergence

import envs.carracing.env as cr
from envs.carracing.env import CONTINUOUS, DESIGNED, BetaPolicy, CarRacingEnv, CarRacingStudent, designed_levels
from envs.carracing.render import GRASS, HULL, MAP_MARGIN, PALETTE, PIXELS_PER_UNIT, ROAD, ViewRenderer, camera_angle, class_map
from envs.carracing.tracks import PLAYFIELD, SKETCH_RATIO, make_track, well_spaced
from envs.walker import WalkerStudent

CELLS = np.array([2, 5, 8, 29, 59, 89, 97, 94, 91, 70, 40, 10])  # a ring around the sketch's border
STILL = np.array([[0.5, 0.0, 0.0]])


@pytest.fixture(autouse=True)
def no_f1_file(monkeypatch):
    monkeypatch.setenv(cr.F1_ENV_VAR, cr.NO_F1_TRACKS)


def newest_green_mean(obs) -> float:
    """The mean green of the newest frame of copy 0's stack (channels 9-11 are its RGB)."""
    return float(obs["image"][0, 10].mean())


# --- the grass penalty: mean green of the rendered frame > 185 (CarRacingWrapper.step) --------------
def test_grass_penalty_is_the_frames_mean_green_not_the_cars_position():
    env = CarRacingEnv(1, 0)
    env.reset(designed_levels(CELLS[None]))
    car = env.cars[0]
    dx, dy = -car.hull.position[0], -car.hull.position[1]  # the car to the playfield's centre: grass,
    for body in [car.hull] + car.wheels:  # 150 units from the road
        body.position = (body.position[0] + dx, body.position[1] + dy)
    env.step(STILL)  # the start tiles' reward
    # Standing on plain grass the frame's mean green is ~183 (grass 204 with a quarter of lighter
    # 230 patches, the black indicator bar, the car): not "on grass" by the reference's test.
    obs, reward, *_ = env.step(STILL)
    x, y = env.agent_positions()[0]
    row, column = (np.array([y, x]) + env.playfield[0]) * PIXELS_PER_UNIT + MAP_MARGIN
    assert env.maps[0][int(row), int(column)] != ROAD  # the hull is off the road
    assert 180 < newest_green_mean(obs) < 185
    assert reward[0] == pytest.approx(-8 * 0.1, abs=1e-6)
    # The same car, its world repainted all light grass: mean green 201 over the top 84 rows, > 185.
    all_grass = np.full_like(env.maps[0], GRASS)
    env.renderer.set_maps([all_grass], env.playfield)
    obs, reward, *_ = env.step(STILL)
    assert newest_green_mean(obs) > 185
    assert reward[0] == pytest.approx(-8 * (0.1 + 0.05), abs=1e-6)
    # Training renders each physics frame for the test; the agent sees the last one, as evaluation's.
    training, evaluation = CarRacingEnv(2, 0), CarRacingEnv(2, 0)
    evaluation.training = False
    levels = designed_levels(np.stack([CELLS, np.roll(CELLS, 2)]))
    assert np.array_equal(training.reset(levels)["image"], evaluation.reset(levels)["image"])
    for action in np.random.default_rng(0).random((6, 2, 3)):
        assert np.array_equal(training.step(action)[0]["image"], evaluation.step(action)[0]["image"])


def test_green_means_of_hand_made_frames():
    frames = np.full((2, 96, 96), GRASS, dtype=np.uint8)
    frames[1, :60] = ROAD  # mostly road
    means = ViewRenderer.green_means(frames)
    assert means[0] == pytest.approx(230.0)  # all grass: penalised
    assert means[1] == pytest.approx((60 * 102 + 36 * 230) / 96)  # 150: not
    assert np.array_equal(means > cr.GRASS_GREEN_MEAN, [True, False])


# --- the camera (CarRacingBezier.render) -----------------------------------------------------------
def test_camera_turns_with_the_velocity_above_speed_half():
    hull = np.array([0.3, 0.3, 0.3, 0.3])
    velocity = np.array([[3.0, 4.0], [-2.0, 0.0], [0.3, 0.3], [0.0, 0.5]])  # speeds 5, 2, 0.42, 0.5
    angle = camera_angle(hull, velocity)
    # The reference's rotation atan2(vx, vy) is hull angle -atan2(vx, vy): a hull at that angle drives
    # towards (-sin, cos) = the velocity's direction.
    assert angle[0] == pytest.approx(-math.atan2(3.0, 4.0))
    assert (-math.sin(angle[0]), math.cos(angle[0])) == pytest.approx((0.6, 0.8))
    assert angle[1] == pytest.approx(math.pi / 2)  # moving towards -x
    assert angle[2] == 0.3 and angle[3] == 0.3  # 0.5 and below: the hull's angle


def render_on_ring(hull_angle, velocity):
    """Class image [96, 96] of a car at (150, 0) on a ring road of radius 150 (the road runs along y)."""
    angle = np.arange(600) * 2 * math.pi / 600
    track = make_track(np.stack([150 * np.cos(angle), 150 * np.sin(angle)], axis=1), PLAYFIELD)
    renderer = ViewRenderer()
    renderer.set_maps([class_map(track)], np.array([PLAYFIELD]))
    car = {
        "x": np.array([150.0]),
        "y": np.array([0.0]),
        "angle": np.array([hull_angle]),
        "velocity": np.array([velocity], dtype=np.float64),
        "wheel_xy": np.array([[[-1.1, 1.6], [1.1, 1.6], [-1.1, -1.64], [1.1, -1.64]]]),
        "wheel_angle": np.zeros((1, 4)),
        "wheel_phase": np.zeros((1, 4)),
        "speed": np.array([math.hypot(*velocity)]),
        "wheel_omega": np.zeros((1, 4)),
        "steering": np.zeros(1),
        "angular_velocity": np.zeros(1),
    }
    view = renderer.render(car)[0].transpose(1, 2, 0)
    return np.argmin(np.abs(view[:, :, None, :].astype(int) - PALETTE[None, None].astype(int)).sum(axis=3), axis=2)


def test_view_follows_the_velocity_and_shows_the_hull_turned():
    # The hull faces +x (across the road, hull angle -pi/2) while the car slides along the road (+y).
    fast = render_on_ring(-math.pi / 2, (0.0, 10.0))
    assert fast[40, 48] == ROAD and fast[72, 10] != ROAD  # the road runs up the image
    rows, columns = np.nonzero(fast == HULL)
    assert np.ptp(columns) * 0.643 > np.ptp(rows) * 0.514  # the hull lies across the image
    slow = render_on_ring(-math.pi / 2, (0.0, 0.4))
    assert slow[40, 48] != ROAD and slow[72, 10] == ROAD  # below 0.5 the hull points up: road across
    rows, columns = np.nonzero(slow == HULL)
    assert np.ptp(rows) * 0.514 > np.ptp(columns) * 0.643


# --- the level generators ----------------------------------------------------------------------------
def test_dr_levels_are_continuous_control_points_in_the_reference_ranges():
    env = CarRacingEnv(1, 0)
    assert env.level_generators["random"] == env.random_levels
    levels = env.random_levels(500, np.random.default_rng(0))
    assert np.all(levels.track == CONTINUOUS) and levels.points.shape == (500, 12, 2)
    points = levels.points
    assert points.min() >= 0 and points.max() < PLAYFIELD  # get_random_points: U[0, 1)^2 * playfield
    assert points.min() < 2 and points.max() > PLAYFIELD - 2
    assert abs(points.mean() - PLAYFIELD / 2) < 3
    off_grid = np.abs(points / SKETCH_RATIO - np.round(points / SKETCH_RATIO)) > 1e-6
    assert off_grid.mean() > 0.99  # not sketch cells
    assert well_spaced(points / PLAYFIELD).mean() > 0.99  # redrawn while crowded
    track = env.track_of(levels, 0)
    assert len(track) == 12 * 40 and np.allclose((track.xy.min(axis=0) + track.xy.max(axis=0)) / 2, 0.0)
    env.reset(levels[:1])
    assert env.step(STILL)[1].shape == (1,)


def test_dr_spacing_uses_the_references_measure():
    # 12 points on a circle of radius 0.4 (neighbours 0.21 apart): one step along (1, -1) has
    # dx + dy = 0, so the set is crowded by the reference's |dx + dy| >= 0.7 / 12 ...
    phase = -3 * math.pi / 4 - math.pi / 12
    angle = phase + np.arange(12) * 2 * math.pi / 12
    crowded = 0.5 + 0.4 * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    # ... and turned by half a step, its smallest |dx + dy| is 0.21 * sqrt(2) sin(pi / 12) = 0.076.
    spaced = 0.5 + 0.4 * np.stack([np.cos(angle + math.pi / 12), np.sin(angle + math.pi / 12)], axis=1)
    assert np.array_equal(well_spaced(np.stack([crowded, spaced])), [False, True])


def test_plr_levels_are_12_sketch_cells_drawn_with_replacement():
    env = CarRacingEnv(1, 0)
    assert env.level_generators["sketch"] == env.random_sketch_levels
    n = 4000
    levels = env.random_sketch_levels(n, np.random.default_rng(0))
    assert np.all(levels.track == DESIGNED) and levels.cells.shape == (n, 12)
    assert levels.cells.min() == 0 and levels.cells.max() == 99
    repeats = np.array([len(set(row)) < 12 for row in levels.cells.tolist()])
    no_repeat = math.prod(1 - k / 100 for k in range(12))  # 12 draws of 100 cells all different: 0.503
    assert repeats.mean() == pytest.approx(1 - no_repeat, abs=0.03)
    counts = np.bincount(levels.cells.reshape(-1), minlength=100)
    assert counts.min() > 0.75 * n * 12 / 100 and counts.max() < 1.25 * n * 12 / 100  # uniform
    doubled = designed_levels(np.array([[11, 11, 14, 17, 41, 47, 71, 74, 77, 77, 77, 44]]))
    track = env.track_of(doubled, 0)  # a repeated cell is one control point twice: no zero steps
    assert np.linalg.norm(np.roll(track.xy, -1, axis=0) - track.xy, axis=1).min() > 1e-3
    env.reset(doubled)
    assert env.step(STILL)[1].shape == (1,)


# --- the student's entropy (CarRacingNetwork.evaluate_actions: Beta.entropy().mean()) -----------------
def test_student_entropy_is_the_mean_over_action_dims():
    uniform = BetaPolicy(Beta(torch.ones(2, 3), torch.ones(2, 3)), 1)
    assert torch.equal(uniform.entropy(), torch.zeros(2))  # Beta(1, 1): entropy 0 per dim
    alpha, beta = torch.tensor([[2.0, 3.0, 1.5]]), torch.tensor([[2.0, 1.2, 4.0]])
    per_dim = Beta(alpha, beta).entropy()  # -0.1251, -0.3512, -0.3216
    policy = BetaPolicy(Beta(alpha, beta), 1)
    assert policy.entropy() == pytest.approx(float(per_dim.mean()))
    action = torch.tensor([[0.3, 0.8, 0.1]])
    assert policy.log_prob(action) == pytest.approx(float(Beta(alpha, beta).log_prob(action).sum()))  # summed
    other = BetaPolicy(Beta(beta, alpha), 1)
    assert kl_divergence(policy, other) == pytest.approx(float(kl_divergence(Beta(alpha, beta), Beta(beta, alpha)).sum()))
    # Through the student: heads with zero weights give alpha = 1 + softplus(bias) for every input.
    student = CarRacingStudent()
    with torch.no_grad():
        for head, bias in ((student.alpha, [0.0, 1.0, 2.0]), (student.beta, [2.0, 1.0, 0.0])):
            head.weight.zero_()
            head.bias.copy_(torch.tensor(bias))
    obs = {"image": torch.randint(0, 256, (4, 12, 96, 96), dtype=torch.uint8)}
    actions = torch.full((4, 3), 0.4)
    _, logprob, entropy, _, _ = student.get_action_and_value(obs, action=actions)
    concentration = (1 + torch.nn.functional.softplus(torch.tensor([0.0, 1.0, 2.0])), 1 + torch.nn.functional.softplus(torch.tensor([2.0, 1.0, 0.0])))
    expected = Beta(*concentration)
    assert torch.allclose(entropy, expected.entropy().mean().expand(4))
    assert torch.allclose(logprob, expected.log_prob(torch.full((3,), 0.4)).sum().expand(4))
    # The walker's Gaussian keeps its reference's sum (FixedNormal.entropy().sum(-1)): log-std 0, 4 dims.
    walker = WalkerStudent()
    _, _, walker_entropy, _, _ = walker.get_action_and_value({"state": torch.zeros(2, 24)})
    assert torch.allclose(walker_entropy, Normal(0.0, 1.0).entropy() * 4)
