"""Tests of envs.py: scenarios, collision truth, kinematics, step semantics, episode files."""
import math

import numpy as np
import pytest

import envs
from envs import PlanarReacher, load_episodes, make_env, median_step, save_episodes


@pytest.fixture(scope="module")
def env():
    e = make_env("planar")
    e.reset(seed=e.eval_seeds()[0])
    return e


def empty_env(obstacles=()):
    """An env whose scene is replaced by hand-built obstacles (N, 5)."""
    e = PlanarReacher()
    e.reset(seed=0)
    e.set_scene(obstacles)
    return e


# ---- scenarios -----------------------------------------------------------------------------------
def test_reset_is_deterministic_and_seeds_differ():
    a, b = make_env("planar"), make_env("planar")
    obs_a, info_a = a.reset(seed=123)
    obs_b, info_b = b.reset(seed=123)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(a.obstacles, b.obstacles)
    np.testing.assert_array_equal(info_a["q"], info_b["q"])
    obs_c, _ = b.reset(seed=124)
    assert not np.array_equal(obs_a, obs_c)


@pytest.mark.parametrize("seed", [0, 1, 2, 10_000, 10_050])
def test_scene_start_is_free_and_goal_has_free_configuration(seed):
    e = make_env("planar")
    _, info = e.reset(seed=seed)
    assert not e.in_collision(info["q"])
    assert not e.goal_reached(info["q"])
    goal_q = e.goal_configurations()
    assert len(goal_q) > 0
    assert np.all(e.goal_reached(goal_q)) and not np.any(e.in_collision(goal_q))
    lo, hi = e.joint_limits
    assert np.all(goal_q >= lo) and np.all(goal_q <= hi)


def test_seed_ranges_are_disjoint():
    e = make_env("planar")
    ev = e.eval_seeds()
    assert len(ev) == 100 and len(set(ev)) == 100
    tr = e.train_seeds(10_000)
    assert not set(tr) & set(ev)
    assert e.train_seeds(3, start=5) == [5, 6, 7]
    with pytest.raises(ValueError, match="train_seeds"):
        e.train_seeds(10, start=9_995)
    assert envs.eval_seeds() == ev and envs.train_seeds(2) == [0, 1]
    assert make_env("planar", max_steps=7).max_steps == 7


# ---- kinematics ----------------------------------------------------------------------------------
def test_fk_at_known_angles(env):
    l1, l2, l3 = env.link_lengths
    pts = env.fk(np.zeros(3))
    np.testing.assert_allclose(pts, [[0, 0], [l1, 0], [l1 + l2, 0], [l1 + l2 + l3, 0]], atol=1e-12)
    pts = env.fk(np.array([math.pi / 2, -math.pi / 2, math.pi / 2]))
    np.testing.assert_allclose(pts, [[0, 0], [0, l1], [l2, l1], [l2, l1 + l3]], atol=1e-12)
    np.testing.assert_allclose(env.ee(np.array([math.pi, 0, 0])), [-(l1 + l2 + l3), 0], atol=1e-12)
    batch = np.array([[0, 0, 0], [math.pi, 0, 0]])
    assert env.fk(batch).shape == (2, 4, 2)


def test_goal_reached_uses_tolerance(env):
    goal_q = env.goal_configurations()[0]
    assert env.goal_reached(goal_q)
    # rotate the base joint until the end effector is just outside / inside the tolerance
    reach = np.linalg.norm(env.ee(goal_q) - env.base)
    inside = goal_q + [0.9 * env.goal_tolerance / reach, 0, 0]
    outside = goal_q + [1.1 * env.goal_tolerance / reach, 0, 0]
    assert env.goal_reached(inside) and not env.goal_reached(outside)


# ---- collision truth -----------------------------------------------------------------------------
def test_link_crossing_a_thin_wall_collides():
    # a long thin wall at x = 0.5 crossing the straight arm (which reaches x = 0.9)
    e = empty_env([[0.5, -0.4, 0.5, 0.4, 0.001]])
    assert e.in_collision(np.zeros(3))
    assert e.pymunk_in_collision(np.zeros(3))
    # pointing the other way: clear
    assert not e.in_collision(np.array([math.pi, 0, 0]))


