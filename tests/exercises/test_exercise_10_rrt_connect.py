"""Exercise 10: RRT-Connect's EXTEND and CONNECT steps (oracle.rrt_connect; paper Sec. V, the RRT
oracle expert). A point robot in the unit square: a wall with a narrow gap blocks the straight line."""
import numpy as np
import pytest

from oracle import PlanningFailed, path_in_collision, rrt_connect

LIMITS = (np.zeros(2), np.ones(2))
RES = 0.005                                        # edge-check spacing (rad here: the unit square)


def wall_with_gap(q):
    """(B, 2) -> (B,) True inside the wall 0.45 <= x <= 0.55, except the gap 0.80 <= y <= 0.88."""
    q = np.atleast_2d(q)
    in_wall = (q[:, 0] >= 0.45) & (q[:, 0] <= 0.55)
    return in_wall & ~((q[:, 1] >= 0.80) & (q[:, 1] <= 0.88))


def box_around(center, half=0.08, wall=0.02):
    """Collides on a square ring around `center`: a goal inside is free but unreachable."""
    def in_collision(q):
        d = np.abs(np.atleast_2d(q) - center).max(axis=1)
        return wall_with_gap(q) | ((d >= half) & (d <= half + wall))
    return in_collision


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_path_through_the_gap_is_free_and_made_of_short_steps(seed):
    start, goal = np.array([0.1, 0.1]), np.array([0.9, 0.1])
    step = 0.1
    path = rrt_connect(start, goal[None], wall_with_gap, LIMITS, np.random.default_rng(seed),
                       step_size=step, resolution=RES, max_iters=3000, max_time=60.0)
    assert np.array_equal(path[0], start) and np.array_equal(path[-1], goal)
    assert not path_in_collision(path, wall_with_gap, RES)
    assert np.all(np.linalg.norm(np.diff(path, axis=0), axis=1) <= step + 1e-9)   # tree edges: <= one step
    assert path[:, 1].max() >= 0.75                                                # detoured up to the gap
    again = rrt_connect(start, goal[None], wall_with_gap, LIMITS, np.random.default_rng(seed),
                        step_size=step, resolution=RES, max_iters=3000, max_time=60.0)
    assert np.array_equal(path, again)                                             # deterministic given the rng


def test_several_goal_roots_reach_the_reachable_one():
    start = np.array([0.1, 0.1])
    goals = np.array([[0.8, 0.3], [0.8, 0.5]])                    # the first is boxed in
    in_collision = box_around(goals[0])
    path = rrt_connect(start, goals, in_collision, LIMITS, np.random.default_rng(3), step_size=0.1,
                       resolution=RES, max_iters=3000, max_time=60.0)
    assert np.array_equal(path[-1], goals[1]) and not path_in_collision(path, in_collision, RES)


def test_an_unreachable_goal_exhausts_the_budget():
    center = np.array([0.8, 0.3])
    with pytest.raises(PlanningFailed):
        rrt_connect(np.array([0.1, 0.1]), center[None], box_around(center), LIMITS,
                    np.random.default_rng(0), step_size=0.1, resolution=RES, max_iters=200, max_time=60.0)
