"""ACCEL's and PAIRED+Evo's own parts on worked examples (accel.py, paired_evo.py): the choice of the
levels to edit, the regret scores of Algorithm 2 (plain and flexible), the children's way into a full
level buffer (each script's copy of Robust PLR's), and the paper's defaults and bad input per script.
(The edits themselves, `env.mutate`, are tested in test_envs_maze_levels.py; the buffer's replay distribution in
test_plr.py.)"""

import numpy as np
import pytest

import accel
import paired_evo
from envs.maze import MazeEnv

SCRIPTS = [accel, paired_evo]

LEVELS = MazeEnv("maze", 1, 0).Levels  # the level type a maze buffer holds


def same_level(a, i, b, j) -> bool:
    """Level a[i] equals level b[j] (walls, goal, agent start and direction)."""
    return (np.array_equal(a.walls[i], b.walls[j]) and np.array_equal(a.goal[i], b.goal[j])
            and np.array_equal(a.agent[i], b.agent[j]) and a.agent_dir[i] == b.agent_dir[j])


# ---------------------------------------------------------------------------------------------------
# The parents of the children: "easy" (lowest-score half, twice each) or "batch" (all, once)
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
def test_easy_parents_are_the_lowest_scoring_half_each_twice(script):
    scores = np.array([0.3, 0.1, 0.3, 0.0, 0.2, 0.1])
    # ascending: 3 (0.0), 1 (0.1), 5 (0.1), 4 (0.2), 0 (0.3), 2 (0.3): the easy half is {3, 1, 5}
    parents = script.select_parents(scores, "easy")
    assert len(parents) == len(scores)
    assert sorted(parents.tolist()) == [1, 1, 3, 3, 5, 5]
    assert np.array_equal(np.bincount(parents, minlength=6), [0, 2, 0, 2, 0, 2])


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
def test_easy_parents_break_ties_at_the_cut_stably(script):
    # ascending: 1 (0.1), then the tie 0 (0.2) and 2 (0.2): the cut after two keeps index 0, not 2
    parents = script.select_parents(np.array([0.2, 0.1, 0.2, 0.3]), "easy")
    assert sorted(parents.tolist()) == [0, 0, 1, 1]
    # all equal: the first half of the batch
    parents = script.select_parents(np.full(8, 0.5), "easy")
    assert sorted(parents.tolist()) == [0, 0, 1, 1, 2, 2, 3, 3]


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
def test_negative_scores_count_as_easiest(script):
    # PAIRED+Evo's regret is not clipped: a level the protagonist masters scores below zero
    parents = script.select_parents(np.array([0.4, -0.5, 0.0, -0.1]), "easy")
    assert sorted(parents.tolist()) == [1, 1, 3, 3]


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
def test_batch_parents_are_every_level_once(script):
    scores = np.array([0.3, 0.1, 0.3, 0.0, 0.2])
    parents = script.select_parents(scores, "batch")
    assert len(parents) == len(scores)
    assert sorted(parents.tolist()) == [0, 1, 2, 3, 4]


# ---------------------------------------------------------------------------------------------------
# Algorithm 2's scores: regret U(A) - U(P) and the flexible regret
# ---------------------------------------------------------------------------------------------------
PROTAGONIST = [[0.5, 0.7], [], [0.9], [0.2], [0.9, 0.1], [0.5, 0.3], []]
ANTAGONIST = [[0.8, 0.6], [0.4], [], [0.1, 0.3], [0.6, 0.2], [0.5, 0.1], []]


def test_regret_is_max_antagonist_minus_mean_protagonist_not_clipped():
    result = paired_evo.regret(PROTAGONIST, ANTAGONIST)
    # 0: 0.8 - 0.6; 1: 0.4 - 0 (no protagonist episode); 2: 0 (no antagonist episode) - 0.9, kept
    # negative; 3: 0.3 - 0.2; 4: 0.6 - 0.5; 5: 0.5 - 0.4; 6: nothing completed
    assert np.allclose(result, [0.2, 0.4, -0.9, 0.1, 0.1, 0.1, 0.0])
    assert result.shape == (7,)


