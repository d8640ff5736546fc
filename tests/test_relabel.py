"""Tests for relabel.py (paper Sec. IV-E): PD return chunks, monotone projection, noised states,
the three noise models, the augmentation sampler and Fig. 1.

Most tests use FakeEnv, a small test double of the env interface of envs.py (joint-space ball
obstacles, planar 3-link forward kinematics), so they run in milliseconds and the collision region
is known exactly. The tests at the end run against the real envs.PlanarReacher and EngineReach3D.
"""
import io
from dataclasses import replace

import numpy as np
import pytest
import torch

import diffusion
import envs
from experiment import environments
from helpers import straight_line_episode  # tests/helpers.py
import relabel
from experiment import checkpoints

from relabel import (AugmentationSampler, ChunkSampler, MixtureSampler, RelabelConfig, corrective_labels,
                     covariance_factor, critically_damped_gains, demo_stats, monotone_projection,
                     noise_factors, pd_return_chunk, perturb_states)

DOF = 3
H = 16  # the label chunk's length in these tests


class FakeEnv:
    """Test double of the env interface: 3 joints, limits ±π, speed limit 0.05 rad/step. The
    obstacle is a ball in joint space (radius `radius`) whose centre depends on the scenario seed,
    so collision checks are exact and cheap. Links of length 1 for fk/ee; the Jacobian and the noise
    ellipses are the real envs' (the same maths on this fk)."""
    dof, obs_dim, max_step, max_steps, dt, dim = DOF, 2 * DOF + 2, 0.05, 200, 0.1, 2
    paper_median_step = max_parallel = None  # no paper unit; any number in lockstep
    ee_jacobian = envs.PlanarReacher.ee_jacobian
    make_obs_near = envs.ArmEnv.make_obs_near  # noised states' observations: make_obs at the new state
    draw_noise_ellipses = envs.PlanarReacher.draw_noise_ellipses
    square_view = envs.PlanarReacher.square_view

    def __init__(self, radius=0.1, center_fn=None):
        self.radius = radius
        self.center_fn = center_fn or (lambda seed: np.array([10.0, 10.0, 10.0]))  # far away: free
        self.reset_calls = 0

    @property
    def joint_limits(self):
        return np.full(DOF, -np.pi), np.full(DOF, np.pi)

    def reset(self, seed=None):
        self.reset_calls += 1
        self.seed = seed
        self.goal = np.array([np.cos(seed), np.sin(seed)])
        self.obstacle = np.asarray(self.center_fn(seed), dtype=np.float64)
        self.q = self.q_prev = np.zeros(DOF)
        return self.make_obs(self.q, self.q_prev), {"q": self.q, "goal": self.goal}

    def set_state(self, q, q_prev=None):
        self.q = np.asarray(q, dtype=np.float64)
        self.q_prev = self.q if q_prev is None else np.asarray(q_prev, dtype=np.float64)

    def in_collision(self, q):
        return np.linalg.norm(np.atleast_2d(q) - self.obstacle, axis=-1) < self.radius

    def make_obs(self, q, q_prev):
        q, q_prev = np.atleast_2d(q), np.atleast_2d(q_prev)
        goal = np.broadcast_to(self.goal, (len(q), 2))
        return np.concatenate([q, q_prev, goal], axis=1).astype(np.float32)

    def fk(self, q):
        ang = np.cumsum(np.atleast_2d(q), axis=1)  # (B, 3)
        pts = np.cumsum(np.stack([np.cos(ang), np.sin(ang)], axis=-1), axis=1)  # (B, 3, 2)
        return np.concatenate([np.zeros((len(ang), 1, 2)), pts], axis=1)

    def ee(self, q):
        return self.fk(q)[:, -1]

    def render(self, ax, q=None, alpha=1.0):
        pts = self.fk(self.q[None])[0]
        ax.plot(pts[:, 0], pts[:, 1], "k-o")


def smooth_trajectory(T=80, phase=0.0):
    """A gently curved joint path (per-step displacement ~0.02 rad, accelerations ~1e-4 rad/step²,
    far below the demos' clamp, so a PD return can track it exactly)."""
    s = np.arange(T, dtype=np.float64)
    return np.stack([0.02 * s, 0.3 * np.sin(0.02 * s + phase), -0.015 * s + 0.2 * np.cos(0.03 * s + phase)], axis=1)


def oracle_like_demo(seed, T=120, accel_limit=0.004, speed=0.03):
    """A demonstration shaped like a time-parameterized planner path: straight joint-space legs at
    cruise speed, a new direction every 25 steps, reached with accelerations of at most accel_limit."""
    rng = np.random.default_rng(seed)
    q, v, v_goal = np.zeros((T, DOF)), np.zeros(DOF), np.zeros(DOF)
    for t in range(1, T):
        if t % 25 == 1:
            d = rng.normal(size=DOF)
            v_goal = speed * d / np.abs(d).max()
        v = v + np.clip(v_goal - v, -accel_limit, accel_limit)
        q[t] = q[t - 1] + v
    return {"q": q, "action": np.concatenate([q[1:], q[-1:]]), "expert": np.ones(T, bool), "seed": seed}


def make_episode(seed=0, T=80, expert=None, phase=0.0):
    q = smooth_trajectory(T, phase)
    action = np.concatenate([q[1:], q[-1:]])
    if expert is None:
        expert = np.ones(T, dtype=bool)
    prev = np.concatenate([q[:1], q[:-1]])
    env = FakeEnv()
    env.reset(seed=seed)
    return {"obs": env.make_obs(q, prev), "q": q, "action": action, "expert": np.asarray(expert, bool), "seed": seed}


def intervention_episode(seed=0, T=80, phase=0.0):
    expert = np.zeros(T, dtype=bool)
    expert[10:60] = True  # one intervention of 50 steps
    return make_episode(seed, T, expert, phase)


@pytest.fixture
def stats():
    demos = [oracle_like_demo(s) for s in range(3)]
    steps = np.abs(np.diff(np.concatenate([d["q"] for d in demos]), axis=0))
    return demo_stats(demos, median_step=float(np.median(steps[steps > 0])), max_step=FakeEnv.max_step)


