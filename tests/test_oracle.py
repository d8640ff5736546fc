"""Tests of oracle.py: planner properties on toy collision functions (test doubles defined here),
then the Oracle on envs.PlanarReacher (demonstrations, determinism, gating, interventions)."""
import math
import re
import time

import numpy as np
import pytest

import envs
from experiment import engine3d, environments  # noqa: F401
import oracle
from oracle import (Oracle, OracleConfig, PlanningFailed, edge_free_fraction, edge_resolution,
                    lever_arms, path_in_collision, rrt_connect, shortcut, smooth_corners, solve_ik,
                    time_parameterize)

DT = 0.1
V_MAX = 0.5
A_MAX = V_MAX / (4 * DT)
J_MAX = A_MAX / (2 * DT)
LIMITS_2D = (np.array([-2.0, -2.0]), np.array([2.0, 2.0]))
H = 20  # the policy's chunk (dagger.Config.horizon)


def make_oracle(**options):
    """Oracle(OracleConfig) with the given options."""
    return Oracle(OracleConfig(**options))


# ---- toy collision functions (test doubles) --------------------------------------------------
def wall_with_gap(q, margin=0.0):
    """2-D: a wall |x| < 0.1 with a gap 0.5 < y < 0.7, inflated by `margin`."""
    q = np.atleast_2d(q)
    return (np.abs(q[:, 0]) < 0.1 + margin) & ~((q[:, 1] > 0.5 + margin) & (q[:, 1] < 0.7 - margin))


def inflated_wall(q):
    """The wall inflated by half the planner's check spacing (0.02): no graze between checks
    (oracle.py's edge checks explain why planning needs this margin)."""
    return wall_with_gap(q, margin=0.01)


def ring(q, centre=(1.0, 1.0)):
    """2-D: a closed annulus 0.3 < |q - centre| < 0.5 (its inside is unreachable from outside)."""
    d = np.linalg.norm(np.atleast_2d(q) - np.asarray(centre), axis=1)
    return (d > 0.3) & (d < 0.5)


def balls_3d(q, margin=0.0):
    """3-D: two balls of radius 0.4 (+ margin) at (0, 0, 0) and (0.8, 0.8, 0)."""
    q = np.atleast_2d(q)
    return ((np.linalg.norm(q, axis=1) < 0.4 + margin)
            | (np.linalg.norm(q - np.array([0.8, 0.8, 0.0]), axis=1) < 0.4 + margin))


def finite_differences(samples, v0, dt=DT, at_rest=True):
    """Velocity, acceleration, jerk at every sample as the env sees them: sample -1 = q0 - v0 dt
    (constant velocity before), and (if at_rest) at rest after the last sample."""
    rest = np.zeros((2 if at_rest else 0, samples.shape[1]))
    vel = np.concatenate([v0[None], v0[None], np.diff(samples, axis=0) / dt, rest])
    acc = np.diff(vel, axis=0) / dt
    return vel, acc, np.diff(acc, axis=0) / dt


def assert_limits(samples, v0, v_max=V_MAX, a_max=A_MAX, j_max=J_MAX, dt=DT, at_rest=True):
    vel, acc, jerk = finite_differences(samples, v0, dt, at_rest)
    tol = 1 + 1e-9
    assert np.all(np.abs(vel) <= v_max * tol), np.abs(vel).max()
    assert np.all(np.abs(acc) <= a_max * tol), np.abs(acc).max()
    assert np.all(np.abs(jerk) <= j_max * tol), np.abs(jerk).max()


