"""Tests of EngineReach3D (experiment/engine3d.py): the UR5 engine-lever reaching env (paper Sec. V, Table II).

FK against hand-computed DH poses, closed-form IK round trips, collision truth on hand-built
configurations, pybullet (the simulator) vs the vectorized numpy check, scenario determinism,
batched == looped, step semantics, drawing, bad input; the scene (the authors' small-engine cell)
and its random starts.
"""
import math

import numpy as np
import pytest

from experiment.environments import make_env
from experiment.engine3d import (ENGINE_SELF_PAIRS, UR5_A, UR5_D, EngineConfig, EngineReach3D, segment_distance_3d,
                                 dh_transform, ur5_frames, ur5_ik)

D1, D4, D5, D6 = UR5_D[0], UR5_D[3], UR5_D[4], UR5_D[5]
A2, A3 = UR5_A[1], UR5_A[2]
TOOL = EngineConfig().tool_length


@pytest.fixture(scope="module")
def env():
    return EngineReach3D()


@pytest.fixture(scope="module")
def scene_env():
    e = EngineReach3D()
    e.reset(seed=e.eval_seeds()[0])
    return e


def clearance(env, q):
    """The reference of env.in_collision: signed distance (B,) in m from the arm at q to everything it may not
    touch (negative: penetration), every pair, no broad phase: arm capsules vs obstacle capsules (segment distance
    minus the two radii), ENGINE_SELF_PAIRS, the forearm .. fingers vs the ground z = 0, every capsule vs the wall."""
    a0, a1 = env._arm_components(np.atleast_2d(q))  # (3, B, 8) each
    r, (i, j) = env.link_radii, ENGINE_SELF_PAIRS.T
    d = (segment_distance_3d(a0[:, :, i], a1[:, :, i], a0[:, :, j], a1[:, :, j]) - r[i] - r[j]).min(axis=1)
    d = np.minimum(d, env._ground_clearance(a0, a1))
    d = np.minimum(d, env._wall_clearance(a0, a1))
    if len(env.obstacles):
        g = env._geom
        dist = segment_distance_3d(a0[..., None], a1[..., None], g["start"][:, None, None],
                                   g["end"][:, None, None])  # (B, 8, N)
        d = np.minimum(d, (dist - g["contact"]).min(axis=(1, 2)))
    return d if np.ndim(q) > 1 else d[0]


# ---- kinematics ----------------------------------------------------------------------------------
def flange(q):
    return ur5_frames(np.atleast_2d(q))[:, 6, :3, 3]


def test_fk_zero_pose_matches_hand_computed_dh(env):
    # zero pose: upper arm and forearm along -x at shoulder height d1, wrist 1 offset -d4 along y,
    # wrist 2 down by d5, flange -d6 along y (the well-known UR5 zero-pose flange position)
    expected = np.array([
        [0, 0, 0], [0, 0, D1], [A2, 0, D1], [A2 + A3, 0, D1], [A2 + A3, -D4, D1],
        [A2 + A3, -D4, D1 - D5], [A2 + A3, -D4 - D6 - TOOL, D1 - D5]])
    np.testing.assert_allclose(env.fk(np.zeros(6)), expected, atol=1e-12)
    np.testing.assert_allclose(flange(np.zeros(6))[0], [-0.81725, -0.19145, -0.005491], atol=1e-12)