# ---------------------------------------------------------------- demo statistics, label steps

def test_demo_stats_match_hand_computation(stats):
    demos = [oracle_like_demo(s) for s in range(3)]
    acc = np.concatenate([np.abs(np.diff(d["q"], 2, axis=0)) for d in demos])
    np.testing.assert_allclose(stats.accel_max, np.percentile(acc, 99, axis=0))
    assert np.all((stats.accel_max > 0.003) & (stats.accel_max <= 0.004 + 1e-12))  # the planner's limit
    np.testing.assert_array_equal(stats.max_step, np.full(DOF, 0.05))


def test_label_steps_follow_the_label_rule():
    label_steps = relabel.paper_label_steps
    expert = np.array([0, 1, 1, 1, 1, 0, 1, 1, 1, 0, 1, 1], dtype=bool)
    t, seg_end = label_steps(expert, horizon=3)
    # run of 4 at 1..4 -> t = 1, 2 (need 3 steps); run of 3 at 6..8 -> t = 6;
    # run 10..11 is shorter than H: discarded although it reaches the episode end (Sec. IV-C)
    np.testing.assert_array_equal(t, [1, 2, 6])
    np.testing.assert_array_equal(seg_end, [5, 5, 9])
    # a run of at least H that reaches the end labels every step of it (padded chunks)
    t, seg_end = label_steps(np.array([0, 0, 1, 1, 1, 1], dtype=bool), horizon=3)
    np.testing.assert_array_equal(t, [2, 3, 4, 5])
    np.testing.assert_array_equal(seg_end, [6, 6, 6, 6])


# ---------------------------------------------------------------- monotone projection

def test_projection_finds_true_closest_point_on_a_line():
    traj = np.stack([np.linspace(0, 1, 11), np.zeros(11), np.zeros(11)], axis=1)
    q = np.array([[0.31, 0.2, 0.0], [0.96, -0.1, 0.05], [-0.5, 0.0, 0.0]])
    np.testing.assert_array_equal(monotone_projection(q, traj, 0), [3, 10, 0])
    assert monotone_projection(q[0], traj, 0) == 3  # single state -> int


def test_projection_never_goes_back_in_time():
    # a U-shaped path: out along x then back; q sits at the start, which the path revisits at the end
    out = np.stack([np.linspace(0, 1, 10), np.zeros(10), np.zeros(10)], axis=1)
    back = np.stack([np.linspace(1, 0.1, 10), 0.3 * np.ones(10), np.zeros(10)], axis=1)
    traj = np.concatenate([out, back])
    q = np.array([0.0, 0.0, 0.0])
    assert monotone_projection(q, traj, 0) == 0
    assert monotone_projection(q, traj, 4) == 19  # the earlier, closer point 0 is not allowed
    assert monotone_projection(q, traj, 4, window=5) == 4  # bounded window: best of 4..8
    assert monotone_projection(q, traj, 4, t_end=8) == 4  # segment end respected


def test_projection_matches_brute_force_and_is_monotone_in_t_start():
    rng = np.random.default_rng(0)
    traj = np.cumsum(rng.normal(size=(40, DOF)), axis=0)
    q = rng.normal(size=(25, DOF)) * 3
    previous = np.zeros(len(q), dtype=np.int64)
    for t0 in range(0, 40, 3):
        got = monotone_projection(q, traj, t0, window=12)
        for b in range(len(q)):
            cand = np.arange(t0, min(t0 + 12, 40))
            assert got[b] == cand[np.argmin(np.linalg.norm(traj[cand] - q[b], axis=1))]
        assert np.all(got >= t0)
    # for an unbounded window the projection of a fixed q never decreases as t_start grows
    for t0 in range(40):
        got = monotone_projection(q, traj, t0)
        assert np.all(got >= previous)
        previous = got


def test_projection_bad_inputs():
    with pytest.raises(ValueError, match="t_start"):
        monotone_projection(np.zeros(DOF), np.zeros((5, DOF)), 5)


# ---------------------------------------------------------------- PD return chunks

def test_gains_are_a_discrete_critically_damped_double_pole():
    for settle in (4.0, 8.0, 30.0):
        kp, kd = critically_damped_gains(settle)
        A = np.array([[1 - kp, 1 - kd], [-kp, 1 - kd]])  # error map of v += a; e += v
        eig = np.linalg.eigvals(A)
        p = np.exp(-5.83 / settle)
        np.testing.assert_allclose(eig.real, [p, p], atol=2e-4)  # a double (repeated) real pole
        np.testing.assert_allclose(eig.imag, 0, atol=2e-4)
    kp, kd = critically_damped_gains(400.0)
    assert kd == pytest.approx(2 * np.sqrt(kp), rel=0.02)  # continuous-time limit Kd = 2 √Kp
    with pytest.raises(ValueError):
        critically_damped_gains(0.0)


def test_pd_from_the_trajectory_reproduces_the_expert_future(stats):
    traj = smooth_trajectory()
    t = 20
    chunk = pd_return_chunk(traj[t], traj[t] - traj[t - 1], traj, t, 16, 0, stats.accel_max, stats.max_step)
    np.testing.assert_allclose(chunk, traj[t + 1:t + 17], atol=1e-12)


def test_pd_unclamped_error_settles_in_settle_steps():
    traj = smooth_trajectory()
    t, H = 20, 16
    e0 = np.array([0.02, -0.015, 0.01])
    chunk = pd_return_chunk(traj[t] + e0, traj[t] - traj[t - 1], traj, t, H, 0, 10.0, 10.0, settle_steps=8)
    err = np.linalg.norm(chunk - traj[t + 1:t + H + 1], axis=1)
    assert err[7] < 0.02 * np.linalg.norm(e0)  # 2 % after 8 steps (the gain design)
    assert err[-1] < 1e-3 * np.linalg.norm(e0)
    assert np.all(np.diff(err[1:]) < 0)  # critically damped: no overshoot ringing