def test_regret_uses_the_antagonist_max_and_the_protagonist_mean():
    # Swapping the students' roles changes the value: it is not symmetric.
    assert np.allclose(paired_evo.regret([[0.2, 0.6]], [[0.1, 0.9]]), [0.9 - 0.4])
    assert np.allclose(paired_evo.regret([[0.1, 0.9]], [[0.2, 0.6]]), [0.6 - 0.5])


def test_flexible_regret_on_worked_examples_with_role_swap():
    result = paired_evo.flexible_regret(PROTAGONIST, ANTAGONIST)
    # 0: A_max 0.8 > P_max 0.7 -> 0.8 - P_mean 0.6 = 0.2
    # 1: A_max 0.4 > P_max 0 (none) -> 0.4 - 0
    # 2: roles swap, P_max 0.9 > A_max 0 -> 0.9 - A_mean 0 = 0.9 (plain regret: -0.9)
    # 3: A_max 0.3 > P_max 0.2 -> 0.3 - 0.2 = 0.1
    # 4: roles swap, P_max 0.9 > A_max 0.6 -> 0.9 - A_mean 0.4 = 0.5 (plain regret: 0.1)
    # 5: a tie A_max = P_max = 0.5 is not "A_max > P_max": P_max - A_mean = 0.5 - 0.3 = 0.2
    #    (the other branch would give 0.5 - 0.4 = 0.1)
    # 6: nothing completed -> 0
    assert np.allclose(result, [0.2, 0.4, 0.9, 0.1, 0.5, 0.2, 0.0])
    assert np.all(result >= 0)


def test_flexible_regret_has_no_fixed_roles():
    # Exchanging protagonist and antagonist gives the same score when the maxima differ.
    p, a = [[0.2, 0.6], [0.9, 0.1], [0.3]], [[0.1, 0.9], [0.5], [0.8, 0.2]]
    assert np.allclose(paired_evo.flexible_regret(p, a), paired_evo.flexible_regret(a, p))
    assert np.allclose(paired_evo.flexible_regret(p, a), [0.9 - 0.4, 0.9 - 0.5, 0.8 - 0.3])


# ---------------------------------------------------------------------------------------------------
# Children into a full buffer: each replaces the level of lowest replay weight if it scores higher
# ---------------------------------------------------------------------------------------------------
NO_RETURNS = np.zeros(4)  # the levels' highest returns (MaxMC's record), which these tests leave aside


def parents_and_children(parent_scores, seed=0):
    env = MazeEnv("maze", 4, 0)
    rng = np.random.default_rng(seed)
    buffer_levels = env.random_levels(4, rng)
    parents = accel.select_parents(np.asarray(parent_scores), "easy")  # (paired_evo.py's is the same code)
    children = env.mutate(buffer_levels[parents], rng, 5)
    # the test below tells levels apart by content: all eight must differ
    pool = type(children).concat([buffer_levels, children])
    assert not any(same_level(pool, i, pool, j) for i in range(8) for j in range(i))
    return buffer_levels, children


def test_children_replace_the_lowest_weighted_levels_of_a_full_buffer():
    buffer = accel.LevelBuffer(capacity=4, temperature=1.0, staleness_coef=0.0, level_type=LEVELS)
    levels, children = parents_and_children([0.4, 0.1, 0.3, 0.2])
    assert buffer.insert(levels, np.array([0.4, 0.1, 0.3, 0.2]), update=1, highest_returns=NO_RETURNS) == 4
    # Children offered one by one (rank weights only, so the lowest weight is the lowest score):
    # child 0 (0.05) < slot 1 (0.1): out; child 1 (0.25) > slot 1 (0.1): takes slot 1;
    # child 2 (0.15) < now-lowest slot 3 (0.2): out; child 3 (0.5) > slot 3 (0.2): takes slot 3.
    entered = buffer.insert(children, np.array([0.05, 0.25, 0.15, 0.5]), update=2, highest_returns=NO_RETURNS)
    assert entered == 2
    assert len(buffer) == 4
    assert np.allclose(buffer.scores, [0.4, 0.25, 0.3, 0.5])
    assert same_level(buffer.levels, 0, levels, 0) and same_level(buffer.levels, 2, levels, 2)
    assert same_level(buffer.levels, 1, children, 1) and same_level(buffer.levels, 3, children, 3)
    assert buffer.last_sampled.tolist() == [1, 2, 1, 2]