# ---- geometry --------------------------------------------------------------------------------
def test_lever_arms_and_resolution_bound_point_motion():
    env = envs.make_env("planar")
    # the finger corners reach past the chain points: 0.10 + 0.07 + 0.08 m along link 3, 0.0525 across
    np.testing.assert_allclose(lever_arms(env), [0.55, 0.25, 0.0] + np.hypot(0.25, 0.0525))
    res = edge_resolution(env, 0.01)
    rng = np.random.default_rng(0)
    q = rng.uniform(*env.joint_limits, size=(2000, env.dof))
    dq = rng.normal(size=(2000, env.dof))
    dq /= np.sum(np.abs(dq) / res, axis=1, keepdims=True)  # exactly one check step apart

    def body_points(q):  # every box corner of every arm part, (B, 24, 2)
        xs, ys = envs.box_corners(*env.part_boxes(q))
        return np.stack([np.concatenate(xs).T, np.concatenate(ys).T], axis=-1)
    moved = np.linalg.norm(body_points(q + dq) - body_points(q), axis=-1).max()
    assert moved <= 0.01 + 1e-12  # the lever-arm bound holds for every point of the arm
    assert moved > 0.005  # and is not absurdly loose


def test_edge_free_fraction_finds_first_collision():
    start = np.array([[-1.0, 0.0], [-1.0, 0.6]])
    end = np.array([[1.0, 0.0], [1.0, 0.6]])
    free = edge_free_fraction(start, end, wall_with_gap, 0.01)
    assert free[1] == 1.0  # through the gap
    assert 0.43 < free[0] < 0.46  # the wall starts at x = -0.1, i.e. 45 % of the way


def test_early_exit_checks_agree_with_checking_every_state():
    rng = np.random.default_rng(0)
    q_from = rng.uniform(-1.5, 1.5, (300, 2))
    q_to = -q_from + rng.normal(0, 0.3, (300, 2))  # most cross x = 0: the wall or its gap
    states, edge, k, n = oracle.interpolate_edges(q_from, q_to, 0.01)
    hit = wall_with_gap(states)
    first_hit = np.full(len(n), np.inf)
    np.minimum.at(first_hit, edge[hit], k[hit])  # reference: every state checked
    expected = (np.minimum(first_hit, n + 1) - 1) / n
    np.testing.assert_array_equal(edge_free_fraction(q_from, q_to, wall_with_gap, 0.01), expected)
    np.testing.assert_array_equal(oracle.edges_free(q_from, q_to, wall_with_gap, 0.01),
                                  expected == 1.0)
    assert 0 < np.mean(expected == 1.0) < 1  # both kinds of edges were tested
    # and early exit does skip states: count the configurations checked
    checked = []
    counting = lambda q: checked.append(len(q)) or wall_with_gap(q)  # noqa: E731
    edge_free_fraction(q_from, q_to, counting, 0.01)
    assert sum(checked) < 0.75 * len(states)  # the wall is mid-edge: about half is past it


def test_with_margin_uses_the_env_margin_except_in_relax_zones():
    env = envs.make_env("planar")
    env.reset(seed=env.eval_seeds()[2])
    q = np.random.default_rng(0).uniform(*env.joint_limits, size=(4000, env.dof))
    plain, true_margin = env.in_collision(q), env.in_collision(q, margin=0.02)
    assert true_margin.sum() > plain.sum()  # the margin does inflate
    native = oracle.with_margin(env, 0.02)(q)
    np.testing.assert_array_equal(native, true_margin)  # the env's own margin is used if offered
    relaxed = oracle.with_margin(env, 0.02, relax_at=q[:10], relax_radius=1e-9)(q)
    np.testing.assert_array_equal(relaxed[:10], plain[:10])  # plain check inside the zones
    np.testing.assert_array_equal(relaxed[10:], true_margin[10:])


# ---- RRT-Connect, shortcut, corners ----------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rrt_connect_path_is_collision_free_under_denser_check(seed):
    rng = np.random.default_rng(seed)
    path = rrt_connect(np.array([-1.0, -1.0]), np.array([[1.0, -1.0]]), inflated_wall, LIMITS_2D,
                       rng, step_size=0.3, resolution=0.02)
    np.testing.assert_array_equal(path[0], [-1.0, -1.0])
    np.testing.assert_array_equal(path[-1], [1.0, -1.0])
    assert not path_in_collision(path, wall_with_gap, 0.002)  # 10x denser than the planner
    assert np.all(path >= LIMITS_2D[0]) and np.all(path <= LIMITS_2D[1])