def test_touching_within_radius_and_clear_by_a_hair():
    r = PlanarReacher().link_radius
    obs_r = 0.02
    for eps, expected in [(-1e-6, True), (1e-6, False)]:
        # disc above the straight arm's link 1, surface distance eps from the link surface
        e = empty_env([[0.5, r + obs_r + eps, 0.5, r + obs_r + eps, obs_r]])
        assert e.in_collision(np.zeros(3)) == expected
        assert e.pymunk_in_collision(np.zeros(3)) == expected
        # a capsule beyond the end effector tip (x = 0.9), end to end. It is tilted a little:
        # for exactly collinear capsules pymunk's GJK reports a zero-depth contact at any overlap.
        tip = float(e.link_lengths.sum())
        e = empty_env([[tip + r + obs_r + eps, 0.0, tip + 0.3, 0.05, obs_r]])
        assert e.in_collision(np.zeros(3)) == expected
        assert e.pymunk_in_collision(np.zeros(3)) == expected


def test_margin_inflates_every_capsule_pair():
    r = PlanarReacher().link_radius
    gap = 0.01  # surface gap between link 1 and a disc above it
    e = empty_env([[0.5, r + 0.02 + gap, 0.5, r + 0.02 + gap, 0.02]])
    q = np.zeros(3)
    assert not e.in_collision(q)
    assert not e.in_collision(q, margin=0.9 * gap) and e.in_collision(q, margin=1.1 * gap)
    # self-collision: a folded arm whose link 2 is clear of link 0: margin just below / above the clearance
    e = empty_env()
    lo_q = np.array([0.0, 2.5, 1.0])  # less folded: clear of link 0
    assert not e.in_collision(lo_q)
    pts = e.fk(lo_q)
    d = math.sqrt(envs.segment_distance_sq(*pts[0], *(pts[1] - pts[0]), *pts[2], *(pts[3] - pts[2])))
    clearance = d - 2 * r
    assert clearance > 0
    assert not e.in_collision(lo_q, margin=0.99 * clearance)
    assert e.in_collision(lo_q, margin=1.01 * clearance)
    # a random batch: margin never removes collisions, and agrees with looped calls
    e.reset(seed=10_001)
    lo, hi = e.joint_limits
    qs = np.random.default_rng(0).uniform(lo, hi, size=(500, 3))
    assert np.all(e.in_collision(qs, margin=0.02) >= e.in_collision(qs))
    assert e.in_collision(qs, margin=0.02).sum() > e.in_collision(qs).sum()
    with pytest.raises(ValueError, match="margin"):
        e.in_collision(qs, margin=-0.1)


def test_self_collision_of_non_adjacent_links_only():
    e = empty_env()
    # fold link 2 back over link 0: q1 = 2.5, q2 = 2.5 -> link 2 points back across link 0
    folded = np.array([0.0, 2.5, 2.5])
    pts = e.fk(folded)
    d = np.sqrt(envs.segment_distance_sq(*pts[0], *(pts[1] - pts[0]), *pts[2], *(pts[3] - pts[2])))
    assert d < 2 * e.link_radius  # the geometry really overlaps
    assert e.in_collision(folded) and e.pymunk_in_collision(folded)
    # adjacent links always touch at their joint, and a sharp elbow alone is not a collision
    elbow = np.array([0.0, 2.5, 0.0])
    assert not e.in_collision(elbow) and not e.pymunk_in_collision(elbow)