@pytest.mark.parametrize("scale", [2.0, 6.0])
def test_pd_chunks_converge_within_clamps(stats, scale):
    """Noised states `scale` median steps (per joint) off a path: every chunk obeys the demos'
    acceleration clamp and the speed limit, and ends on (or, for large noise, nearer to) the path."""
    rng = np.random.default_rng(1)
    traj = smooth_trajectory()
    B, H, unit = 300, 16, stats.median_step
    t = rng.integers(5, 50, size=B)
    q0 = traj[t] + rng.normal(size=(B, DOF)) * scale * unit
    v0 = traj[t] - traj[t - 1]
    proj = monotone_projection(q0, traj, t, window=32)
    ahead = np.zeros(B, dtype=np.int64)  # the time-matched reference (corrective_labels' 'pd')
    chunk = pd_return_chunk(q0, v0, traj, proj, H, ahead, stats.accel_max, stats.max_step)
    assert chunk.shape == (B, H, DOF)
    # velocity and acceleration, including the first step from (q0, v0)
    path = np.concatenate([q0[:, None], chunk], axis=1)  # (B, H+1, dof)
    vel = np.diff(path, axis=1)
    acc = np.diff(np.concatenate([v0[:, None], vel], axis=1), axis=1)
    assert np.all(np.abs(vel) <= stats.max_step + 1e-12)
    assert np.all(np.abs(acc) <= stats.accel_max + 1e-12)
    # distance to the moving reference r_{k+1} = traj[proj + ahead + k + 1] tracked by chunk[k]
    ref = traj[np.minimum(proj[:, None] + ahead[:, None] + np.arange(1, H + 1), len(traj) - 1)]
    end_gap = np.linalg.norm(chunk[:, -1] - ref[:, -1], axis=1) / unit
    dist_to_path = lambda x: np.min(np.linalg.norm(traj[None] - x[:, None], axis=-1), axis=1) / unit
    if scale == 2.0:  # reachable within H under the clamp: the chunk has rejoined the path
        assert np.all(end_gap < 1.0) and np.percentile(end_gap, 90) < 0.1
    else:  # far off: not always rejoined within one chunk, but always heading back
        assert np.median(end_gap) < 1.0
        assert np.all(dist_to_path(chunk[:, -1]) < dist_to_path(q0))


def test_pd_brake_limit_reduces_overshoot_under_the_clamp():
    """On a straight path with a tight clamp, the closing-speed cap √(2 a_max |e|) limits the
    wind-up overshoot of a saturated PD (without the cap this case overshoots by 25 % of e0)."""
    traj = np.outer(np.arange(100), [0.02, -0.01, 0.015])
    e0 = np.array([0.3, 0.2, -0.25])
    chunk = pd_return_chunk(traj[10] + e0, traj[10] - traj[9], traj, 10, 16, 0, 0.004, 0.05)
    err = chunk - traj[11:27]
    overshoot = np.max(-err * np.sign(e0), axis=0)  # how far past the path each joint goes
    assert np.all(overshoot < 0.12 * np.abs(e0))
    # a gap within reach of the clamp is closed with almost no overshoot
    e0 = np.array([0.05, -0.05, 0.03])
    chunk = pd_return_chunk(traj[10] + e0, traj[10] - traj[9], traj, 10, 16, 0, 0.002, 0.05)
    err = chunk - traj[11:27]
    assert np.all(np.max(-err * np.sign(e0), axis=0) < 0.01 * np.abs(e0))
    assert np.all(np.abs(err[-1]) < 1e-3 * np.abs(e0))


def test_pd_clamped_acceleration_slows_the_return(stats):
    traj = smooth_trajectory()
    q0, v0 = traj[20] + 0.05, traj[20] - traj[19]
    fast = pd_return_chunk(q0, v0, traj, 20, 16, 2, 1.0, 1.0)
    slow = pd_return_chunk(q0, v0, traj, 20, 16, 2, 1e-3, 1.0)
    acc = np.diff(np.concatenate([[v0], np.diff(np.concatenate([[q0], slow]), axis=0)]), axis=0)
    assert np.abs(acc).max() <= 1e-3 + 1e-15
    ref = traj[22 + 16]  # chunk[-1] tracks r_H = traj[t_proj + lookahead + H]
    assert np.linalg.norm(slow[-1] - ref) > np.linalg.norm(fast[-1] - ref)


def test_pd_holds_the_segment_end_and_respects_limits():
    traj = smooth_trajectory()
    chunk = pd_return_chunk(traj[30], np.zeros(DOF), traj, 30, 16, 0, 1.0, 1.0, t_end=33)
    np.testing.assert_allclose(chunk[-1], traj[32], atol=1e-5)  # stops at the last expert point
    lo, hi = np.full(DOF, -0.1), np.full(DOF, 0.1)
    far = np.ones((1, DOF)) * 3.0
    chunk = pd_return_chunk(np.zeros(DOF), np.zeros(DOF), far, 0, 16, 0, 1.0, 1.0, limits=(lo, hi))
    assert np.all(chunk <= hi) and np.all(chunk >= lo)


def test_pd_bad_inputs(stats):
    traj = smooth_trajectory()
    with pytest.raises(ValueError, match="accel_max"):
        pd_return_chunk(traj[0], np.zeros(DOF), traj, 0, 16, 0, np.nan, 1.0)


# ---------------------------------------------------------------- noised states

def perturb(episode, sigma, rng, n, env, t_index=None, median_step=None, max_tries=10):
    """n noised states around `episode`'s steps t_index (an int, or (n,)), or around steps drawn uniformly
    over its labelable steps: noise_factors -> perturb_states, as the sampler and Fig. 1 call them.
    Returns (q̃ (m, dof), t (m,)) of the states kept."""
    if t_index is None:
        t = rng.choice(relabel.paper_label_steps(episode["expert"], H)[0], size=n)
    else:
        t = np.broadcast_to(np.asarray(t_index, dtype=np.int64), (n,)).copy()
    factors = noise_factors(sigma, t, DOF, median_step=median_step)
    env.reset(seed=int(episode["seed"]))
    q_tilde, kept = perturb_states(episode["q"][t], factors, rng, env, max_tries)
    return q_tilde[kept], t[kept]