def test_rrt_connect_3d_with_several_goals_reaches_a_free_one():
    goals = np.array([[0.0, 0.0, 0.0],  # inside a ball: must be ignored
                      [1.5, 1.5, 0.5], [0.8, 0.8, 0.8]])
    path = rrt_connect(np.array([-1.0, -1.0, 0.0]), goals, lambda q: balls_3d(q, 0.01),
                       (np.full(3, -2.0), np.full(3, 2.0)), np.random.default_rng(0),
                       resolution=0.02)
    assert any(np.array_equal(path[-1], g) for g in goals[1:])
    assert not path_in_collision(path, balls_3d, 0.002)
    # a one-state path: only its state is checked
    assert path_in_collision(goals[:1], balls_3d, 0.002) and not path_in_collision(path[:1], balls_3d, 0.002)


def test_rrt_connect_fails_cleanly_on_a_closed_ring():
    # the goal is free but enclosed by the ring: no path exists; the iteration budget ends it
    with pytest.raises(PlanningFailed) as info:
        rrt_connect(np.array([-1.0, -1.0]), np.array([[1.0, 1.0]]), ring, LIMITS_2D,
                    np.random.default_rng(0), resolution=0.02, max_iters=50)
    assert "max_iters=50" in info.value.reason
    # and the time budget ends it even with an enormous iteration budget
    t0 = time.perf_counter()
    with pytest.raises(PlanningFailed, match="time budget"):
        rrt_connect(np.array([-1.0, -1.0]), np.array([[1.0, 1.0]]), ring, LIMITS_2D,
                    np.random.default_rng(0), resolution=0.02, max_iters=10 ** 9, max_time=0.3)
    assert time.perf_counter() - t0 < 0.3 + 5.0  # one iteration of slack (loaded CI machine)


def test_rrt_connect_rejects_bad_input_and_colliding_start():
    with pytest.raises(ValueError, match="q_goals"):
        rrt_connect(np.zeros(2), np.zeros((1, 3)), ring, LIMITS_2D, np.random.default_rng(0))
    with pytest.raises(PlanningFailed, match="start"):
        rrt_connect(np.array([0.0, 0.0]), np.array([[1.0, -1.0]]), wall_with_gap, LIMITS_2D,
                    np.random.default_rng(0))


def test_shortcut_shortens_and_stays_free():
    rng = np.random.default_rng(3)
    path = rrt_connect(np.array([-1.0, -1.0]), np.array([[1.0, -1.0]]), inflated_wall, LIMITS_2D,
                       rng, step_size=0.2, resolution=0.02)
    short = shortcut(path, inflated_wall, np.random.default_rng(0), iters=64, resolution=0.02)
    length = lambda p: np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))  # noqa: E731
    assert length(short) <= length(path) + 1e-12
    assert len(short) <= len(path)
    np.testing.assert_array_equal(short[[0, -1]], path[[0, -1]])
    assert not path_in_collision(short, wall_with_gap, 0.002)
    # the shortest path goes through the gap: about 2 * sqrt(1^2 + 1.5^2) = 3.6
    assert length(short) < 4.2


class FixedDraws:
    """Test double of np.random.Generator for shortcut: uniform(low, high, size) returns low + (high - low) * u
    for fixed fractions u (batch, 2), so the proposals' arc positions are known."""

    def __init__(self, u):
        self.u = np.asarray(u, dtype=np.float64)

    def uniform(self, low, high, size):
        assert size == self.u.shape
        return low + (high - low) * self.u