def test_a_child_must_beat_not_equal_the_lowest_level():
    buffer = accel.LevelBuffer(capacity=4, temperature=1.0, staleness_coef=0.0, level_type=LEVELS)
    levels, children = parents_and_children([0.4, 0.1, 0.3, 0.2], seed=1)
    buffer.insert(levels, np.array([0.4, 0.1, 0.3, 0.2]), update=1, highest_returns=NO_RETURNS)
    assert buffer.insert(children, np.array([0.1, 0.1, 0.0, -0.3]), update=2, highest_returns=NO_RETURNS) == 0
    assert np.allclose(buffer.scores, [0.4, 0.1, 0.3, 0.2])
    assert all(same_level(buffer.levels, i, levels, i) for i in range(4))


def test_with_staleness_the_lowest_weight_not_the_lowest_score_is_replaced():
    # scores [0.1, 0.2, 0.3, 0.4], T = 1: rank weights (1/4, 1/3, 1/2, 1) / (25/12) = [0.12, 0.16, 0.24, 0.48];
    # rho = 0.5 and slot 0 stale (last sampled at 0, the others at 5; update 5): staleness [1, 0, 0, 0].
    # P = [0.56, 0.08, 0.12, 0.24]: the lowest weight is slot 1 (score 0.2), not slot 0 (score 0.1).
    buffer = accel.LevelBuffer(capacity=4, temperature=1.0, staleness_coef=0.5, level_type=LEVELS)
    levels, children = parents_and_children([0.1, 0.2, 0.3, 0.4], seed=2)
    buffer.insert(levels, np.array([0.1, 0.2, 0.3, 0.4]), update=5, highest_returns=NO_RETURNS)
    buffer.last_sampled[:] = [0, 5, 5, 5]
    assert np.allclose(buffer.replay_weights(5), [0.56, 0.08, 0.12, 0.24])
    # child 0 (0.15) beats slot 0's 0.1 but not slot 1's 0.2: out; child 1 (0.25) takes slot 1 (fresh, now
    # scores [0.1, 0.25, 0.3, 0.4], ranks unchanged: slot 1 lowest again); child 2 (0.35) takes slot 1
    # (now the lowest weight is slot 2's, score 0.3); child 3 (0.2) < 0.3: out.
    entered = buffer.insert(children, np.array([0.15, 0.25, 0.35, 0.2]), update=5, highest_returns=NO_RETURNS)
    assert entered == 2
    assert np.allclose(buffer.scores, [0.1, 0.35, 0.3, 0.4])
    assert same_level(buffer.levels, 1, children, 2)
    assert all(same_level(buffer.levels, i, levels, i) for i in (0, 2, 3))


def test_children_fill_free_room_first():
    buffer = accel.LevelBuffer(capacity=6, temperature=0.3, staleness_coef=0.5, level_type=LEVELS)
    levels, children = parents_and_children([0.4, 0.1, 0.3, 0.2], seed=3)
    buffer.insert(levels, np.array([0.4, 0.1, 0.3, 0.2]), update=1, highest_returns=NO_RETURNS)
    # two free slots: the first two children enter whatever their score (slots 4 and 5); then the buffer
    # is full, its lowest weight is slot 4's (score -0.2, lowest rank, fresh): child 2 (-0.5) stays out,
    # child 3 (0.9) takes slot 4
    entered = buffer.insert(children, np.array([-0.2, 0.0, -0.5, 0.9]), update=2, highest_returns=NO_RETURNS)
    assert entered == 3
    assert len(buffer) == 6
    assert np.allclose(buffer.scores, [0.4, 0.1, 0.3, 0.2, 0.9, 0.0])
    assert same_level(buffer.levels, 4, children, 3) and same_level(buffer.levels, 5, children, 1)