def test_perturb_states_draws_q_plus_L_z_and_redraws_only_the_rejected_rows():
    """Fails if perturb_states' draw is not q_t + L_t z with z the generator's next standard normals, row by
    row (e.g. q_t - L z, Lᵀ z, or z drawn for every row again in a redraw round): the run's states, bit for bit."""
    q_t = smooth_trajectory()[[10, 20, 30]]
    factors = covariance_factor(np.stack([np.diag([1e-4, 4e-4, 1e-6]), np.full((DOF, DOF), 1e-4),
                                          np.diag([9e-4, 1e-6, 1e-4]) + 5e-5]))
    first = np.random.default_rng(0).standard_normal((3, DOF))
    free = FakeEnv()
    free.reset(seed=0)
    q, kept = perturb_states(q_t, factors, np.random.default_rng(0), free)
    np.testing.assert_array_equal(q, q_t + np.einsum("mij,mj->mi", factors, first))
    assert kept.all()
    # the middle state's first draw collides; the next round draws for that row alone
    env = FakeEnv(radius=1e-3, center_fn=lambda seed: q[1])
    env.reset(seed=0)
    q2, kept = perturb_states(q_t, factors, np.random.default_rng(0), env)
    gen = np.random.default_rng(0)
    gen.standard_normal((3, DOF))
    np.testing.assert_array_equal(q2[[0, 2]], q[[0, 2]])
    np.testing.assert_array_equal(q2[1], q_t[1] + np.einsum("mij,mj->mi", factors[1:2], gen.standard_normal((1, DOF)))[0])
    assert kept.all()


def test_isotropic_sigma_has_the_right_std_in_median_steps():
    ep = make_episode()
    rng = np.random.default_rng(2)
    q, t = perturb(ep, 4.0, rng, 20000, FakeEnv(), t_index=30, median_step=0.01)
    assert len(q) == 20000 and np.all(t == 30)
    std = (q - ep["q"][30]).std(axis=0) / 0.01
    np.testing.assert_allclose(std, 4.0, rtol=0.03)
    assert np.abs(np.corrcoef((q - ep["q"][30]).T)[np.triu_indices(DOF, 1)]).max() < 0.03


def test_pooled_covariance_is_reproduced_including_near_singular():
    ep = make_episode()
    rng = np.random.default_rng(3)
    A = rng.normal(size=(DOF, DOF)) * 0.01
    cov = A @ A.T
    q, _ = perturb(ep, cov, rng, 40000, FakeEnv(), t_index=25)
    emp = np.cov((q - ep["q"][25]).T)
    assert np.linalg.norm(emp - cov) < 0.03 * np.linalg.norm(cov)
    # rank one (a flat ellipse): Cholesky would fail; samples must lie on the line
    d = np.array([1.0, 2.0, -1.0]) / np.sqrt(6)
    flat = 1e-4 * np.outer(d, d) + 1e-18 * np.eye(DOF)
    q, _ = perturb(ep, flat, rng, 5000, FakeEnv(), t_index=25)
    dev = q - ep["q"][25]
    off_line = dev - np.outer(dev @ d, d)
    assert np.abs(off_line).max() < 1e-7
    assert (dev @ d).std() == pytest.approx(1e-2, rel=0.05)


def test_per_step_covariances_use_the_nearest_measured_step():
    ep = make_episode()
    rng = np.random.default_rng(4)
    c_a = np.diag([1e-4, 4e-4, 1e-6])
    c_b = np.diag([9e-4, 1e-6, 1e-4])
    per_step = (np.array([10, 20]), np.stack([c_a, c_b]))
    for t_query, expect in [(10, c_a), (14, c_a), (16, c_b), (40, c_b), (0, c_a)]:
        q, _ = perturb(ep, per_step, rng, 20000, FakeEnv(), t_index=t_query)
        emp = np.cov((q - ep["q"][t_query]).T)
        assert np.linalg.norm(emp - expect) < 0.04 * np.linalg.norm(expect), t_query
    f = noise_factors(per_step, np.array([15]), DOF)  # tie between 10 and 20 -> the earlier
    np.testing.assert_allclose(f[0] @ f[0].T, c_a)


def test_perturbed_states_are_collision_free_and_inside_limits():
    ep = intervention_episode()
    # the obstacle ball sits right next to the trajectory, so a good share of draws hits it
    env = FakeEnv(radius=0.15, center_fn=lambda seed: smooth_trajectory()[30] + np.array([0.1, 0.0, 0.0]))
    rng = np.random.default_rng(5)
    q, t = perturb(ep, 15.0, rng, 3000, env, median_step=0.01, max_tries=1)
    assert 0 < len(q) < 3000  # with a single try, colliding draws are dropped, not kept
    assert not env.in_collision(q).any()
    q, t = perturb(ep, 15.0, rng, 3000, env, median_step=0.01, max_tries=10)
    assert len(q) == 3000 and not env.in_collision(q).any()
    assert np.all((t >= 10) & (t < 60))  # only intervention steps with a valid label
    lo, hi = env.joint_limits
    # a state close to a joint limit: out-of-limit draws are rejected, not clipped onto the limit
    near = make_episode()
    near["q"] = near["q"] + np.array([np.pi - 0.01, 0, 0]) - near["q"][30, 0] * np.array([1, 0, 0])
    q, _ = perturb(near, 2.0, rng, 4000, FakeEnv(), t_index=30, median_step=0.01)
    assert np.all(q <= hi) and np.all(q >= lo)
    assert np.sum(q[:, 0] == hi[0]) == 0


def test_states_are_dropped_when_every_draw_collides():
    ep = make_episode()
    env = FakeEnv(radius=100.0, center_fn=lambda seed: np.zeros(DOF))  # everything is in collision
    q, t = perturb(ep, 1.0, np.random.default_rng(0), 50, env, median_step=0.01)
    assert q.shape == (0, DOF) and t.shape == (0,)