def test_shortcut_applies_the_free_proposal_that_saves_most_at_its_exact_points():
    """Fails if shortcut's random phase puts a proposal's points anywhere but at their arc positions on the path
    (the interpolation t = (s - cum[seg]) / (cum[seg + 1] - cum[seg])), draws them over less than the whole path
    (cum[-1]), or ranks proposals by anything but the length they save (arc - chord): a U path around a wall
    (greedy keeps every corner) and five known proposals -- same edge, blocked by the wall (the largest saving),
    a long one along the first edge that saves little, one at the far corner that saves little, and the free one
    that saves most, at corner B: it is the one applied, with its points exactly 0.3 before and after B."""
    def wall(q):  # the open box -1 < x < 1.9, 0.3 < y < 1.7: the path goes around its right side
        x, y = np.atleast_2d(q).T
        return (x > -1.0) & (x < 1.9) & (y > 0.3) & (y < 1.7)
    A, B, C, D = [0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]        # arc positions 0, 2, 4, 6
    path = np.array([A, B, C, D])
    arcs = np.array([[0.5, 1.5],     # both on edge AB: nothing to cut
                     [1.0, 3.0],     # (1, 0) -> (2, 1): through the wall, saves 2 - sqrt(2) = 0.59
                     [0.0, 2.05],    # A -> (2, 0.05): free, saves 2.05 - sqrt(4.0025) = 0.05
                     [3.9, 4.1],     # (2, 1.9) -> (1.9, 2): free, saves 0.2 - 0.1 sqrt(2) = 0.06
                     [1.7, 2.3]])    # (1.7, 0) -> (2, 0.3): free, saves 0.6 - 0.3 sqrt(2) = 0.18
    short = shortcut(path, wall, FixedDraws(arcs / 6.0), iters=5, resolution=0.01, batch=5)
    np.testing.assert_allclose(short, [A, [1.7, 0.0], [2.0, 0.3], C, D], atol=1e-12)
    # without a free proposal that saves length, the greedy pass's path is returned as it is
    unchanged = shortcut(path, wall, FixedDraws(arcs[:2] / 6.0), iters=2, resolution=0.01, batch=2)
    np.testing.assert_array_equal(unchanged, path)


def test_smooth_corners_rounds_free_corners_and_keeps_blocked_ones():
    path = np.array([[0.0, -1.0], [0.0, 0.0], [1.0, 0.0]])
    free = lambda q: np.zeros(len(np.atleast_2d(q)), bool)  # noqa: E731
    inside = lambda q: (np.atleast_2d(q)[:, 0] > 1e-3) & (np.atleast_2d(q)[:, 1] < -1e-3)  # noqa: E731
    rounded = smooth_corners(path, free, resolution=0.01)
    assert len(rounded) > len(path)
    assert not np.any(np.all(rounded == [0.0, 0.0], axis=1))  # the sharp corner is gone
    turn = np.diff(np.arctan2(*np.diff(rounded, axis=0).T[::-1]))
    assert np.abs(turn).max() < math.pi / 4  # direction changes gradually
    kept = smooth_corners(path, inside, resolution=0.01)  # rounding cuts into the obstacle
    np.testing.assert_array_equal(kept, path)
    assert not path_in_collision(kept, inside, 0.001)


# ---- time parameterization -------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
def test_time_parameterize_limits_at_every_sample_and_handoff(seed):
    rng = np.random.default_rng(seed)
    path = np.cumsum(rng.uniform(-1, 1, (6, 3)), axis=0)
    v0 = rng.uniform(-V_MAX, V_MAX, 3) if seed % 2 else np.zeros(3)
    samples = time_parameterize(path, V_MAX, A_MAX, J_MAX, DT, v0=v0)
    np.testing.assert_array_equal(samples[0], path[0])
    np.testing.assert_allclose(samples[-1], path[-1], atol=1e-12)  # ends on the goal ...
    assert_limits(samples, v0)  # ... at rest (limits hold with zero velocity after it)
    # handoff: from a constant-velocity history, the first step's velocity differs from v0 by
    # at most one step of maximal jerk
    assert np.all(np.abs((samples[1] - samples[0]) / DT - v0) <= J_MAX * DT ** 2 * (1 + 1e-9))


