"""The maze's optimal-return solver (true regret = optimal return - the student's expected return):
hand-worked levels, a brute-force search on small random grids, and an optimal path played in the env."""

from collections import deque

import numpy as np
import pytest

from envs.maze.env import DIRECTION_VECTORS, FORWARD, LEFT, RIGHT, MazeEnv, optimal_returns
from envs.maze.levels import MazeLevels

EAST, SOUTH, WEST, NORTH = 0, 1, 2, 3


def level(rows: str, agent_dir: int) -> MazeLevels:
    grid = np.array([list(r.strip()) for r in rows.strip().splitlines()])
    (gy,), (gx,) = np.nonzero(grid == "G")
    (ay,), (ax,) = np.nonzero(grid == "A")
    return MazeLevels((grid == "#")[None], np.array([[gx, gy]]), np.array([[ax, ay]]), np.array([agent_dir], np.int8))


def best(actions: int, max_steps: int = 250) -> float:
    return 1.0 - 0.9 * actions / max_steps


OPEN = """
#####
#A.G#
#...#
#...#
#####
"""


@pytest.mark.parametrize("direction, actions", [
    (EAST, 2),  # straight line: forward, forward
    (SOUTH, 3),  # one turn (left), then forward twice
    (NORTH, 3),  # one turn (right)
    (WEST, 4),  # facing away: two turns
])
def test_hand_worked_levels(direction, actions):
    assert optimal_returns(level(OPEN, direction)) == pytest.approx([best(actions)])


def test_a_path_around_a_wall():
    walled = """
    #####
    #A#G#
    #...#
    #####
    """
    # Facing east: right (south), forward, left (east), forward, forward, left (north), forward = 7.
    assert optimal_returns(level(walled, EAST)) == pytest.approx([best(7)])


def test_walled_off_goal_and_the_step_limit():
    walled_off = """
    #####
    #A#G#
    #.###
    #####
    """
    assert optimal_returns(level(walled_off, EAST)) == [0.0]
    # Two actions needed: within a limit of 2, out of reach within 1.
    two = level(OPEN, EAST)
    assert optimal_returns(two, max_steps=2) == pytest.approx([best(2, 2)])
    assert optimal_returns(two, max_steps=1) == [0.0]


def test_a_random_start_direction_gives_the_mean_over_directions():
    # East 2, south 3, west 4, north 3 actions: the expected optimum over a uniform direction.
    expected = np.mean([best(2), best(3), best(4), best(3)])
    assert optimal_returns(level(OPEN, -1)) == pytest.approx([expected])


def brute_force(walls, goal, agent, direction):
    """Breadth-first search over (x, y, direction) with the env's rules, one state at a time; returns the
    fewest actions to the goal and the actions themselves (None if unreachable)."""
    start = (agent[0], agent[1], direction)
    parent = {start: None}
    queue = deque([start])
    while queue:
        x, y, d = queue.popleft()
        for action in (LEFT, RIGHT, FORWARD):
            if action == FORWARD:
                dx, dy = DIRECTION_VECTORS[d]
                nxt = (x, y, d) if walls[y + dy, x + dx] else (x + dx, y + dy, d)
            else:
                nxt = (x, y, (d + (1 if action == RIGHT else -1)) % 4)
            if nxt in parent:
                continue
            parent[nxt] = ((x, y, d), action)
            if (nxt[0], nxt[1]) == tuple(goal):
                path = []
                while parent[nxt] is not None:
                    nxt, action = parent[nxt]
                    path.append(action)
                return len(path), path[::-1]
            queue.append(nxt)
    return None, None


def test_against_brute_force_and_the_env_on_random_grids():
    rng = np.random.default_rng(0)
    env = MazeEnv("maze", 1, seed=0)
    checked = {True: 0, False: 0}
    for _ in range(150):
        size = int(rng.integers(5, 9))
        walls = rng.random((size, size)) < rng.uniform(0.1, 0.5)
        walls[[0, -1], :] = True
        walls[:, [0, -1]] = True
        free = np.argwhere(~walls)
        if len(free) < 2:
            continue
        (gy, gx), (ay, ax) = free[rng.choice(len(free), 2, replace=False)]
        direction = int(rng.integers(0, 4))
        levels = MazeLevels(walls[None], np.array([[gx, gy]]), np.array([[ax, ay]]), np.array([direction], np.int8))
        actions, path = brute_force(walls, (gx, gy), (ax, ay), direction)
        solver = optimal_returns(levels)[0]
        checked[actions is not None] += 1
        if actions is None:
            assert solver == 0.0
            continue
        assert solver == pytest.approx(best(actions))
        # Played in the env, the optimal actions earn exactly that return.
        env.reset(levels)
        for action in path:
            _, reward, terminated, _, _ = env.step(np.array([action]))
        assert terminated[0] and reward[0] == pytest.approx(solver, abs=1e-6)
    assert min(checked.values()) >= 10  # both reachable and unreachable goals were tested