def test_segment_distance_cases():
    d = lambda a, u, b, v: float(np.sqrt(envs.segment_distance_sq(*a, *u, *b, *v)))
    assert d((0, 0), (1, 0), (0.5, -1), (0, 2)) == 0.0  # crossing
    assert d((0, 0), (1, 0), (2, 1), (0, 0)) == pytest.approx(math.sqrt(2))  # point, endpoint
    assert d((0, 0), (1, 0), (0.3, 0.5), (0.4, 0)) == pytest.approx(0.5)  # parallel
    assert d((0, 0), (1, 0), (0.5, 0.2), (0, 1)) == pytest.approx(0.2)  # T shape, not crossing
    assert d((0, 0), (1, 0), (2, 0), (1, 0)) == pytest.approx(1.0)  # collinear, apart


@pytest.mark.parametrize("seed", [10_000, 10_001, 10_002, 3])
def test_numpy_and_pymunk_agree_on_random_configurations(seed):
    e = make_env("planar")
    e.reset(seed=seed)
    lo, hi = e.joint_limits
    q = np.random.default_rng(seed).uniform(lo, hi, size=(3000, 3))
    numpy_says = e.in_collision(q)
    pymunk_says = e.pymunk_in_collision(q)
    assert 0.1 < numpy_says.mean() < 0.9  # both outcomes well represented
    np.testing.assert_array_equal(numpy_says, pymunk_says)


def test_numpy_and_pymunk_agree_at_the_contact_boundary():
    # Bisect between free and colliding random configurations to points on the contact boundary,
    # then step 1e-9 rad to either side: both checks must give the same answer there.
    e = make_env("planar")
    rng = np.random.default_rng(7)
    lo, hi = e.joint_limits
    n_points = 0
    for seed in (10_004, 10_005):
        e.reset(seed=seed)
        qa, qb = rng.uniform(lo, hi, size=(2, 250, 3))
        differ = e.in_collision(qa) != e.in_collision(qb)
        a, b = qa[differ], qb[differ]
        t0, t1 = np.zeros(len(a)), np.ones(len(a))  # in_collision(a + t0 d) == in_collision(a)
        start = e.in_collision(a)
        for _ in range(45):
            tm = 0.5 * (t0 + t1)
            same = e.in_collision(a + tm[:, None] * (b - a)) == start
            t0, t1 = np.where(same, tm, t0), np.where(same, t1, tm)
        step = 1e-9 / np.linalg.norm(b - a, axis=1)
        for t in (t0 - step, t1 + step):
            q = a + t[:, None] * (b - a)
            np.testing.assert_array_equal(e.in_collision(q), e.pymunk_in_collision(q))
        assert np.all(e.in_collision(a + (t1 + step)[:, None] * (b - a)) != start)
        n_points += len(a)
    assert n_points > 100


def test_batched_equals_looped(env):
    lo, hi = env.joint_limits
    q = np.random.default_rng(1).uniform(lo, hi, size=(200, 3))
    looped = np.array([env.in_collision(qi) for qi in q])
    np.testing.assert_array_equal(env.in_collision(q), looped)
    np.testing.assert_allclose(env.fk(q), np.stack([env.fk(qi) for qi in q]))
    np.testing.assert_array_equal(env.goal_reached(q), [env.goal_reached(qi) for qi in q])
    np.testing.assert_array_equal(env.make_obs(q, q[::-1]),
                                  np.stack([env.make_obs(a, b) for a, b in zip(q, q[::-1])]))


# ---- stepping ------------------------------------------------------------------------------------
def test_step_speed_limit_and_joint_limit_clipping():
    e = empty_env()
    lo, hi = e.joint_limits
    e.set_state(np.array([0.0, 0.0, 0.0]))
    _, _, _, _, info = e.step(np.array([1.0, -0.01, 0.0]))
    np.testing.assert_allclose(e.q, [e.max_step, -0.01, 0.0])
    np.testing.assert_allclose(e.q_prev, [0.0, 0.0, 0.0])
    assert not info["collision"] and e.step_count == 1
    # a target beyond the joint limit is clipped at the limit
    e.set_state(np.array([0.0, hi[1] - 0.01, 0.0]))
    e.step(np.array([0.0, 100.0, 0.0]))
    assert e.q[1] == hi[1]