def test_time_parameterize_straight_line_is_near_time_optimal():
    path = np.array([[0.0, 0.0, 0.0], [2.0, -1.0, 0.5]])
    samples = time_parameterize(path, V_MAX, A_MAX, J_MAX, DT)
    duration = (len(samples) - 1) * DT
    # any rest-to-rest move: joint 0 travels 2 rad at |v| <= V_MAX, |a| <= A_MAX, a trapezoid of D/v + v/a
    bound = 2.0 / V_MAX + V_MAX / A_MAX
    assert bound <= duration <= 1.1 * bound


def test_time_parameterize_repairs_corner_cuts_that_collide():
    path = np.array([[0.0, -1.0], [0.0, 0.0], [1.0, 0.0]])
    inside = lambda q: (np.atleast_2d(q)[:, 0] > 0.01) & (np.atleast_2d(q)[:, 1] < -0.01)  # noqa: E731
    fast = time_parameterize(path, V_MAX, A_MAX, J_MAX, DT)
    assert path_in_collision(fast, inside, 0.001)  # the filter cuts the corner ...
    safe = time_parameterize(path, V_MAX, A_MAX, J_MAX, DT, in_collision=inside, resolution=0.005)
    assert not path_in_collision(safe, inside, 0.0005)  # ... unless slowed down there
    assert_limits(safe, np.zeros(2))
    assert len(safe) > len(fast)


def test_time_parameterize_gives_up_at_the_speed_floor_and_says_how_slow_it_went():
    """A path that crosses an obstacle cannot be repaired by slowing down: the repairs slow the pieces around the
    crossing until one is under min_speed_factor of full speed, then PlanningFailed says the slowest piece's
    factor. Fails if the message reports another piece's factor (min -> max gives 1: the far pieces never slow)
    or if the loop stops before the floor."""
    path = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    wall = lambda q: np.abs(np.atleast_2d(q)[:, 0] - 1.5) < 0.05  # noqa: E731  (across the middle piece)
    with pytest.raises(PlanningFailed, match="of full speed") as info:
        time_parameterize(path, V_MAX, A_MAX, J_MAX, DT, in_collision=wall, resolution=0.005,
                          min_speed_factor=1e-2)
    slowest = float(re.search(r"slowing down to ([0-9.e-]+) of full speed", str(info.value)).group(1))
    assert 1e-2 * 0.7 <= slowest < 1e-2  # one repair (factor 0.7) past the floor, not a piece at full speed


def test_time_parameterize_rejects_bad_input():
    with pytest.raises(ValueError, match="v0"):
        time_parameterize(np.zeros((2, 2)), V_MAX, A_MAX, J_MAX, DT, v0=np.array([1.0, 0.0]))
    with pytest.raises(ValueError, match="a_max"):
        time_parameterize(np.zeros((2, 2)), V_MAX, -1.0, J_MAX, DT)


# ---- the Oracle on the planar env -------------------------------------------------------------
@pytest.fixture(scope="module")
def env():
    return envs.make_env("planar")


@pytest.fixture(scope="module")
def demo(env):
    seed = env.eval_seeds()[0]
    return make_oracle().demonstrate(env, seed)


def test_solve_ik_reaches_goal_and_is_collision_free(env):
    env.reset(seed=env.eval_seeds()[1])
    goals = solve_ik(env, env.goal, np.random.default_rng(0), 8, q_start=env.q, n_seeds=256)
    assert 1 <= len(goals) <= 8
    assert np.all(np.linalg.norm(env.ee(goals) - env.goal, axis=1) <= 1e-3)
    assert not env.in_collision(goals).any()
    lo, hi = env.joint_limits
    assert np.all(goals >= lo) and np.all(goals <= hi)
    gaps = np.abs(goals[:, None] - goals[None]).max(-1) + np.eye(len(goals)) * 9
    assert gaps.min() > 0.2  # deduplicated