def test_zero_covariance_gives_the_expert_state_and_the_expert_label(stats):
    ep = intervention_episode()
    q, t = perturb(ep, 0.0, np.random.default_rng(0), 20, FakeEnv(), median_step=0.01)
    np.testing.assert_array_equal(q, ep["q"][t])
    q2, _ = perturb(ep, np.zeros((DOF, DOF)), np.random.default_rng(0), 20, FakeEnv())
    np.testing.assert_array_equal(q2, q)
    v = ep["q"][t] - ep["q"][t - 1]
    chunks = corrective_labels(q, v, ep["q"], t, np.full(len(t), 60), stats, RelabelConfig(H))
    for c, ti in zip(chunks, t):  # the PD: identical to the expert's own future (held at the segment's end)
        np.testing.assert_allclose(c, ep["q"][np.minimum(np.arange(ti + 1, ti + 17), 59)], atol=1e-12)


def test_covariance_factor_batched():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(5, DOF, DOF))
    covs = A @ np.swapaxes(A, 1, 2)
    L = covariance_factor(covs)
    np.testing.assert_allclose(L @ np.swapaxes(L, 1, 2), covs, atol=1e-12)


# ---------------------------------------------------------------- augmentation sampler

def small_cfg(**kw):
    base = dict(pool_size=256, refresh_size=64, reuse=2.0, episodes_per_refresh=4)
    base.update(kw)
    return RelabelConfig(H, **base)


def make_sampler(stats, noise="isotropic", sigma=4.0, cfg=None, n_eps=5):
    eps = [intervention_episode(seed=s, phase=0.2 * s) for s in range(n_eps)]
    return AugmentationSampler(eps, FakeEnv, stats, noise, sigma, cfg or small_cfg()), eps


def test_sampler_shapes_dtypes_and_labels(stats):
    sampler, eps = make_sampler(stats, cfg=small_cfg(velocity_noise=0.0))  # the expert's own velocities
    obs, chunks, mask = sampler(128, np.random.default_rng(0))
    assert obs.shape == (128, FakeEnv.obs_dim) and obs.dtype == np.float32
    assert chunks.shape == (128, 16, DOF) and chunks.dtype == np.float32
    assert mask.shape == (128, 16) and mask.dtype == bool and mask.all()
    q_tilde, q_prev = obs[:, :DOF].astype(np.float64), obs[:, DOF:2 * DOF].astype(np.float64)
    # the observed velocity is one of the expert's velocities at an intervention step
    expert_vel = np.concatenate([ep["q"][10:60] - ep["q"][9:59] for ep in eps])
    vel = q_tilde - q_prev
    assert np.min(np.abs(vel[:, None] - expert_vel[None]).max(-1), axis=1).max() < 1e-6
    # the goal part of the observation belongs to one of the episodes' scenarios
    goals = np.array([[np.cos(s), np.sin(s)] for s in range(5)], dtype=np.float32)
    assert np.min(np.abs(obs[:, None, -2:] - goals[None]).max(-1), axis=1).max() < 1e-6
    # every chunk starts within one speed-limited step of its noised state
    assert np.all(np.abs(chunks[:, 0] - q_tilde) <= FakeEnv.max_step + 1e-6)
    assert sampler.n_kept == sampler.n_drawn > 0


def test_sampler_is_deterministic_given_the_seed(stats):
    outs = []
    for _ in range(2):
        sampler, _ = make_sampler(stats)
        rng = np.random.default_rng(42)
        outs.append([sampler(64, rng) for _ in range(5)])
    for first, second in zip(*outs):
        for x1, x2 in zip(first, second):  # obs, chunks, mask
            np.testing.assert_array_equal(x1, x2)
    sampler, _ = make_sampler(stats)
    o3, _, _ = sampler(64, np.random.default_rng(43))
    assert not np.array_equal(o3, outs[0][0][0])


def test_sampler_pool_is_refreshed_and_envs_are_cached(stats):
    # a refresh of 64 pairs after every reuse * refresh_size = 0.25 * 64 = 16 pairs served
    sampler, _ = make_sampler(stats, cfg=small_cfg(pool_size=128, refresh_size=64, reuse=0.25))
    rng = np.random.default_rng(0)
    sampler(8, rng)  # call 1 fills the pool
    assert sampler._filled == 128
    before = sampler._pool_obs.copy()
    drawn = sampler.n_drawn
    sampler(8, rng)  # 8 served so far: no refresh
    assert sampler.n_drawn == drawn
    sampler(8, rng)  # 16 served: refresh of 64 pairs, then serve
    assert sampler.n_drawn == drawn + 64
    changed = np.any(sampler._pool_obs != before, axis=1)
    assert changed.sum() == 64
    sampler(16, rng)  # 8 served since the refresh
    assert sampler.n_drawn == drawn + 64
    sampler(1, rng)  # 24 >= 16: the next refresh
    assert sampler.n_drawn == drawn + 128
    assert len(sampler._envs) >= 2 and set(sampler._envs) <= set(range(5))  # one env per scenario seed
    assert all(env.reset_calls == 1 for env in sampler._envs.values())


def test_sampler_pooled_noise_matches_covariance(stats):
    rng = np.random.default_rng(7)
    A = rng.normal(size=(DOF, DOF)) * 0.02
    cov = A @ A.T
    sampler, eps = make_sampler(stats, noise="pooled", sigma=cov,
                                cfg=small_cfg(pool_size=8192, refresh_size=8192, velocity_noise=0.0))
    sampler(0, rng)  # fills the pool
    q_tilde = sampler._pool_obs[:, :DOF].astype(np.float64)
    q_prev = sampler._pool_obs[:, DOF:2 * DOF].astype(np.float64)
    # recover q_t from the observed velocity: find the expert step with that velocity and position
    all_q = np.concatenate([ep["q"][10:60] for ep in eps])
    all_v = np.concatenate([ep["q"][10:60] - ep["q"][9:59] for ep in eps])
    match = np.argmin(np.abs((q_tilde - q_prev)[:, None] - all_v[None]).sum(-1), axis=1)
    dev = q_tilde - all_q[match]
    emp = np.cov(dev.T)
    assert np.linalg.norm(emp - cov) < 0.06 * np.linalg.norm(cov)