def test_fk_hand_computed_poses(env):
    # base turned by 90 deg: the zero-pose flange rotated about z
    q = np.array([math.pi / 2, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(flange(q)[0], [D4 + D6, A2 + A3, D1 - D5], atol=1e-12)
    np.testing.assert_allclose(env.ee(q), [D4 + D6 + TOOL, A2 + A3, D1 - D5], atol=1e-12)
    # upright "home" (0, -pi/2, 0, -pi/2, 0, 0): arm straight up, wrist 2 on top
    q = np.array([0, -math.pi / 2, 0, -math.pi / 2, 0, 0])
    np.testing.assert_allclose(flange(q)[0], [0, -D4 - D6, D1 - A2 - A3 + D5], atol=1e-12)
    # elbow bent down by pi/2: forearm points to -z, wrist 2 (q2+q3+q4 = pi/2) along +x
    q = np.array([0, 0, math.pi / 2, 0, 0, 0])
    np.testing.assert_allclose(flange(q)[0], [A2 + D5, -D4 - D6, D1 + A3], atol=1e-12)


def test_fk_planar_chain_formula_at_random_angles(env):
    # with q1 = q5 = 0 the shoulder, elbow and wrist move in the x-z plane (angles q2, q2 + q3,
    # q2 + q3 + q4) and the flange axis z5 = z6 stays along -y: every point has a closed form
    rng = np.random.default_rng(0)
    q = np.zeros((50, 6))
    q[:, 1:4] = rng.uniform(-3, 3, size=(50, 3))
    q[:, 5] = rng.uniform(-3, 3, size=50)  # joint 6 turns about z6: no point moves
    q2, q23, q234 = q[:, 1], q[:, 1] + q[:, 2], q[:, 1] + q[:, 2] + q[:, 3]
    elbow = np.stack([A2 * np.cos(q2), 0 * q2, D1 + A2 * np.sin(q2)], axis=1)
    wrist1 = elbow + np.stack([A3 * np.cos(q23), 0 * q2, A3 * np.sin(q23)], axis=1)
    wrist2 = wrist1 + [0, -D4, 0]
    wrist3 = wrist2 + D5 * np.stack([np.sin(q234), 0 * q2, -np.cos(q234)], axis=1)
    points = env.fk(q)
    for k, expected in zip((2, 3, 4, 5, 6), (elbow, wrist1, wrist2, wrist3, wrist3 + [0, -D6 - TOOL, 0])):
        np.testing.assert_allclose(points[:, k], expected, atol=1e-12)
    np.testing.assert_allclose(flange(q), wrist3 + [0, -D6, 0], atol=1e-12)


def test_dh_transform_is_rz_tz_tx_rx():
    """The standard DH link transform is Rz(theta) Tz(d) Tx(a) Rx(alpha), composed here from the four elementary
    matrices at random parameters (batched). Fails on a sign, a swapped sin/cos or an entry in the wrong place."""
    def rot(axis, t):
        c, s = np.cos(t), np.sin(t)
        R = np.eye(4)
        i, j = {"z": (0, 1), "x": (1, 2)}[axis]
        R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
        return R

    def move(axis, x):
        T = np.eye(4)
        T["xz".index(axis) * 2, 3] = x
        return T

    rng = np.random.default_rng(3)
    theta, d, a, alpha = rng.uniform(-3, 3, (4, 5))
    got = dh_transform(theta, d, a, alpha)
    assert got.shape == (5, 4, 4)
    for i in range(5):
        want = rot("z", theta[i]) @ move("z", d[i]) @ move("x", a[i]) @ rot("x", alpha[i])
        np.testing.assert_allclose(got[i], want, atol=1e-12)


def test_fast_fk_equals_the_dh_chain_at_random_angles(env):
    # env.fk / link_segments write the DH chain out point by point; ur5_frames multiplies the
    # 4x4 DH transforms: the same kinematics
    rng = np.random.default_rng(8)
    q = rng.uniform(-4, 4, size=(500, 6))
    frames = ur5_frames(q)
    assert frames.shape == (500, 7, 4, 4)  # base and frames 1..6: no frame past the flange (an uninitialized one)
    points = env.fk(q)
    np.testing.assert_allclose(points[:, :6], frames[:, :6, :3, 3], atol=1e-12)
    np.testing.assert_allclose(points[:, 6], frames[:, 6, :3, 3] + TOOL * frames[:, 6, :3, 2], atol=1e-12)
    finger_bar = env.link_segments(q)[:, 7]  # (B, 2, 3), along x6 through the probe axis
    np.testing.assert_allclose(np.cross(finger_bar[:, 1] - finger_bar[:, 0], frames[:, 6, :3, 0]), 0, atol=1e-12)


def test_no_arm_point_is_farther_from_a_joint_than_the_fk_chain_beyond_it(env):
    # the lever-arm bound planners derive from fk (oracle.lever_arms): the fingers included
    rng = np.random.default_rng(7)
    q = rng.uniform(*env.joint_limits, size=(5000, 6))
    points = env.fk(q)  # (B, 7, 3)
    chain = np.linalg.norm(np.diff(points, axis=1), axis=-1)  # (B, 6), constant per row
    beyond = np.cumsum(chain[:, ::-1], axis=1)[:, ::-1]  # (B, 6) chain length beyond joint j
    seg = env.link_segments(q)  # (B, 8, 2, 3)
    for j in range(6):
        ends = seg[:, j + 1:].reshape(len(q), -1, 3)  # every capsule end beyond joint j
        dist = np.linalg.norm(ends - points[:, j:j + 1], axis=-1).max(axis=1)
        assert np.all(dist <= beyond[:, j] + 1e-12), j


def test_closed_form_ik_recovers_the_configuration_and_the_pose():
    rng = np.random.default_rng(1)
    q = rng.uniform(-math.pi, math.pi, size=(300, 6))
    pose = ur5_frames(q)[:, 6]
    solutions = ur5_ik(pose)  # (300, 8, 6)
    valid = ~np.isnan(solutions[..., 0])
    assert valid.sum(axis=1).min() >= 2  # every reachable pose has several branches
    reached = ur5_frames(np.nan_to_num(solutions.reshape(-1, 6)))[:, 6].reshape(300, 8, 4, 4)
    assert np.abs(reached - pose[:, None])[valid].max() < 1e-10
    wrapped = (solutions - q[:, None] + math.pi) % (2 * math.pi) - math.pi
    assert np.all(np.nanmin(np.abs(wrapped).max(axis=2), axis=1) < 1e-9)  # q itself is a branch


def test_goal_configurations_reach_the_goal_collision_free(scene_env):
    goal_q = scene_env.goal_configurations()
    assert len(goal_q) >= scene_env.cfg.min_goal_configurations
    np.testing.assert_allclose(scene_env.ee(goal_q), np.broadcast_to(scene_env.goal, (len(goal_q), 3)), atol=1e-9)
    assert not scene_env.in_collision(goal_q).any()
    lo, hi = scene_env.joint_limits
    assert np.all((goal_q >= lo) & (goal_q <= hi))


# ---- collision truth -----------------------------------------------------------------------------
def test_segment_distance_hand_cases():
    def dist(a0, a1, b0, b1):
        return float(segment_distance_3d(*(np.asarray(p, dtype=float)[:, None] for p in (a0, a1, b0, b1)))[0])
    assert dist([0, 0, 0], [1, 0, 0], [0.5, -1, 1], [0.5, 1, 1]) == pytest.approx(1.0)  # skew, 1 apart
    assert dist([0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]) == pytest.approx(1.0)  # collinear gap
    assert dist([0, 0, 0], [1, 0, 0], [0, 0.3, 0], [1, 0.3, 0]) == pytest.approx(0.3)  # parallel
    assert dist([0, 0, 0], [1, 0, 0], [0.5, -1, 0], [0.5, 1, 0]) == pytest.approx(0.0)  # crossing
    assert dist([0, 0, 0], [0, 0, 0], [3, 4, 0], [3, 4, 0]) == pytest.approx(5.0)  # two points


def test_collision_truth_on_hand_built_configurations():
    env = EngineReach3D()
    env.set_scene(np.zeros((0, 7)))
    upright = np.array([0, -math.pi / 2, 0, -math.pi / 2, 0, 0])
    assert not env.in_collision(upright)
    assert env.in_collision(np.zeros(6))  # zero pose: wrist 2 / 3 dip below the table (z = -0.005)
    # wrist 3 folded back onto the forearm (q5 near pi turns z5 from -y to +y): self-collision
    assert env.in_collision(np.array([0, 0, 0, math.pi / 2, 3.0, 0]))
    assert not env.in_collision(np.array([0, 0, 0, math.pi / 2, 0.0, 0]))  # the same, unfolded
    # a pipe along x beside the upright forearm (the z axis, radius 0.05): 0.05 + 0.03 = contact
    for offset, expected in ((0.08 + 1e-6, False), (0.08 - 1e-6, True), (0.0, True), (0.2, False)):
        env.set_scene([[-0.3, offset, 0.7, 0.3, offset, 0.7, 0.03]])
        assert env.in_collision(upright) == expected, offset
        assert env.pybullet_in_collision(upright) == expected, offset


def test_left_out_self_pairs_can_never_touch(env):
    # the wrist pairs left out of ENGINE_SELF_PAIRS are held apart by the DH offsets
    rng = np.random.default_rng(2)
    q = rng.uniform(*env.joint_limits, size=(20000, 6))
    seg = env.link_segments(q)  # (B, 8, 2, 3)
    checked = {tuple(p) for p in ENGINE_SELF_PAIRS.tolist()}
    left_out = [(i, j) for i in range(8) for j in range(i + 2, 8) if (i, j) not in checked]
    assert len(left_out) == 6
    r = env.link_radii
    for i, j in left_out:
        d = segment_distance_3d(*(np.moveaxis(seg[:, k, e], -1, 0) for k, e in ((i, 0), (i, 1), (j, 0), (j, 1))))
        assert d.min() - r[i] - r[j] > 0.004, (i, j)


def test_in_collision_equals_exact_clearance_with_margins(scene_env):
    rng = np.random.default_rng(3)
    q = rng.uniform(*scene_env.joint_limits, size=(5000, 6))
    clearance_q = clearance(scene_env, q)
    for margin in (0.0, 0.01, 0.03):
        np.testing.assert_array_equal(scene_env.in_collision(q, margin=margin), clearance_q < margin)


def test_pybullet_agrees_with_numpy_on_random_configurations():
    env = EngineReach3D()
    rng = np.random.default_rng(4)
    n_hit = 0
    for seed in env.eval_seeds()[:3]:
        env.reset(seed=seed)
        q = rng.uniform(*env.joint_limits, size=(1000, 6))
        numpy_hit = env.in_collision(q)
        np.testing.assert_array_equal(env.pybullet_in_collision(q), numpy_hit)
        n_hit += numpy_hit.sum()
    assert 0.2 * 3000 < n_hit < 0.8 * 3000  # both outcomes well represented


def test_pybullet_agrees_with_numpy_at_the_contact_boundary(scene_env):
    # bisection between free and colliding configurations finds points on the contact boundary;
    # 1e-6 rad on either side (arm motion <= 1.3e-6 m) the two checks must still agree
    rng = np.random.default_rng(5)
    q = rng.uniform(*scene_env.joint_limits, size=(400, 6))
    hit = scene_env.in_collision(q)
    free, coll = q[~hit][:60], q[hit][:60]
    lo, hi = np.zeros(60), np.ones(60)
    for _ in range(45):
        mid = 0.5 * (lo + hi)
        mid_hit = scene_env.in_collision(free + mid[:, None] * (coll - free))
        hi = np.where(mid_hit, mid, hi)
        lo = np.where(mid_hit, lo, mid)
    step = 1e-6 / np.abs(coll - free).max(axis=1)  # 1e-6 rad on the fastest joint
    outside = free + (lo - step)[:, None] * (coll - free)
    inside = free + (hi + step)[:, None] * (coll - free)
    assert not scene_env.in_collision(outside).any() and scene_env.in_collision(inside).all()
    assert not scene_env.pybullet_in_collision(outside).any()
    assert scene_env.pybullet_in_collision(inside).all()


# ---- scenarios -----------------------------------------------------------------------------------
def test_reset_is_deterministic_and_seeds_differ():
    a, b = EngineReach3D(), EngineReach3D()
    obs_a, info_a = a.reset(seed=10_003)
    obs_b, info_b = b.reset(seed=10_003)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(a.obstacles, b.obstacles)
    np.testing.assert_array_equal(info_a["goal"], info_b["goal"])
    a.reset(seed=10_004)
    assert not np.array_equal(a.obstacles[:, :6], b.obstacles[:, :6])
    assert obs_a.dtype == np.float32 and obs_a.shape == (a.obs_dim,)


def test_authors_scene_is_one_engine_and_lever_with_two_boxes_drawn_per_seed():
    env = EngineReach3D()
    goal_q = np.asarray(env.cfg.goal_q)
    fixed, boxes = None, []
    for seed in env.eval_seeds()[:8]:
        env.reset(seed=seed)
        kinds = np.array(env.obstacle_kinds)
        assert list(kinds) == ["engine", "engine", "lever", "lever", "box", "box"]
        if fixed is None:
            fixed = env.obstacles[kinds != "box"].copy()
        np.testing.assert_array_equal(env.obstacles[kinds != "box"], fixed)  # engine, lever: fixed
        np.testing.assert_array_equal(env.witness, goal_q)
        np.testing.assert_allclose(env.goal, env.ee(goal_q), atol=1e-12)  # the goal: TCP of their q_goal_bias
        assert not env.in_collision(goal_q) and not env.in_collision(env.q)
        box = env.obstacles[kinds == "box"]  # (2, 7), capsules lying on the table
        np.testing.assert_allclose(box[:, 2], box[:, 6])
        np.testing.assert_allclose(box[:, 5], box[:, 6])
        centre = 0.5 * (box[:, :3] + box[:, 3:6])
        for i in range(2):
            assert env.cfg.box_x[i][0] <= centre[i, 0] <= env.cfg.box_x[i][1]
            assert env.cfg.box_y[i][0] <= centre[i, 1] <= env.cfg.box_y[i][1]
        boxes.append(box)
    assert len({b.tobytes() for b in boxes}) == len(boxes)  # the boxes move from seed to seed
    # the goal is near the engine: the tool points at it and the lever handle sits just beyond the TCP
    assert 0.0 < clearance(env, goal_q) < 0.06


def test_the_wall_is_a_half_space_in_numpy_and_pybullet():
    env = EngineReach3D()
    env.set_scene(np.zeros((0, 7)), goal=[0.2, -0.4, 0.2])
    upright = np.array([0, -math.pi / 2, 0, -math.pi / 2, 0, 0])  # forearm up along z, at y = d4
    # turning the shoulder (q1) swings the lateral offset d4 (and wrist 2 / 3) toward +y, the wall
    q1 = np.linspace(-math.pi, math.pi, 721)
    q = np.tile(upright, (len(q1), 1))
    q[:, 0] = q1
    seg = env.link_segments(q)  # (B, 8, 2, 3)
    expected = (env.cfg.wall_y - seg[..., 1].max(axis=2) - env.link_radii).min(axis=1)
    free = EngineReach3D(EngineConfig(wall_y=100.0))  # the wall 100 m away: only the ground and the arm
    free.set_scene(np.zeros((0, 7)))
    np.testing.assert_allclose(clearance(env, q), np.minimum(expected, clearance(free, q)), atol=1e-12)
    hit = env.in_collision(q)
    assert hit.any() and (~hit).any()  # some shoulder angles reach the wall, others do not
    np.testing.assert_array_equal(hit, expected < 0)  # nothing else is near in this empty scene
    np.testing.assert_array_equal(env.pybullet_in_collision(q), hit)
    assert not free.in_collision(q).any()  # without the wall nothing collides


def test_starts_are_clear_far_from_the_goal_and_spread_over_the_joint_limits():
    env = EngineReach3D()
    starts = []
    for seed in env.train_seeds(12):
        env.reset(seed=seed)
        assert not env.in_collision(env.q, margin=env.cfg.start_clearance)
        assert np.linalg.norm(env.ee(env.q) - env.goal) >= env.cfg.start_goal_min_dist
        starts.append(env.q)
    assert np.array(starts).std(axis=0).max() > 1.0  # the authors' starts: uniform within the limits


def test_make_env_builds_the_engine_env_with_config_fields():
    env = make_env("engine3d", max_steps=50)
    assert isinstance(env, EngineReach3D) and env.max_steps == 50
    assert make_env("engine3d").max_steps == 333  # the authors' 1000 frames at 30 Hz, at 10 Hz
    assert env.dof == 6 and env.obs_dim == 2 * 6 + 3 + 7 * env.cfg.n_max_obstacles


def test_seed_ranges_are_disjoint(env):
    assert len(env.eval_seeds()) == 100
    assert not set(env.eval_seeds()) & set(env.train_seeds(500))


# ---- batched == looped ---------------------------------------------------------------------------
def test_batched_equals_looped(scene_env):
    rng = np.random.default_rng(6)
    q = rng.uniform(*scene_env.joint_limits, size=(40, 6))
    q_prev = q + rng.normal(scale=0.01, size=q.shape)
    for fn in (scene_env.fk, scene_env.ee, scene_env.in_collision, scene_env.goal_reached):
        batched = fn(q)
        np.testing.assert_array_equal(batched, np.stack([fn(qi) for qi in q]))
    np.testing.assert_array_equal(scene_env.make_obs(q, q_prev),
                                  np.stack([scene_env.make_obs(a, b) for a, b in zip(q, q_prev)]))


def test_make_obs_layout(scene_env):
    """The docstring's layout: q, q_prev, the goal, then n_max_obstacles slots of 7 numbers, the absent ones zero
    (make_obs; its first part, _joint_goal_obs, is shared with the image variant, tests/test_image_obs.py)."""
    q = np.stack([scene_env.q, scene_env.witness])
    q_prev = q - 0.01
    obs = scene_env.make_obs(q, q_prev)
    assert obs.shape == (2, 127) and obs.dtype == np.float32
    np.testing.assert_array_equal(obs[:, :6], q.astype(np.float32))
    np.testing.assert_array_equal(obs[:, 6:12], q_prev.astype(np.float32))
    np.testing.assert_array_equal(obs[:, 12:15], np.tile(scene_env.goal, (2, 1)).astype(np.float32))
    slots, n = obs[0, 15:].reshape(scene_env.cfg.n_max_obstacles, 7), len(scene_env.obstacles)
    np.testing.assert_array_equal(slots[:n], scene_env.obstacles.astype(np.float32))
    assert n > 0 and not slots[n:].any()
    np.testing.assert_array_equal(scene_env.make_obs(q[1], q_prev[1]), obs[1])  # (dof,) -> (obs_dim,)


# ---- stepping ------------------------------------------------------------------------------------
def test_step_speed_limit_joint_limits_and_q_prev():
    env = EngineReach3D()
    env.reset(seed=10_000)
    q0 = env.q
    obs, reward, terminated, truncated, info = env.step(q0 + np.array([1.0, -1.0, 0.01, 0, 0, 0]))
    np.testing.assert_allclose(env.q - q0, [0.05, -0.05, 0.01, 0, 0, 0], atol=1e-12)
    np.testing.assert_array_equal(env.q_prev, q0)
    np.testing.assert_array_equal(obs[6:12], q0.astype(np.float32))
    assert info["step"] == 1 and reward == 0.0
    lo, hi = env.joint_limits
    env.set_state(np.array([0, -0.02, 1.0, -1.0, -1.0, 0]))
    env.step(np.array([0, 5.0, 1.0, -1.0, -1.0, 0]))  # shoulder target beyond its limit 0
    assert env.q[1] == hi[1]


def test_step_terminates_on_collision_success_and_truncates():
    env = EngineReach3D(EngineConfig(max_steps=3))
    env.reset(seed=10_001)
    goal_q = env.goal_configurations()[0]
    env.set_state(goal_q + np.array([0.03, 0, 0, 0, 0, 0]))
    _, reward, terminated, truncated, info = env.step(goal_q)
    assert info["success"] and terminated and not truncated and reward == 1.0
    # drive into an obstacle: a pipe placed across the arm's next configuration
    env.set_state(env.witness)
    target = env.witness + 0.05
    seg = env.link_segments(target)[0, 2]  # the forearm at the target
    mid = seg.mean(axis=0)
    env.set_scene(np.concatenate([env.obstacles, [[*(mid - [0, 0, 0.2]), *(mid + [0, 0, 0.2]), 0.02]]]),
                  kinds=env.obstacle_kinds + ["pipe"])
    _, _, terminated, truncated, info = env.step(target)
    assert info["collision"] and terminated and not info["success"]
    env.reset(seed=10_001)
    for _ in range(3):
        _, _, terminated, truncated, info = env.step(env.q)  # stand still
    assert truncated and not terminated and info["step"] == 3


# ---- drawing --------------------------------------------------------------------------------------
def test_render_scene_image_writes_a_png(scene_env, tmp_path):
    from experiment.engine3d import render_scene_image
    path = tmp_path / "scene.png"
    image = render_scene_image(scene_env, path, q=scene_env.witness, width=80, height=60)
    assert image.shape == (60, 80, 3) and path.stat().st_size > 1000


def test_render_draws_the_camera_image(scene_env):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots()
    scene_env.render(ax, q=np.stack([scene_env.witness, scene_env.q]))  # a batch: the first configuration
    assert len(ax.images) == 1 and ax.images[0].get_array().shape == (360, 480, 3)
    plt.close(fig)