def test_demonstrate_gives_a_valid_successful_expert_episode(env, demo):
    T = len(demo["q"])
    assert demo["success"] and demo["seed"] == env.eval_seeds()[0]
    assert demo["obs"].shape == (T, env.obs_dim) and demo["obs"].dtype == np.float32
    assert demo["q"].shape == demo["action"].shape == (T, env.dof)
    assert demo["expert"].dtype == bool and demo["expert"].all()
    # actions are reachable targets: the env follows them exactly (no speed clipping)
    np.testing.assert_allclose(demo["q"][1:], demo["action"][:-1], atol=1e-12)
    assert np.abs(demo["action"] - demo["q"]).max() <= env.max_step * (1 + 1e-9)
    visited = np.concatenate([demo["q"], demo["action"][-1:]])
    assert env.goal_reached(visited[-1:])[0]
    v_max, a_max, j_max = make_oracle().limits(env)
    # the env ends the episode on reaching the goal, possibly before the plan has come to rest
    assert_limits(visited, np.zeros(env.dof), v_max, a_max, j_max, env.dt, at_rest=False)
    # collision-free under a check 10x denser than the planner's
    res = edge_resolution(env, 0.1 * make_oracle().sweep(env))
    assert not path_in_collision(visited, env.in_collision, res)


def test_demonstrate_is_deterministic(env, demo):
    again = make_oracle().demonstrate(env, env.eval_seeds()[0])
    for key in ("q", "action", "obs"):
        np.testing.assert_array_equal(again[key], demo[key])


def test_plan_fails_cleanly_when_the_goal_is_walled_off(env):
    # a block in link 1's way at angle 0 and the shoulder's +-pi limit wall the arm off from every
    # goal configuration (they all need the shoulder up): the search must give up, not hang
    env.reset(seed=env.eval_seeds()[0])
    env.set_scene([[0.25, 0.0, 0.035, 0.035, 0.0]], goal=[0.0, 0.45])
    q_start = np.array([-math.pi / 2, 0.0, 0.0])
    assert not env.in_collision(q_start) and np.all(env.goal_configurations()[:, 0] > 0)
    t0 = time.perf_counter()
    with pytest.raises(PlanningFailed):
        make_oracle(max_iters=50).plan(env, q_start, None, np.random.default_rng(0))
    assert time.perf_counter() - t0 < 30.0  # returned, did not hang