def test_step_terminates_on_success_and_collision_and_truncates():
    e = make_env("planar")
    e.reset(seed=10_000)
    goal_qs = e.goal_configurations()
    # a goal configuration whose neighbourhood is free too
    goal_q = next(g for g in goal_qs if not e.in_collision(g + [0.01, 0.0, 0.0]))
    e.set_state(goal_q + [0.01, 0.0, 0.0])
    _, reward, terminated, truncated, info = e.step(goal_q)
    assert info["success"] and terminated and not truncated and reward == 1.0
    # collision: walk into a wall
    w = empty_env([[0.5, -0.4, 0.5, 0.4, 0.02]])
    w.set_state(np.array([0.5, 0.0, 0.0]))
    for _ in range(100):
        _, _, terminated, truncated, info = w.step(np.array([-0.5, 0.0, 0.0]))
        if terminated:
            break
    assert info["collision"] and terminated and not info["success"]
    # truncation at max_steps, counted from set_state
    w = empty_env()
    w.set_state(np.array([math.pi, 0.0, 0.0]), step_count=w.max_steps - 1)
    _, _, terminated, truncated, info = w.step(np.array([math.pi, 0.0, 0.0]))
    assert truncated and not terminated


def test_step_checks_states_inside_the_step():
    # A small disc just beyond the tip of the straight arm: swinging joint 0 from -0.025 to
    # +0.025 rad passes it (collision at the middle) while both end states are clear. (Slightly
    # off the arm's axis: pymunk's GJK reports zero-depth contacts for exactly collinear capsules.)
    tip = float(PlanarReacher().link_lengths.sum())
    r = PlanarReacher().link_radius
    x = tip + r + 0.005 - 0.001
    e = empty_env([[x, 0.001, x, 0.001, 0.005]])
    q0, q1 = np.array([-0.025, 0.0, 0.0]), np.array([0.025, 0.0, 0.0])
    assert not e.in_collision(q0) and not e.in_collision(q1)
    assert e.in_collision(0.5 * (q0 + q1))
    e.set_state(q0)
    _, _, terminated, _, info = e.step(q1)
    assert info["collision"] and terminated


def test_bad_input_raises(env):
    env.reset(seed=10_000)
    for bad, word in [(np.array([np.nan, 0, 0]), "finite"), (np.array([0, np.inf, 0]), "finite"),
                      (np.zeros(2), "shape"), (np.zeros((1, 3)), "shape")]:
        with pytest.raises(ValueError, match=word):
            env.step(bad)
    with pytest.raises(ValueError, match="shape"):
        env.in_collision(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="finite"):
        env.set_state(np.array([0, np.nan, 0]))
    with pytest.raises(ValueError, match="joint limits"):
        env.set_state(np.array([0, 3.0, 0]))
    with pytest.raises(ValueError, match="unknown environment"):
        make_env("nope")
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=-1)


def test_make_obs_layout(env):
    env.reset(seed=10_001)
    q, q_prev = np.array([0.1, 0.2, 0.3]), np.array([0.4, 0.5, 0.6])
    obs = env.make_obs(q, q_prev)
    assert obs.shape == (env.obs_dim,) and obs.dtype == np.float32
    np.testing.assert_allclose(obs[:3], q, rtol=1e-6)
    np.testing.assert_allclose(obs[3:6], q_prev, rtol=1e-6)
    np.testing.assert_allclose(obs[6:8], env.goal, rtol=1e-6)
    n = len(env.obstacles)
    slots = obs[8:].reshape(-1, 5)
    np.testing.assert_allclose(slots[:n], env.obstacles, rtol=1e-6)
    assert np.all(slots[n:] == 0)
    # reset's observation = make_obs at the start with q_prev = q
    obs0, info = env.reset(seed=10_001)
    np.testing.assert_array_equal(obs0, env.make_obs(info["q"], info["q"]))