def test_sampler_per_step_dict_and_list(stats):
    covs = (np.array([12, 30, 50]), np.stack([np.eye(DOF) * 1e-4, np.eye(DOF) * 4e-4, np.eye(DOF) * 1e-5]))
    eps = [intervention_episode(seed=s) for s in range(3)]
    rng = np.random.default_rng(0)
    for per_step in ({0: covs, 1: covs, 2: covs}, [covs, covs, covs]):
        sampler = AugmentationSampler(eps, FakeEnv, stats, "per_step", per_step, small_cfg())
        obs, chunks, _ = sampler(32, rng)
        assert obs.shape == (32, FakeEnv.obs_dim) and chunks.shape == (32, 16, DOF)
        # step 31 (nearest measurement at 30) gets 4e-4 I; step 13 gets 1e-4 I
        np.testing.assert_allclose(sampler.factors[31 - 10] @ sampler.factors[31 - 10].T, np.eye(DOF) * 4e-4)
        np.testing.assert_allclose(sampler.factors[13 - 10] @ sampler.factors[13 - 10].T, np.eye(DOF) * 1e-4)
    with pytest.raises(KeyError):  # no covariances for episode 2
        AugmentationSampler(eps, FakeEnv, stats, "per_step", {0: covs, 1: covs}, small_cfg())


def test_sampler_bad_configuration(stats):
    eps = [intervention_episode()]
    blocked = lambda: FakeEnv(radius=100.0, center_fn=lambda s: np.zeros(DOF))
    sampler = AugmentationSampler(eps, blocked, stats, "isotropic", 4.0, small_cfg(max_tries=2))
    with pytest.raises(ValueError, match="too large"):
        sampler(8, np.random.default_rng(0))


# ---------------------------------------------------------------- figure 1

def test_plot_recovery_writes_a_png(tmp_path, stats):
    path = tmp_path / "fig1.png"
    out = relabel.plot_recovery(FakeEnv(), intervention_episode(), np.eye(DOF) * 1e-3, str(path),
                                np.random.default_rng(0), stats, RelabelConfig(H), n_recoveries=5)
    assert out == str(path) and path.stat().st_size > 10_000
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------- the real planar env

PLANAR_SEEDS = (4, 13, 30)  # scenarios where that straight path is >= 60 steps long


@pytest.fixture(scope="module")
def planar():
    env = envs.make_env("planar")
    eps = [straight_line_episode(env, s) for s in PLANAR_SEEDS]
    st = demo_stats(eps, envs.median_step(eps), env.max_step)
    return envs, eps, st


def test_planar_perturbed_states_are_free_by_the_pymunk_check(planar):
    envs, eps, st = planar
    env = envs.make_env("planar")
    rng = np.random.default_rng(0)
    for ep in eps:
        q, t = perturb(ep, 8.0, rng, 300, env, median_step=st.median_step)
        assert len(q) > 250
        assert not env.in_collision(q).any()
        assert not np.any(env.pymunk_in_collision(q))  # the simulator's own, independent check
        lo, hi = env.joint_limits
        assert np.all((q >= lo) & (q <= hi))


def test_planar_sampler_without_noise_reproduces_the_episodes(planar):
    envs, eps, st = planar
    cfg = small_cfg(velocity_noise=0.0)  # no noise at all; the PD label has feed-forward
    sampler = AugmentationSampler(eps, lambda: envs.make_env("planar"), st, "isotropic", 0.0, cfg)
    obs, chunks, _ = sampler(64, np.random.default_rng(0))
    for o, c in zip(obs, chunks):
        found = [(e, t) for e, ep in enumerate(eps) for t in np.flatnonzero(np.all(ep["obs"] == o, axis=1))]
        assert len(found) == 1  # the observation the episode recorded at that step, bit for bit
        e, t = found[0]
        q = eps[e]["q"]
        # the expert's own future; tiny differences where the smoothstep's final braking exceeds the
        # 99th-percentile acceleration clamp
        np.testing.assert_allclose(c, q[np.minimum(np.arange(t + 1, t + 17), len(q) - 1)], atol=0.05 * st.median_step)


def test_planar_sampler_pooled_noise(planar):
    envs, eps, st = planar
    cov = np.diag([4.0, 2.0, 1.0]) ** 2 * st.median_step ** 2
    sampler = AugmentationSampler(eps, lambda: envs.make_env("planar"), st, "pooled", cov, small_cfg())
    obs, chunks, mask = sampler(128, np.random.default_rng(1))
    env = envs.make_env("planar")
    assert mask.shape == (128, 16) and mask.all()
    assert obs.shape == (128, env.obs_dim) and chunks.shape == (128, 16, 3)
    for seed in PLANAR_SEEDS:  # every noised state is free in its own scenario
        env.reset(seed=seed)
        mine = np.all(obs[:, 6:] == env.make_obs(np.zeros(3), np.zeros(3))[6:], axis=1)
        assert not np.any(env.pymunk_in_collision(obs[mine, :3].astype(np.float64)))
    steps = np.abs(np.diff(np.concatenate([obs[:, None, :3], chunks], axis=1), axis=1))
    assert steps.max() <= env.max_step + 1e-6  # every chunk is executable as is


def test_planar_fig1(planar, tmp_path):
    envs, eps, st = planar
    env = envs.make_env("planar")
    path = relabel.plot_recovery(env, eps[0], np.diag([5.0, 3.0, 2.0]) ** 2 * st.median_step ** 2,
                                 str(tmp_path / "fig1.png"), np.random.default_rng(0), st, RelabelConfig(H))
    assert (tmp_path / "fig1.png").stat().st_size > 20_000