def test_gate_triggers_on_collision_and_stall_not_on_safe_progress(env, demo):
    oracle_ = make_oracle(gate_lookahead=None)  # the whole pending chunk
    env.reset(seed=demo["seed"])
    gate = oracle_.gate(env)
    # safe, progressing: the expert's own next H targets after half the demo was driven
    for t in range(len(demo["q"]) // 2):
        env.step(demo["action"][t])
        gate.record(env)
    t = len(demo["q"]) // 2
    assert gate.should_intervene(env, demo["action"][t:t + H]) is None
    # a chunk that drives into an obstacle
    rng = np.random.default_rng(0)
    box = rng.uniform(-H * env.max_step, H * env.max_step, size=(5000, env.dof)) + env.q
    target = box[env.in_collision(box)][0]
    chunk = env.q + np.linspace(0, 1, H + 1)[1:, None] * (target - env.q)
    assert gate.should_intervene(env, chunk) == "collision"
    # holding still for the stall window: no progress
    hold = np.repeat(env.q[None], H, axis=0)
    assert gate.should_intervene(env, hold) is None  # not stalled yet
    for _ in range(oracle_.cfg.stall_window + 1):
        env.step(env.q)
        gate.record(env)
    assert gate.should_intervene(env, hold) == "stall"


def test_intervention_matches_handoff_velocity_and_hands_back_safely(env, demo):
    oracle_ = make_oracle()
    plans = []  # the Plans the interventions make
    oracle_.plan = lambda *args, plan=oracle_.plan: plans.append(plan(*args)) or plans[-1]
    t = 20  # mid-motion: the expert moves at speed here
    env.reset(seed=demo["seed"])
    env.set_state(demo["q"][t], demo["q"][t - 1])
    v0 = (demo["q"][t] - demo["q"][t - 1]) / env.dt
    assert np.abs(v0).max() > 0.5 * env.max_step / env.dt
    actions = oracle_.intervention(env)
    assert len(actions) >= H  # dagger drops interventions shorter than H
    again = oracle_.intervention(env)
    np.testing.assert_array_equal(actions, again)  # same state -> same plan
    traj = np.concatenate([env.q[None], actions])
    v_max, a_max, j_max = oracle_.limits(env)
    vel = np.diff(traj, axis=0) / env.dt
    assert np.abs(vel).max() <= v_max.max() * (1 + 1e-9)
    acc = np.diff(np.concatenate([v0[None], v0[None], vel]), axis=0) / env.dt
    assert np.abs(acc).max() <= a_max.max() * (1 + 1e-9)
    assert np.abs(np.diff(acc, axis=0)).max() / env.dt <= j_max.max() * (1 + 1e-9)
    # the first step continues the policy's motion (velocity matched up to one jerk step)
    assert np.all(np.abs(vel[0] - v0) <= j_max * env.dt ** 2 * (1 + 1e-9))
    for a in actions:
        _, _, terminated, _, info = env.step(a)
        assert not info["collision"]
        if terminated:
            break
    lo, hi = oracle_.cfg.handback_steps  # the authors' random hand-back (benchmarks/SETUP.md §3) ...
    assert lo <= len(actions) <= hi or len(actions) == len(plans[-1].samples) - 1  # ... or the whole plan


def test_gate_looks_gate_lookahead_steps_ahead_at_gate_clearance(env):
    """A straight chunk that first comes within gate_clearance of a collision at step j triggers the gate
    iff j <= gate_lookahead."""
    rng = np.random.default_rng(1)
    for seed in env.eval_seeds()[:20]:
        env.reset(seed=int(seed))
        for _ in range(200):
            d = rng.normal(size=env.dof)
            chunk = env.q + np.arange(1, 21)[:, None] * env.max_step * d / np.abs(d).max()  # (20, dof)
            lo, hi = env.joint_limits
            if np.any(chunk < lo) or np.any(chunk > hi):
                continue
            near = make_oracle(gate_lookahead=None)
            hit = [near.chunk_collides(env, chunk[:j]) for j in range(1, 21)]
            if not any(hit) or hit.index(True) + 1 <= 4:
                continue
            j = hit.index(True) + 1  # first prefix length that comes too close
            assert not make_oracle(gate_lookahead=j - 1).chunk_collides(env, chunk)
            assert make_oracle(gate_lookahead=j).chunk_collides(env, chunk)
            wide = make_oracle(gate_lookahead=None, gate_clearance=0.05)  # a wider band: sooner
            assert wide.chunk_collides(env, chunk[:j]) and any(wide.chunk_collides(env, chunk[:i]) for i in range(1, j))
            return
    raise AssertionError("no straight chunk that comes close to an obstacle after a few steps")


def test_gate_time_triggers_and_the_cap_on_interventions(env, demo):
    cfg = OracleConfig(time_trigger_first=5, time_trigger_every=(3, 3), max_interventions=2,
                       stall_window=1000, gate_lookahead=1)
    oracle_ = Oracle(cfg)
    env.reset(seed=demo["seed"])
    gate = oracle_.gate(env, np.random.default_rng(0))
    safe = demo["action"][:1]
    for t in range(4):
        env.step(demo["action"][t])
        gate.record(env)
        assert gate.should_intervene(env, demo["action"][t + 1:t + 2]) is None  # 1..4 policy steps
    env.step(demo["action"][4])
    gate.record(env)
    assert gate.should_intervene(env, demo["action"][5:6]) == "time"  # 5 policy steps
    gate.interventions += 1
    for t in range(5, 7):  # expert steps do not count toward the next time trigger
        env.step(demo["action"][t])
        gate.record(env, by_expert=True)
    for t in range(7, 9):
        env.step(demo["action"][t])
        gate.record(env)
        assert gate.should_intervene(env, demo["action"][t + 1:t + 2]) is None
    env.step(demo["action"][9])
    gate.record(env)
    assert gate.should_intervene(env, demo["action"][10:11]) == "time"  # 3 policy steps later
    gate.interventions += 1
    assert gate.should_intervene(env, demo["action"][10:11]) is None  # the cap: max_interventions taken
    lo, hi = cfg.rewind_steps
    assert all(lo <= gate.rewind_steps(1000) <= hi for _ in range(20)) and gate.rewind_steps(3) <= 3
    recorded = list(gate.distances)
    gate.rewound(2)  # the env was put back 2 steps: their distances are forgotten
    assert gate.distances == recorded[:-2]


@pytest.mark.parametrize("name, seed_index",
                         [("planar", 0), ("planar", 1), ("planar", 2), ("engine3d", 0)])
def test_planned_paths_keep_their_clearance_under_a_dense_recheck(name, seed_index):
    """The edge-validation argument (oracle.py's edge checks) on real scenes: checks spaced
    s = 2 (margin - verify_margin) apart under the planning margin leave every state of the
    path -- RRT-Connect's, then shortcut's, then smooth_corners' -- at least verify_margin
    clear, re-checked 100x more densely than the planner checks."""
    env = environments.make_env(name)
    expert = make_oracle()
    sweep = expert.sweep(env)
    margin, verify = expert.cfg.margin * sweep, expert.cfg.verify_margin * sweep
    resolution = edge_resolution(env, 2 * (margin - verify))
    collides = oracle.with_margin(env, margin)  # no relax zones: the argument holds everywhere
    rng = np.random.default_rng(seed_index)
    # the seed_index-th evaluation scene whose start is clear under the margin and whose path is no
    # straight line (random starts are often within a few mm of something)
    candidates = []
    for seed in env.eval_seeds():
        env.reset(seed=seed)
        goals = solve_ik(env, env.goal, np.random.default_rng(seed_index), 8, q_start=env.q, in_collision=collides)
        if len(goals) and not collides(env.q[None])[0] and oracle.edge_free_fraction(
                np.repeat(env.q[None], len(goals), 0), goals, collides, resolution).max() < 1.0:
            candidates.append(seed)
            if len(candidates) > seed_index:
                break
    env.reset(seed=candidates[seed_index])
    goals = solve_ik(env, env.goal, np.random.default_rng(seed_index), 8, q_start=env.q, in_collision=collides)
    clear = lambda q: env.in_collision(q, margin=0.999 * verify)  # noqa: E731
    dense = edge_resolution(env, 0.01 * 2 * (margin - verify))
    path = rrt_connect(env.q, goals, collides, env.joint_limits, rng, resolution=resolution)
    assert len(path) > 2  # a real search, not the straight line
    assert not path_in_collision(path, clear, dense)
    path = shortcut(path, collides, rng, resolution=resolution)
    assert not path_in_collision(path, clear, dense)
    path = smooth_corners(path, collides, resolution)
    assert not path_in_collision(path, clear, dense)


def test_plot_demonstration_writes_png(env, demo, tmp_path):
    out = tmp_path / "fig5_planar.png"
    oracle.plot_demonstration(env, demo, out)
    assert out.stat().st_size > 10_000