# ---------------------------------------------------------------------------------------------------
# The paper's defaults and bad input
# ---------------------------------------------------------------------------------------------------
def test_accel_maze_defaults_are_the_papers():
    args = accel.resolve_args(accel.paper_args(env="maze"))
    assert (args.replay_prob, args.level_buffer_size, args.temperature, args.staleness_coef, args.num_edits) == (0.8, 4000, 0.3, 0.3, 5)
    assert (args.num_envs, args.num_steps, args.learning_rate, args.gamma, args.gae_lambda) == (32, 256, 1e-4, 0.995, 0.95)
    assert (args.generator, args.edit_levels, args.min_fill_ratio, args.exp_name) == ("empty", "easy", 0.5, "accel")
    assert accel.paper_args(env="maze", generator="random").exp_name == "accel_random"  # the variant keeps its own name


def test_paired_evo_maze_defaults_are_the_papers():
    args = paired_evo.resolve_args(paired_evo.paper_args(env="maze"))
    assert (args.replay_prob, args.level_buffer_size, args.bc_coef, args.flexible) == (0.5, 4000, 0.0, False)
    assert (args.temperature, args.staleness_coef, args.num_edits, args.student_ent_coef) == (0.3, 0.3, 5, 0.0)
    assert (args.generator, args.exp_name) == ("empty", "paired_evo")
    assert paired_evo.paper_args(env="maze", generator="random", bc_coef=0.01).exp_name == "paired_evo_unibc_random"
    flexible = paired_evo.resolve_args(paired_evo.paper_args(env="maze", flexible=True))
    assert (flexible.replay_prob, flexible.level_buffer_size, flexible.bc_coef) == (0.9, 4000, 0.0)
    # an explicit replay probability wins over either default
    assert paired_evo.resolve_args(paired_evo.paper_args(env="maze", flexible=True, replay_prob=0.3)).replay_prob == 0.3
    assert paired_evo.resolve_args(paired_evo.paper_args(env="maze", replay_prob=0.7)).replay_prob == 0.7


def test_an_odd_batch_is_fine_when_every_level_is_edited():
    assert accel.resolve_args(accel.paper_args(num_envs=5, edit_levels="batch")).num_envs == 5
    assert paired_evo.resolve_args(paired_evo.paper_args(num_envs=5, edit_levels="batch")).num_envs == 5


BAD = [dict(num_envs=5), dict(num_edits=0), dict(replay_prob=1.5), dict(env="mars")]


@pytest.mark.parametrize("bad", BAD, ids=lambda b: "-".join(f"{k}={v}" for k, v in b.items()))
@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
def test_bad_arguments_exit_with_status_2(script, bad, capsys):
    with pytest.raises(SystemExit) as exit_info:
        make = script.Args if "env" in bad else script.paper_args  # an unknown env has no paper values
        script.resolve_args(make(**bad))
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.startswith("error: ")


@pytest.mark.parametrize("bad", [dict(bc_coef=-0.1), dict(bc_interval=0), dict(replay_prob=1.5, flexible=True)],
                         ids=lambda b: "-".join(f"{k}={v}" for k, v in b.items()))
def test_paired_evo_bad_cloning_arguments_exit_with_status_2(bad, capsys):
    with pytest.raises(SystemExit) as exit_info:
        paired_evo.resolve_args(paired_evo.paper_args(**bad))
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.startswith("error: ")