def test_fig1_on_the_3d_env_writes_a_png(tmp_path):
    """Fig. 1 on EngineReach3D: drawn in the top view (x, y) with env.draw_noise_ellipses in the plane
    (0, 1); EngineReach3D.render would show a camera image, so no arm is drawn."""
    env = environments.make_env("engine3d")
    eps = [straight_line_episode(env, s) for s in (3, 5)]  # 55 and 32 expert steps
    st = demo_stats(eps, envs.median_step(eps), env.max_step)
    path = tmp_path / "fig1_3d.png"
    out = relabel.plot_recovery(env, eps[0], np.diag([3.0, 2.0, 2.0, 1.5, 1.5, 1.5]) ** 2 * st.median_step ** 2,
                                str(path), np.random.default_rng(0), st, RelabelConfig(H))
    assert out == str(path) and path.stat().st_size > 20_000
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sampler_state_dict_resumes_the_same_stream(stats):
    a, _ = make_sampler(stats)
    rng = np.random.default_rng(9)
    for _ in range(3):
        a(np.int64(32), rng)  # relabel.MixtureSampler passes its multinomial counts: numpy ints
    state, rng_state = checkpoints.sampler_state(a), rng.bit_generator.state
    expect = [a(32, rng) for _ in range(4)]
    b, _ = make_sampler(stats)
    # the state goes through a checkpoint file, read back as train() reads it (torch's safe loader, which
    # refuses numpy scalars: a stopped co-training run could not resume)
    buffer = io.BytesIO()
    torch.save({"sampler": checkpoints._as_torch(state)}, buffer)
    buffer.seek(0)
    checkpoints.restore_sampler(b, checkpoints._as_numpy(torch.load(buffer, weights_only=True)["sampler"]))
    rng2 = np.random.default_rng()
    rng2.bit_generator.state = rng_state
    for first, second in zip(expect, [b(32, rng2) for _ in range(4)]):
        for x1, x2 in zip(first, second):  # obs, chunks, mask
            np.testing.assert_array_equal(x1, x2)


def test_pd_label_is_time_matched(stats):
    """The PD's reference is trajectory[t_proj + k] (lookahead 0), so the chunk ends on the point
    the expert reaches H steps after the projection (the literal 'gap' lookahead was measured worse:
    benchmarks/HISTORY.md, "The PD label's lookahead")."""
    traj = smooth_trajectory()
    rng = np.random.default_rng(3)
    t = np.full(50, 20)
    q = traj[t] + rng.normal(size=(50, DOF)) * 3 * stats.median_step
    v = traj[t] - traj[t - 1]
    end = np.full(50, len(traj))
    timed = corrective_labels(q, v, traj, t, end, stats, RelabelConfig(H))
    proj = monotone_projection(q, traj, t, window=32)
    np.testing.assert_allclose(timed, pd_return_chunk(q, v, traj, proj, H, 0, stats.accel_max, stats.max_step))
    assert np.median(np.linalg.norm(timed[:, -1] - traj[proj + H], axis=1)) < 0.1 * stats.median_step


# ---------------------------------------------------------------- the authors' relabeling (benchmarks/SETUP.md §6)

def line_episode(seed=0, T=60, step=(0.02, -0.01, 0.015)):
    """A constant-velocity expert episode: its demo tangent q_t - q_{t-1} is `step` at every t."""
    q = np.array([0.1, 0.2, -0.3]) + np.arange(T)[:, None] * np.asarray(step)
    prev = np.concatenate([q[:1], q[:-1]])
    expert = np.zeros(T, bool)
    expert[5:] = True
    env = FakeEnv()
    env.reset(seed=seed)
    return {"obs": env.make_obs(q, prev), "q": q, "action": np.concatenate([q[1:], q[-1:]]),
            "expert": expert, "seed": seed}


def test_velocity_noise_has_the_configured_std_and_rebuilds_q_prev(stats):
    step = np.array([0.02, -0.01, 0.015])
    sampler = AugmentationSampler([line_episode()], FakeEnv, stats, "isotropic", 2.0,
                                  small_cfg(pool_size=4096, refresh_size=4096))
    sampler(0, np.random.default_rng(0))  # fills the pool
    obs = sampler._pool_obs[: sampler._filled].astype(np.float64)
    v = obs[:, :DOF] - obs[:, DOF:2 * DOF]  # q̃ - q_prev, and q_prev = q̃ - v
    noise = v - step  # velocity = demo tangent + N(0, (0.3 median_step)²) per joint
    assert len(noise) > 3000
    np.testing.assert_allclose(noise.mean(0), 0, atol=0.1 * 0.3 * stats.median_step)
    np.testing.assert_allclose(noise.std(0), 0.3 * stats.median_step, rtol=0.05)


