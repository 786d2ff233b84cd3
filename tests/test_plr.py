"""PLR's parts on small worked examples: the replay distribution, the buffer (plr.py's copy; accel.py's and paired_evo.py's
are the same code, tests/test_duplicated_helpers.py), the decision.
(The level scores: test_scores.py.)"""

import numpy as np
import pytest

import plr
from envs.maze import MazeEnv
from plr import LevelBuffer, rank_weights, staleness_weights

LEVELS = MazeEnv("maze", 1, 0).Levels  # the level type a maze buffer holds


def test_rank_weights_with_temperature():
    scores = np.array([3.0, 1.0, 2.0])  # ranks 1, 3, 2
    assert np.allclose(rank_weights(scores, 1.0), np.array([1, 1 / 3, 1 / 2]) / (11 / 6))
    squared = np.array([1, 1 / 9, 1 / 4])  # T = 0.5: (1 / rank)^2
    assert np.allclose(rank_weights(scores, 0.5), squared / squared.sum())


def test_staleness_weights():
    assert np.allclose(staleness_weights(np.array([0, 5, 10]), 10), [2 / 3, 1 / 3, 0])
    assert np.allclose(staleness_weights(np.array([4, 4]), 4), [0.5, 0.5])


def make_levels(n, seed=0):
    return MazeEnv("maze", n, 0).random_levels(n, np.random.default_rng(seed))


def test_replay_weights_mix_rank_and_staleness():
    buffer = LevelBuffer(capacity=3, temperature=1.0, staleness_coef=0.3, level_type=LEVELS)
    buffer.insert(make_levels(3), np.array([3.0, 1.0, 2.0]), update=0, highest_returns=np.zeros(3))
    buffer.last_sampled[:] = [0, 5, 10]
    expected = 0.7 * np.array([6, 2, 3]) / 11 + 0.3 * np.array([2 / 3, 1 / 3, 0])
    assert np.allclose(buffer.replay_weights(10), expected)


def test_insertion_and_replacement_in_a_full_buffer():
    buffer = LevelBuffer(capacity=3, temperature=1.0, staleness_coef=0.0, level_type=LEVELS)
    levels = make_levels(5)
    assert buffer.insert(levels[np.arange(3)], np.array([0.5, 0.1, 0.3]), update=1, highest_returns=np.zeros(3)) == 3
    assert len(buffer) == 3
    # Full: a level scoring below the lowest-weighted one (score 0.1, slot 1) stays out ...
    assert buffer.insert(levels[np.array([3])], np.array([0.05]), update=2, highest_returns=np.zeros(1)) == 0
    assert np.allclose(buffer.scores, [0.5, 0.1, 0.3])
    # ... one scoring above it takes its slot.
    assert buffer.insert(levels[np.array([4])], np.array([0.2]), update=2, highest_returns=np.zeros(1)) == 1
    assert np.allclose(buffer.scores, [0.5, 0.2, 0.3])
    assert np.array_equal(buffer.levels.walls[1], levels.walls[4])
    assert buffer.last_sampled[1] == 2


def test_sampling_follows_weights_and_refreshes_staleness():
    buffer = LevelBuffer(capacity=3, temperature=0.1, staleness_coef=0.0, level_type=LEVELS)
    buffer.insert(make_levels(3), np.array([0.9, 0.1, 0.2]), update=0, highest_returns=np.zeros(3))
    index = buffer.sample(200, update=7, rng=np.random.default_rng(0))
    assert np.mean(index == 0) > 0.95  # (1/rank)^10: the top level dominates
    assert buffer.last_sampled[0] == 7


def test_replay_decision():
    args = plr.resolve_args(plr.paper_args(level_buffer_size=100, replay_prob=0.5))
    rng = np.random.default_rng(0)
    assert not any(plr.decide_replay(49, args, rng) for _ in range(100))  # below half full: never
    decisions = [plr.decide_replay(50, args, rng) for _ in range(2000)]
    assert 0.45 < np.mean(decisions) < 0.55
    args.replay_prob = 0.0
    assert not any(plr.decide_replay(100, args, rng) for _ in range(100))


def test_buffer_state_round_trip():
    buffer = LevelBuffer(capacity=4, temperature=0.3, staleness_coef=0.3, level_type=LEVELS)
    buffer.insert(make_levels(3), np.array([0.1, 0.2, 0.3]), update=3, highest_returns=np.array([0.0, 0.5, 0.9]))
    restored = LevelBuffer(capacity=4, temperature=0.3, staleness_coef=0.3, level_type=LEVELS)
    restored.load_state_dict(buffer.state_dict())
    assert np.array_equal(restored.scores, buffer.scores)
    assert np.array_equal(restored.levels.walls, buffer.levels.walls)
    assert np.array_equal(restored.highest_returns, [0.0, 0.5, 0.9])  # MaxMC's record survives a resume


@pytest.mark.parametrize("bad", [dict(num_envs=30, num_minibatches=4), dict(replay_prob=1.5), dict(temperature=0.0)])
def test_bad_arguments_exit_with_status_2(bad):
    with pytest.raises(SystemExit) as exit_info:
        plr.resolve_args(plr.paper_args(**bad))
    assert exit_info.value.code == 2