# ---- episode files -------------------------------------------------------------------------------
def test_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    episodes = []
    for i, T in enumerate([5, 1, 12]):
        episodes.append({"obs": rng.normal(size=(T, 48)).astype(np.float32),
                         "q": rng.normal(size=(T, 3)), "action": rng.normal(size=(T, 3)),
                         "expert": rng.random(T) < 0.5, "seed": 100 + i, "success": bool(i % 2),
                         "goal": rng.normal(size=2)})
    path = tmp_path / "eps.npz"
    save_episodes(path, episodes)
    back = load_episodes(path)
    assert len(back) == 3
    for a, b in zip(episodes, back):
        assert set(a) == set(b)
        for k in ("obs", "q", "action", "expert"):
            np.testing.assert_array_equal(a[k], b[k])
            assert a[k].dtype == b[k].dtype
        assert b["seed"] == a["seed"] and isinstance(b["seed"], int)
        assert b["success"] == a["success"] and isinstance(b["success"], bool)
        np.testing.assert_array_equal(a["goal"], b["goal"])
    with pytest.raises(ValueError, match="missing"):
        save_episodes(path, [episodes[0], {"q": np.zeros((2, 3))}])
    with pytest.raises(FileNotFoundError):
        load_episodes(tmp_path / "missing.npz")


def test_median_step_ignores_zero_motion():
    q = np.array([[0, 0, 0], [0.1, 0, 0.2], [0.1, 0, 0.5], [0.1, 0, 0.5]], dtype=float)
    # nonzero |diffs|: 0.1, 0.2, 0.3 -> median 0.2
    assert median_step([{"q": q}]) == pytest.approx(0.2)
    with pytest.raises(ValueError):
        median_step([{"q": np.zeros((4, 3))}])


# ---- scene construction and drawing --------------------------------------------------------------
def test_generated_obstacles_stay_out_of_link0_disc():
    # an obstacle inside the disc link 0 sweeps would cut joint 0's range in two (unsolvable scenes)
    e = make_env("planar")
    keep_out = e.link_lengths[0] + e.link_radius + e.cfg.base_clearance
    for seed in range(10_000, 10_020):
        e.reset(seed=seed)
        assert 3 <= len(e.obstacles) <= e.cfg.n_max_obstacles
        for x0, y0, x1, y1, rad in e.obstacles:
            d = np.array([x1 - x0, y1 - y0])
            dist = math.sqrt(envs._point_segment_dist_sq(0.0, 0.0, x0, y0, *d, 1 / max(d @ d, 1e-300)))
            assert dist - rad >= keep_out - 1e-12


def test_set_scene_validates_and_feeds_both_checks():
    e = PlanarReacher()
    with pytest.raises(ValueError, match="n_max_obstacles"):
        e.set_scene(np.zeros((e.cfg.n_max_obstacles + 1, 5)))
    with pytest.raises(ValueError, match="radius"):
        e.set_scene([[0, 0, 1, 1, -0.1]])
    e.set_scene([[0.6, -0.1, 0.6, 0.1, 0.02]], goal=[0.0, 0.8])
    np.testing.assert_array_equal(e.goal, [0.0, 0.8])
    assert e.in_collision(np.zeros(3)) and e.pymunk_in_collision(np.zeros(3))
    with pytest.raises(ValueError, match="before reset"):
        e.step(np.zeros(3))


def test_render_draws_scene_and_arms():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = make_env("planar")
    e.reset(seed=10_003)
    fig, ax = plt.subplots()
    e.render(ax)
    n_scene = len(ax.patches)
    assert n_scene == len(e.obstacles) + 1 + e.dof  # obstacles, goal disc, 3 links
    e.render(ax, q=np.zeros((4, 3)), alpha=0.3, show_scene=False)
    assert len(ax.patches) == n_scene + 4 * e.dof
    # a link polygon spans the link length plus both radii
    xy = ax.patches[-1].get_xy()
    assert np.ptp(xy[:, 0]) == pytest.approx(e.link_lengths[2] + 2 * e.link_radius, abs=1e-9)
    plt.close(fig)