def test_velocity_noise_is_the_authors_rate_per_env_step(stats):
    """The authors add N(0, (0.3 m_p)²) per joint to a noised state's velocity, in rad per 30 Hz frame (m_p
    their median step, benchmarks/SETUP.md §6). Per env step that must be the same speed in rad/s at any control
    period. With the stats built as the project builds them (frames_per_step = env.dt / PAPER_FRAME_DT, as
    dagger's demo statistics do) for one motion sampled at our 10 Hz and at the authors' 30 Hz (where a step
    is their frame, so their 0.3 m_p unconverted), the std over env.dt is one number; one 10 Hz step spans as
    many of their frames as the data say. A missing conversion (3x too little at 10 Hz), a random walk's
    sqrt(3), or the inverse (9x) each break one of these."""
    cfg = RelabelConfig(H)
    assert relabel.velocity_noise_std(cfg, stats) == pytest.approx(0.3 * stats.median_step)   # no units known
    speeds = np.array([0.1, -0.2, 0.26])  # rad/s: one motion, joints at different constant speeds

    def project_stats(dt):
        env = envs.make_env("planar", dt=dt)
        q = np.array([0.3, -1.0, 2.0]) + np.arange(round(3.0 / dt) + 1)[:, None] * dt * speeds  # 3 s
        demos = [{"q": q}]
        return env, q, demo_stats(demos, envs.median_step(demos), env.max_step,
                                  paper_median_step=env.paper_median_step,
                                  frames_per_step=env.dt / envs.PAPER_FRAME_DT)

    env10, q10, at_10hz = project_stats(0.1)
    env30, q30, at_30hz = project_stats(1 / 30)  # the authors' rate (benchmarks/SETUP.md §1), not PAPER_FRAME_DT
    # frames per step, from the data: how much further one 10 Hz step moves than one 30 Hz step
    assert at_10hz.frames_per_step == pytest.approx(np.abs(np.diff(q10, axis=0)).max() / np.abs(np.diff(q30, axis=0)).max())
    assert at_30hz.frames_per_step == pytest.approx(1.0)
    noise_30hz = relabel.velocity_noise_std(cfg, at_30hz)
    assert noise_30hz == pytest.approx(cfg.velocity_noise * envs.PlanarReacher.paper_median_step)  # theirs, as set
    noise_10hz = relabel.velocity_noise_std(cfg, at_10hz)
    assert noise_10hz / env10.dt == pytest.approx(noise_30hz / env30.dt)  # the same rad/s at either rate
    assert noise_10hz != pytest.approx(cfg.velocity_noise * at_10hz.median_step, rel=0.2)  # not 0.3 of ours
    # the sampler draws it: q_prev = q - v with v = the demo tangent + that noise
    step = np.array([0.02, -0.01, 0.015])
    planar = replace(stats, paper_median_step=at_10hz.paper_median_step, frames_per_step=at_10hz.frames_per_step)
    sampler = AugmentationSampler([line_episode()], FakeEnv, planar, "isotropic", 2.0,
                                  small_cfg(pool_size=4096, refresh_size=4096))
    sampler(0, np.random.default_rng(0))
    obs = sampler._pool_obs[: sampler._filled].astype(np.float64)
    noise = obs[:, :DOF] - obs[:, DOF:2 * DOF] - step
    np.testing.assert_allclose(noise.std(0), noise_10hz, rtol=0.05)
    assert noise_10hz != pytest.approx(0.3 * stats.median_step, rel=0.2)  # FakeEnv's own unit would differ
    demo = demo_stats([oracle_like_demo(0)], 0.01, FakeEnv.max_step, paper_median_step=0.0176, frames_per_step=3)
    assert (demo.paper_median_step, demo.frames_per_step) == (0.0176, 3.0)


def test_planar_obs_of_a_noised_state_is_rebuilt_by_forward_kinematics(planar):
    envs, eps, st = planar
    env = envs.make_env("planar")
    sampler = AugmentationSampler(eps, lambda: envs.make_env("planar"), st, "isotropic", 4.0, small_cfg())
    obs, _, _ = sampler(64, np.random.default_rng(2))
    q_tilde = obs[:, :3].astype(np.float64)
    np.testing.assert_allclose(obs[:, -2:], env.ee(q_tilde), atol=1e-5)  # end effector of q̃, not of q_t
    v = q_tilde - obs[:, 3:6]
    assert np.abs(v).max() > 0  # the previous frame q̃ - v is in the obs


def test_sampler_pool_mask_survives_its_resume_state(stats):
    a, _ = make_sampler(stats)
    a(16, np.random.default_rng(0))
    state = checkpoints.sampler_state(a)
    assert state["pool_mask"].dtype == bool and state["pool_mask"].shape == (256, 16)
    b, _ = make_sampler(stats)
    checkpoints.restore_sampler(b, state)
    np.testing.assert_array_equal(b._pool_mask, a._pool_mask)


def test_chunk_and_mixture_samplers_draw_rows_in_proportion(stats):
    """ChunkSampler serves the recorded (obs, expert chunk) pairs; MixtureSampler splits a batch over its
    samplers by a multinomial of the weights and adds an all-True mask to a sampler that gives none."""
    eps = [intervention_episode(seed=s, phase=0.2 * s) for s in range(3)]
    recorded = ChunkSampler(eps, H)
    obs, chunks = recorded(200, np.random.default_rng(0))
    assert obs.shape == (200, FakeEnv.obs_dim) and chunks.shape == (200, H, DOF)
    data_obs, data_chunks = diffusion.chunk_dataset(eps, H)[:2]
    rows = [np.flatnonzero(np.all(data_obs == o, axis=1))[0] for o in obs]
    np.testing.assert_array_equal(chunks, data_chunks[rows])  # each row a recorded pair, as recorded
    noised, _ = make_sampler(stats)
    mix = MixtureSampler([recorded, noised], [3, 1])
    np.testing.assert_allclose(mix.p, [0.75, 0.25])
    obs, chunks, mask = mix(400, np.random.default_rng(1))
    assert obs.shape == (400, FakeEnv.obs_dim) and chunks.shape == (400, H, DOF) and mask.shape == (400, H)
    n_recorded = np.random.default_rng(1).multinomial(400, [0.75, 0.25])[0]  # the mixture's first draw
    assert 250 < n_recorded < 350 and mask[:n_recorded].all()  # the recorded rows come first, all in the loss
    assert MixtureSampler([recorded, recorded], [1, 1])(10, np.random.default_rng(2))[1].shape == (10, H, DOF)
    state = checkpoints.sampler_state(mix)  # the noised sampler's pool, under its index
    assert list(state) == ["1"]
    again = MixtureSampler([recorded, make_sampler(stats)[0]], [3, 1])
    checkpoints.restore_sampler(again, state)
    np.testing.assert_array_equal(again.samplers[1]._pool_obs, noised._pool_obs)


def test_generate_labels_in_one_pass_when_no_redraw_is_allowed(stats):
    """max_redraws = 0: one labelling pass, the rows it rejects dropped, not redrawn. Fails if generate's loop made
    no pass (range(max_redraws - 1)) or a second one (range(max_redraws + 2))."""
    sampler, _ = make_sampler(stats, cfg=small_cfg(max_redraws=0, near_end_steps=30))  # many rows rejected
    rng = np.random.default_rng(0)
    rows = sampler._draw_rows(64, rng)
    limits = sampler._env(int(sampler.seeds[rows[0]])).joint_limits
    (kept, *_), rejected = sampler._label_rows(rows, rng, limits)     # the first pass, by hand
    assert len(rejected) > 0 and len(kept) > 0                          # the case can tell one pass from two
    obs, chunks, mask = sampler.generate(64, np.random.default_rng(0))  # the same draws
    assert len(obs) == len(kept) and sampler.n_kept == len(kept)
    assert chunks.shape == (len(obs), H, DOF) and mask.shape == (len(obs), H)
