"""Tests of calibrate.py: the math of Eqs. (1), (2), (12)-(16), the fit, and one real calibration."""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import calibrate as cal
import dagger
import diffusion
import envs
from helpers import straight_line_episode  # tests/helpers.py
from experiment import environments, profiles
from experiment.run_folder import calibration_to_json


# ----------------------------------------------------------------------------------------------
# Eq. (12) and its fit
# ----------------------------------------------------------------------------------------------

def test_equilibrium_limits_and_shape():
    W, r = 0.3, 5.0
    assert cal.equilibrium(0.0, W, r) == 0.0                     # pure expert: no error
    assert cal.equilibrium(1.0, W, r) == pytest.approx(W)        # pure policy: its own settling error
    s = np.linspace(0, 1, 50)
    x = cal.equilibrium(s, W, r)
    assert np.all(np.diff(x) > 0)                                # error grows with the policy's share
    # r = 1 (equal gains) makes the blend linear in s
    np.testing.assert_allclose(cal.equilibrium(s, W, 1.0), W * s)
    with pytest.raises(ValueError, match="r = K"):
        cal.equilibrium(s, W, 0.0)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        cal.equilibrium(1.5, W, r)


def _blend_points(W, r, noise, seed):
    rng = np.random.default_rng(seed)
    # s of the 13 ratios under a squared-cosine schedule spans about [0.01, 0.98]
    beta = np.linspace(0.05, 0.90, 13)
    s = np.sin(beta * math.pi / 2) ** 2
    x = cal.equilibrium(s, W, r) * (1 + noise * rng.standard_normal(len(s)))
    return s, x


@pytest.mark.parametrize("W,r", [(0.2, 4.0), (0.05, 0.5), (1.3, 20.0)])
def test_fit_recovers_W_and_r_from_noisy_points(W, r):
    s, x = _blend_points(W, r, noise=0.03, seed=1)
    fit = cal.fit_equilibrium(s, x)
    assert fit.W == pytest.approx(W, rel=0.08)
    assert fit.r == pytest.approx(r, rel=0.3)
    assert fit.n_points == 13
    exact = cal.fit_equilibrium(*_blend_points(W, r, noise=0.0, seed=0))
    assert exact.W == pytest.approx(W, rel=1e-5) and exact.r == pytest.approx(r, rel=1e-4)


def test_fit_at_the_edges_of_the_gain_ratio_grid():
    """Points whose best r lies beyond the grid (r_bounds (1e-3, 1e3)) fit at its edge, finite and near the end:
    fails if the golden section's bracket ran past the grid's last or first point (an index error or a bracket
    off the grid)."""
    for r_true, edge in ((5e4, 1e3), (1e-5, 1e-3)):
        s, x = _blend_points(0.2, r_true, noise=0.0, seed=0)
        fit = cal.fit_equilibrium(s, x)
        assert math.isfinite(fit.W) and fit.W > 0
        assert fit.r == pytest.approx(edge, rel=0.05)


def test_fit_degenerate_inputs():
    with pytest.raises(ValueError, match=">= 3"):
        cal.fit_equilibrium([0.2, 0.9], [0.1, 0.2])
    with pytest.raises(ValueError, match=">= 3"):                # NaNs are not usable points
        cal.fit_equilibrium([0.2, 0.5, 0.9], [0.1, np.nan, 0.2])
    with pytest.raises(ValueError, match="distinct"):
        cal.fit_equilibrium([0.5, 0.5, 0.5], [0.1, 0.2, 0.3])
    zero = cal.fit_equilibrium([0.1, 0.5, 0.9], [0.0, 0.0, 0.0])
    assert zero.W == 0.0 and zero.r == 1.0 and math.isfinite(zero.rms_residual)


# ----------------------------------------------------------------------------------------------
# Eqs. (2), (13)-(16)
# ----------------------------------------------------------------------------------------------

def _random_covariances(n, d, seed):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, d, d))
    return A @ A.transpose(0, 2, 1) / d                          # (n, d, d) SPD


def test_trace_scaling_is_exact_and_keeps_the_shape():
    S = _random_covariances(20, 3, seed=0)
    W = np.array([0.1, -0.2, 0.05])
    S_alpha = cal.calibrated_sigma(S, W)
    np.testing.assert_allclose(np.trace(S_alpha, axis1=1, axis2=2), np.sum(W ** 2), rtol=1e-12)
    ratio = S_alpha / S                                          # a positive multiple of each Sigma_hat_t
    np.testing.assert_allclose(ratio, ratio[:, :1, :1] * np.ones_like(ratio), rtol=1e-10)
    # the scalar norm gives the same result as the vector
    np.testing.assert_allclose(cal.calibrated_sigma(S, np.linalg.norm(W)), S_alpha, rtol=1e-12)


def test_dart_eq2_with_alpha_from_eq13_is_eq14():
    S = _random_covariances(5, 3, seed=1)
    W, T = 0.3, 57
    np.testing.assert_allclose(cal.dart_sigma(S, cal.dart_alpha(W, T), T), cal.calibrated_sigma(S, W))
    assert cal.dart_alpha(np.array([3.0, 4.0]), 2) == pytest.approx(50.0)


def test_zero_trace_falls_back_to_isotropic():
    S = _random_covariances(3, 3, seed=2)
    S[1] = 0.0
    S_alpha = cal.calibrated_sigma(S, 0.6)
    assert np.all(np.isfinite(S_alpha))
    np.testing.assert_allclose(S_alpha[1], 0.36 / 3 * np.eye(3))
    np.testing.assert_allclose(np.trace(S_alpha, axis1=1, axis2=2), 0.36)


def test_pooled_sigma_is_the_scaled_mean_of_the_per_step_ones():
    S = _random_covariances(40, 3, seed=3)
    sigma_bar = S.mean(axis=0)
    # with ||W||^2 = tr(Sigma_bar) Eq. (16) leaves the mean unchanged
    np.testing.assert_allclose(cal.pooled_sigma(S, math.sqrt(np.trace(sigma_bar))), sigma_bar, rtol=1e-12)
    pooled = cal.pooled_sigma(S, 0.4)
    assert np.trace(pooled) == pytest.approx(0.16)
    np.testing.assert_allclose(pooled, 0.16 / np.trace(sigma_bar) * sigma_bar)
    with pytest.raises(ValueError, match="non-empty"):
        cal.pooled_sigma(np.zeros((0, 3, 3)), 0.4)


def test_sigma_in_median_steps():
    sigma = np.diag([4.0, 9.0, 16.0]) * 0.01 ** 2
    np.testing.assert_allclose(cal.sigma_in_median_steps(sigma, 0.01), [2.0, 3.0, 4.0])


# ----------------------------------------------------------------------------------------------
# Segments, labels and Eq. (1) with a test double of known noise
# ----------------------------------------------------------------------------------------------

def _episode(expert, dof=3, seed=0):
    rng = np.random.default_rng(seed)
    T = len(expert)
    q = np.cumsum(rng.normal(0, 0.01, (T, dof)), axis=0)
    return {"obs": np.arange(T, dtype=np.float32)[:, None],     # obs = the step index (for the double)
            "q": q, "action": q + 0.01, "expert": np.asarray(expert, bool), "seed": 0}


def test_segments_and_label_starts_follow_the_contract():
    H = 4
    expert = [True] * 6 + [False] * 3 + [True] * 3 + [False] * 2 + [True] * 5
    ep = _episode(expert)
    assert diffusion.expert_runs(ep["expert"], H) == [(0, 6), (14, 19)]      # the 3-step run is too short
    # first segment ends inside the episode: t + H <= 6; the last reaches the end: every step
    np.testing.assert_array_equal(np.flatnonzero(diffusion.label_mask(ep["expert"], H)), [0, 1, 2, 14, 15, 16, 17, 18])
    chunk = cal.expert_chunk(ep["action"], 4, H, end=6)          # padded with the segment's last action
    np.testing.assert_array_equal(chunk, ep["action"][[4, 5, 5, 5]])


class NoisyExpertPolicy:
    """Test double: returns the expert chunk plus N(mean, S) noise, so Eq. (1) must give S + mean mean^T."""

    class cfg:
        horizon = 4

    def __init__(self, episode, S, mean):
        self.actions = episode["action"]
        self.L = np.linalg.cholesky(S)
        self.mean = np.asarray(mean)
        self.calls = 0

    def sample(self, obs, generator=None, use_ema=True):
        self.calls += 1
        t = obs[:, 0].astype(int)
        chunks = np.stack([cal.expert_chunk(self.actions, int(i), self.cfg.horizon) for i in t])
        z = torch.randn(chunks.shape, generator=generator, dtype=torch.float64).numpy()
        return chunks + self.mean + z @ self.L.T


def test_open_loop_sigma_recovers_a_known_covariance():
    ep = _episode([True] * 41)
    S = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, -0.5], [0.0, -0.5, 1.0]]) * 1e-4
    mean = np.array([0.01, 0.0, -0.02])
    policy = NoisyExpertPolicy(ep, S, mean)
    out = cal.open_loop_sigma(policy, [ep], stride=2, n_samples=400, generator=torch.Generator().manual_seed(0),
                              max_batch=5000)
    np.testing.assert_array_equal(out.timestep, np.arange(0, 41, 2))   # every other step, to the end
    np.testing.assert_array_equal(out.episode_index, 0)
    assert policy.calls == 2                                     # batched: 21 steps x 400 samples, 5000 rows a call
    pooled = out.sigma.mean(axis=0)
    expected = S + np.outer(mean, mean)                          # uncentered, as in Eq. (1)
    np.testing.assert_allclose(pooled, expected, atol=0.05 * np.abs(expected).max())
    same = cal.open_loop_sigma(policy, [ep], 2, 400, torch.Generator().manual_seed(0), 5000)
    np.testing.assert_array_equal(same.sigma, out.sigma)        # same seed, same numbers


def test_open_loop_sigma_rejects_data_without_labels():
    ep = _episode([False] * 10)
    with pytest.raises(ValueError, match="no valid expert label"):
        cal.open_loop_sigma(NoisyExpertPolicy(ep, np.eye(3), np.zeros(3)), [ep], stride=2, n_samples=4)
    with pytest.raises(ValueError, match="n_samples=0"):
        cal.open_loop_sigma(NoisyExpertPolicy(ep, np.eye(3), np.zeros(3)), [ep], stride=2, n_samples=0)


class ExecutedStepsPolicy:
    """Test double: the expert chunk, exact for the first n_act steps and far off after them."""

    class cfg:
        horizon = 4
        n_act = 2

    def __init__(self, episode):
        self.actions = episode["action"]

    def sample(self, obs, generator=None, use_ema=True):
        t = obs[:, 0].astype(int)
        chunks = np.stack([cal.expert_chunk(self.actions, int(i), self.cfg.horizon) for i in t])
        chunks[:, self.cfg.n_act:] += 1.0                                    # wrong, but never executed
        return chunks


def test_open_loop_sigma_compares_only_the_executed_steps():
    ep = _episode([True] * 20)
    policy = ExecutedStepsPolicy(ep)
    out = cal.open_loop_sigma(policy, [ep], stride=2, n_samples=4)           # n_act from policy.cfg
    np.testing.assert_allclose(out.sigma, 0.0, atol=1e-20)
    # all H steps would see the unexecuted error: (H - n_act) / H of 1 rad^2 per joint pair
    full = cal.open_loop_sigma(policy, [ep], stride=2, n_samples=4, n_act=4)
    np.testing.assert_allclose(full.sigma, 0.5, rtol=1e-12)
    with pytest.raises(ValueError, match="n_act"):
        cal.open_loop_sigma(policy, [ep], stride=2, n_samples=4, n_act=5)


def _expert_path(n=60, dof=3):
    """A smooth expert joint path (n + 1, dof) with distinct states, about 0.02 rad a step."""
    t = np.arange(n + 1)[:, None]
    return np.concatenate([0.02 * t, 0.3 * np.sin(0.05 * t), 0.01 * t], axis=1)[:, :dof]


def _project_onto_expert(trajectory, expert_q, window):
    """cal.advance_cursor along a whole recorded trajectory (n + 1, dof), the cursor starting at 0, as
    blend_rollouts does it online -> the cursor (n + 1,) and the nearest-state distance (n + 1,)."""
    cursor = np.zeros(len(trajectory), dtype=np.int64)
    distance = np.zeros(len(trajectory))
    distance[0] = cal.nearest_expert_state(trajectory[0], expert_q, 0, window)[1]
    for i in range(1, len(trajectory)):
        cursor[i], distance[i] = cal.advance_cursor(trajectory[i], expert_q, int(cursor[i - 1]), window)
    return cursor, distance


def _tracked(trajectory, expert, min_steps=20):
    """Rollouts for one recorded trajectory, tracked as blend_rollouts does it."""
    cursor, error = _project_onto_expert(trajectory, expert, window=16)
    n = len(trajectory) - 1
    reference = expert[np.minimum(np.arange(n + 1), len(expert) - 1)]
    return cal.Rollouts(trajectory[None], reference[None], np.array([n]), np.array([n]), np.zeros(1, bool),
                        cursor=cursor[None], nearest_error=error[None], min_steps=min_steps)


def test_settling_error_is_the_nearest_state_distance_not_the_time_matched_one():
    expert = _expert_path()
    lagging = expert[np.maximum(np.arange(len(expert)) - 3, 0)]             # the same path, 3 steps behind
    roll = _tracked(lagging, expert)
    assert cal.settling_error(roll)[0] < 1e-12                              # on the path: no error
    np.testing.assert_array_equal(roll.cursor[0, 3:], np.arange(len(expert) - 3))   # the cursor lags too
    # the old rule (time-matched state) reads the pace difference as a large error
    dev = (roll.trajectory - roll.reference)[0, 13:41]
    assert math.sqrt(np.mean(np.sum(dev ** 2, axis=-1))) > 0.05
    # the error is measured over steps [settle_start, settle_end] only
    off = lagging.copy()
    off[:13, 1] += 5.0                                                      # a transient before step 13 ...
    off[41:, 1] += 5.0                                                      # ... and a jump after step 40
    off[13:41, 1] += 0.1                                                    # settled 0.1 rad beside the path
    x = cal.settling_error(_tracked(off, expert))[0]
    assert 0.03 < x <= 0.1 + 1e-12


def test_settling_error_is_the_rms_over_the_inclusive_window_of_recorded_steps():
    """settling_error's window exactly, on hand-made nearest-state errors e_t = t (rad): steps settle_start..
    settle_end, both included, and never past the last recorded step n (entries past it repeat its value, as
    blend_rollouts pads them); a rollout that stopped before settle_start takes steps 1..n (step 0, the start
    on the expert, and the padding out). Catches a window end or start one step off in either branch (the
    short-rollout one, `1:n + 1` -> `1:n - 1`, survived the other tests) and a mean instead of the RMS."""
    L = 60
    n_recorded = np.array([60, 30, 13, 10, 1])
    error = np.tile(np.arange(L + 1, dtype=np.float64), (len(n_recorded), 1))     # (B, L + 1): e_t = t
    for b, n in enumerate(n_recorded):
        error[b, n + 1:] = n                                                      # padded with the last
    B = len(n_recorded)
    zeros = np.zeros((B, L + 1, 3))
    roll = cal.Rollouts(zeros, zeros, np.full(B, L), n_recorded, np.zeros(B, bool),
                        cursor=np.zeros((B, L + 1), np.int64), nearest_error=error)
    rms = lambda steps: math.sqrt(np.mean(np.square(steps, dtype=np.float64)))    # noqa: E731
    expected = [rms(np.arange(13, 41)),    # settled: steps 13..40, 28 of them
                rms(np.arange(13, 31)),    # stopped at 30: steps 13..30
                rms(np.arange(13, 14)),    # stopped at 13 = settle_start: that one step
                rms(np.arange(1, 11)),     # stopped at 10, before the window: steps 1..10
                rms(np.arange(1, 2))]      # one step recorded: step 1
    np.testing.assert_allclose(cal.settling_error(roll, 13, 40), expected, rtol=1e-12)
    np.testing.assert_allclose(cal.settling_error(roll), expected, rtol=1e-12)      # the defaults: 13 and 40
    np.testing.assert_allclose(cal.settling_error(roll, 5, 8)[:2], [rms(np.arange(5, 9))] * 2, rtol=1e-12)


def test_cursor_is_monotone_and_advances_at_most_one_index_a_step():
    rng = np.random.default_rng(0)
    expert = _expert_path()
    for trajectory in (expert[::2], expert[::-1], expert + rng.normal(0, 0.05, expert.shape),
                       rng.normal(0, 1.0, expert.shape)):                   # too fast, backwards, noisy, random
        cursor, error = _project_onto_expert(trajectory, expert, window=16)
        steps = np.diff(cursor)
        assert np.all((steps == 0) | (steps == 1))
        assert cursor[0] == 0 and cursor.max() < len(expert)
        # the error is the distance to the nearest expert state within 8 steps of the cursor
        for i in (5, 17, 25):
            lo, hi = max(cursor[i] - 8, 0), min(cursor[i] + 9, len(expert))
            assert error[i] == pytest.approx(np.linalg.norm(expert[lo:hi] - trajectory[i], axis=1).min())
    # a rollout twice as fast moves the cursor one index a step, and its nearest-state error stays 0
    # while it is less than 8 steps ahead
    cursor, error = _project_onto_expert(expert[::2], expert, window=16)
    np.testing.assert_array_equal(cursor, np.arange(len(cursor)))
    assert np.all(error[:8] < 1e-12) and error[20] > 0


def test_rollouts_too_short_are_discarded():
    expert = _expert_path()
    assert not _tracked(expert[:21], expert).discarded[0]                  # 20 steps recorded: kept
    assert _tracked(expert[:20], expert).discarded[0]                      # 19 steps: too short
    assert _tracked(expert[:20], expert, min_steps=0).discarded[0] == False


# ----------------------------------------------------------------------------------------------
# Calibration record
# ----------------------------------------------------------------------------------------------

def _calibration():
    S = _random_covariances(6, 3, seed=4)
    W = 0.05
    return cal.Calibration(
        W=W, r=3.0, fit_note="fit", median_step=0.01, sigma_hat=S,
        sigma_alpha=cal.calibrated_sigma(S, W), episode_index=np.arange(6), timestep=np.arange(6) * 2,
        pooled=cal.pooled_sigma(S, W), blend_beta=np.linspace(0.05, 0.9, 13),
        blend_s=np.linspace(0.01, 0.98, 13), blend_x=np.linspace(0.0, 0.04, 13),
        blend_kept=np.arange(13) < 11, blend_episode=np.arange(13) % 4, blend_start=np.full(13, 5),
        W_ci=(0.04, 0.062))


def test_diverge_radius_is_the_authors_15_median_steps_in_radians():
    # a distance: 15 of the paper's median steps whatever our unit or rate; 15 of ours only without theirs
    assert cal.diverge_radius(15.0, 0.0245, 0.0176) == pytest.approx(0.264)
    assert cal.diverge_radius(15.0, 0.0245, 0.0176) / 0.0245 == pytest.approx(10.78, abs=0.01)
    assert cal.diverge_radius(15.0, 0.0245, 0.0166) == pytest.approx(0.249)          # the UR5 lever
    assert cal.diverge_radius(15.0, 0.0245, None) == pytest.approx(15 * 0.0245)
    assert cal.CalibrationConfig.diverge_threshold == 15.0


def test_plot_blend_fit_writes_a_figure(tmp_path):
    path = tmp_path / "fig4.png"
    cal.plot_blend_fit(_calibration(), None, path)
    assert path.stat().st_size > 10_000


# ----------------------------------------------------------------------------------------------
# The real modules: closed-loop rollouts in the planar env and one whole calibration
# ----------------------------------------------------------------------------------------------

def _tiny_policy(env, episodes):
    """A tiny untrained policy (normalizer fitted on the episodes)."""
    policy = diffusion.DiffusionPolicy(diffusion.PolicyConfig(
        obs_dim=env.obs_dim, dof=env.dof, horizon=16, n_act=8, K=10, down_dims=(8, 16), n_groups=4,
        step_embed_dim=16))
    policy.fit_normalizer(*diffusion.chunk_dataset(episodes, 16))
    return policy


@pytest.fixture(scope="module")
def planar():
    """The planar env, stand-in expert episodes (all expert, at least 32 steps), and a tiny untrained
    policy (normalizer fitted)."""
    env = envs.make_env("planar")
    episodes = [straight_line_episode(env, seed, expert_from=0) for seed in env.train_seeds(40)]
    episodes = [ep for ep in episodes if len(ep["q"]) >= 32][:4]
    assert len(episodes) == 4
    return env, episodes, _tiny_policy(env, episodes)


CFG = cal.CalibrationConfig(n_samples=2, n_act=10)                          # the tiny policy's H = 16


def _longest(episode, H=16):
    return max(diffusion.expert_runs(episode["expert"], H), key=lambda se: se[1] - se[0])


def test_blend_at_beta_zero_retraces_the_expert(planar):
    env, episodes, policy = planar
    ep = episodes[0]
    out = cal.blend_rollouts(env, policy, [(ep, _longest(ep))] * 2, [0.0, 0.0], CFG, torch.Generator().manual_seed(0),
                             0.4)
    T = len(ep["q"])
    assert np.all(out.rollouts.n_recorded == T - 1) and np.all(out.kept)
    # every per-step record spans the rollout's L + 1 states (a shorter one drops the last steps' errors silently)
    L = int(out.rollouts.n_steps.max())
    assert out.rollouts.nearest_error.shape == out.rollouts.cursor.shape == out.rollouts.trajectory.shape[:2] == (
        2, L + 1)
    np.testing.assert_allclose(out.rollouts.trajectory[0], ep["q"], atol=1e-12)   # time-matched, exact
    np.testing.assert_array_equal(out.x, 0.0)
    np.testing.assert_array_equal(out.s, 0.0)
    # several scenarios in one batched run: each rollout follows its own segment's expert
    jobs = [(e, diffusion.expert_runs(e["expert"], 16)[0]) for e in episodes[:3]]
    multi = cal.blend_rollouts(env, policy, jobs, np.zeros(3), cal.CalibrationConfig(n_samples=2, n_act=8), None, 0.5)
    for b, e in enumerate(episodes[:3]):
        n = len(e["q"]) - 1
        np.testing.assert_allclose(multi.rollouts.trajectory[b, :n + 1], e["q"], atol=1e-12)


def test_rollouts_refuse_episodes_from_another_scenario(planar):
    env, episodes, policy = planar
    wrong = dict(episodes[0], seed=episodes[1]["seed"])
    with pytest.raises(ValueError, match="does not reproduce"):
        cal.blend_rollouts(env, policy, [(wrong, _longest(wrong))], [0.5], CFG, None, 0.4)


def test_blend_rollouts_mark_divergence(planar):
    env, episodes, policy = planar
    out = cal.blend_rollouts(env, policy, [(episodes[0], _longest(episodes[0]))], [0.9], CFG,
                             torch.Generator().manual_seed(0), diverge_rad=1e-6)
    assert out.rollouts.diverged[0] and not out.kept[0]
    # discarded, but run to the segment's full length (the authors' blended episodes): its settling error is
    # the RMS over the whole settling window, as for a kept rollout, not cut where it crossed the radius
    start, end = _longest(episodes[0])
    assert out.rollouts.n_recorded[0] == min(end, len(episodes[0]["q"]) - 1) - start
    e = out.rollouts.nearest_error[0, cal.CalibrationConfig.settle_start:cal.CalibrationConfig.settle_end + 1]
    assert out.x[0] == pytest.approx(np.sqrt(np.mean(e ** 2))) and out.x[0] > 0


def _line_into_an_obstacle(env, seeds, past=3, speed=0.8):
    """An all-expert episode that moves in a straight joint-space line toward the goal configuration
    nearest its start (speed times the joint step limit) and runs `past` steps into the first obstacle
    it meets, in the first of the scenarios where the line meets one; and its first contact step."""
    for seed in seeds:
        env.reset(seed=int(seed))
        q0, goals = env.q, env.goal_configurations()
        target = goals[np.argmin(np.abs(goals - q0).max(axis=1))]
        n = int(np.ceil(np.abs(target - q0).max() / (speed * env.max_step)))
        line = q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (target - q0)    # (n + 1, dof)
        hits = env.in_collision(line)
        if hits.any() and int(np.argmax(hits)) + past >= 32:
            q = line[:int(np.argmax(hits)) + past]
            q_prev = np.concatenate([q[:1], q[:-1]])
            episode = {"obs": env.make_obs(q, q_prev), "q": q, "action": np.concatenate([q[1:], q[-1:]]),
                       "expert": np.ones(len(q), dtype=bool), "seed": int(seed)}
            return episode, int(np.argmax(hits))
    raise AssertionError("no straight line meets an obstacle")


def test_contacts_never_discard_a_rollout(planar):
    env, _, policy = planar
    # an expert path that runs 3 steps into an obstacle: at beta = 0 the rollout retraces it exactly
    ep, first_contact = _line_into_an_obstacle(env, env.train_seeds(80))
    kept = cal.blend_rollouts(env, policy, [(ep, _longest(ep))], [0.0], CFG, None, 0.4)
    assert env.in_collision(kept.rollouts.trajectory[0]).any()                # it touched the obstacle ...
    assert kept.kept[0] and kept.x[0] == 0.0                                 # ... and was kept
    assert kept.rollouts.n_recorded[0] == len(ep["q"]) - 1 > first_contact    # ran through the contact


def test_calibrate_end_to_end_on_the_planar_env(planar, tmp_path):
    env, episodes, policy = planar
    unit = envs.median_step(episodes)
    cfg = cal.CalibrationConfig(n_samples=2, n_act=10, stride=4, bootstrap=20)
    c = cal.calibrate(env, policy, episodes, unit, cfg, torch.Generator().manual_seed(0))
    M = len(c.timestep)
    assert c.sigma_hat.shape == c.sigma_alpha.shape == (M, 3, 3) and M > 10
    segments = cal.blend_schedule(episodes, policy.cfg.horizon, cfg)[1]
    long_enough = {e for e, ep in enumerate(episodes) for a, b in diffusion.expert_runs(ep["expert"], policy.cfg.horizon)
                   if b - a >= cfg.min_rollout_steps}
    assert len(c.blend_beta) == 13 * len({(e, seg) for e, seg in segments})
    assert set(c.blend_episode) == long_enough                                # one rollout per ratio from each
    assert all(np.sum(c.blend_beta == b) == len(long_enough) for b in cfg.betas)
    for value in (c.W, *c.pooled.ravel(), *c.blend_x, *c.sigma_per_joint):
        assert math.isfinite(value)
    np.testing.assert_allclose(np.trace(c.sigma_alpha, axis1=1, axis2=2), c.W ** 2, rtol=1e-9)
    assert (c.W_ci is None) == (c.r is None)                                 # an interval with every fit
    assert c.r is not None or c.fit_note.startswith("FALLBACK")                # a fallback says so
    assert c.W_ci is None or c.W_ci[0] <= c.W_ci[1]
    assert np.trace(c.pooled) == pytest.approx(c.W ** 2)
    # deterministic: same seed, same calibration
    again = cal.calibrate(env, policy, episodes, unit, cfg, torch.Generator().manual_seed(0))
    assert calibration_to_json(again) == calibration_to_json(c)
    assert c.paper_median_step == envs.PlanarReacher.paper_median_step           # recorded for the report
    json.dumps(calibration_to_json(c))
    cal.plot_blend_fit(c, unit, tmp_path / "fig4.png")
    cal.plot_method_overview(env, episodes[0], c, policy, tmp_path / "fig2.png", n_samples=2,
                             generator=torch.Generator().manual_seed(1))
    assert (tmp_path / "fig2.png").stat().st_size > 20_000


def test_calibrate_falls_back_when_every_blend_rollout_diverges(planar):
    env, episodes, policy = planar
    unit = envs.median_step(episodes)
    cfg = cal.CalibrationConfig(n_samples=2, n_act=10, stride=4, diverge_threshold=1e-9)
    c = cal.calibrate(env, policy, episodes[:2], unit, cfg, torch.Generator().manual_seed(0))
    assert not c.blend_kept.any()
    assert c.r is None and c.fit_note.startswith("FALLBACK")
    assert c.W_ci is None                                                     # no fit, no interval
    assert c.W ** 2 == pytest.approx(np.trace(c.sigma_hat.mean(axis=0)))       # ||W||^2 = tr(Sigma_bar)
    np.testing.assert_allclose(c.pooled, c.sigma_hat.mean(axis=0))            # i.e. Sigma_bar unscaled


def test_calibrate_holds_W_within_the_authors_fit_bounds(planar, monkeypatch):
    """When the surviving ratios all sit at small s the Eq. (12) fit can extrapolate W far beyond the data;
    W is held within the authors' curve_fit bounds, [1, 60] of the paper's median steps, and the note says so."""
    env, episodes, policy = planar
    unit = envs.median_step(episodes)
    paper = envs.PlanarReacher.paper_median_step
    cfg = cal.CalibrationConfig(n_samples=2, n_act=10, stride=4, diverge_threshold=1e3, bootstrap=5)
    monkeypatch.setattr(cal, "fit_equilibrium", lambda s, x, **kw: cal.EquilibriumFit(1e5 * unit, 1e2, len(s), 0.0))
    c = cal.calibrate(env, policy, episodes[:2], unit, cfg, torch.Generator().manual_seed(0))
    assert c.W == pytest.approx(60 * paper)                                  # in rad: the bound in their unit
    assert c.fit_note.startswith("fit, W at the fit's bound 60") and "extrapolated to" in c.fit_note
    assert c.W_ci == (pytest.approx(c.W), pytest.approx(c.W))                # bounded like W
    assert np.trace(c.pooled) == pytest.approx(c.W ** 2)
    monkeypatch.setattr(cal, "fit_equilibrium", lambda s, x, **kw: cal.EquilibriumFit(0.01 * unit, 0.1, len(s), 0.0))
    c = cal.calibrate(env, policy, episodes[:2], unit, cfg, torch.Generator().manual_seed(0))
    assert c.W == pytest.approx(1 * paper) and "bound 1 " in c.fit_note       # the lower bound
    monkeypatch.setattr(cal, "fit_equilibrium", lambda s, x, **kw: cal.EquilibriumFit(5 * paper, 0.1, len(s), 0.0))
    c = cal.calibrate(env, policy, episodes[:2], unit, cfg, torch.Generator().manual_seed(0))
    assert c.W == pytest.approx(5 * paper) and c.fit_note == "fit"           # inside the bounds: as fitted


def test_ratio_cells_average_the_kept_rollouts_per_ratio_and_need_three():
    """The authors' cells: per ratio the RMS of the kept rollouts' settling errors; a ratio with fewer than
    min_survivors kept rollouts is not fitted (and its discarded rollouts never enter a mean)."""
    betas = np.array([0.1, 0.1, 0.1, 0.1, 0.5, 0.5, 0.5, 0.9])
    s = np.array([0.01] * 4 + [0.3] * 3 + [0.9])
    x = np.array([1.0, 2.0, 2.0, 100.0, 3.0, 4.0, 5.0, 7.0])
    kept = np.array([True, True, True, False, True, True, False, True])
    cells = cal.ratio_cells(betas, s, x, kept, min_survivors=3)
    np.testing.assert_allclose(cells.betas, [0.1, 0.5, 0.9])
    np.testing.assert_allclose(cells.s, [0.01, 0.3, 0.9])
    np.testing.assert_allclose(cells.x, [np.sqrt((1 + 4 + 4) / 3), np.sqrt((9 + 16) / 2), 7.0])  # RMS, not mean
    assert cells.n.tolist() == [3, 2, 1] and cells.fitted.tolist() == [True, False, False]
    assert cells.spread[0] == pytest.approx(np.std([1.0, 2.0, 2.0], ddof=1)) and cells.spread[2] == 0.0
    assert np.isnan(cal.ratio_cells(betas, s, x, np.zeros(8, bool)).x).all()  # nothing kept: no value


def test_blend_schedule_starts_every_ratio_from_every_long_enough_segment():
    """One rollout per ratio from each expert segment the settling window can use (>= min_rollout_steps),
    longest first."""
    def episode(lengths):
        expert = np.concatenate([np.r_[np.ones(n, bool), np.zeros(5, bool)] for n in lengths])
        return {"expert": expert}
    episodes = [episode([30, 12]), episode([25, 40])]                        # segments of >= H = 10 steps
    cfg = cal.CalibrationConfig(n_samples=4, n_act=10, min_rollout_steps=20)
    beta, jobs = cal.blend_schedule(episodes, 10, cfg)
    lengths = sorted({(e, b - a) for e, (a, b) in jobs}, key=lambda item: -item[1])
    assert [n for _, n in lengths] == [40, 30, 25]                           # the 12-step one is too short
    assert len(beta) == 13 * 3 and all(np.sum(beta == b) == 3 for b in cfg.betas)
    beta, jobs = cal.blend_schedule(episodes, 10, cal.CalibrationConfig(n_samples=4, n_act=10, min_rollout_steps=50))
    assert {b - a for _, (a, b) in jobs} == {40} and len(beta) == 13          # none long enough: the longest
    late = [episode([30, 12]), episode([12, 12, 12, 25])]   # a shorter segment far into its episode (steps 51-76)
    beta, jobs = cal.blend_schedule(late, 10, cal.CalibrationConfig(n_samples=4, n_act=10, min_rollout_steps=20))
    assert [b - a for _, (a, b) in jobs[:2]] == [30, 25]                     # by length, not by position
    beta, jobs = cal.blend_schedule(late, 10, cal.CalibrationConfig(n_samples=4, n_act=10, min_rollout_steps=50))
    assert {(e, b - a) for e, (a, b) in jobs} == {(0, 30)}                   # the fallback is the longest one


def test_plot_method_overview_draws_the_3d_env_in_the_top_view(tmp_path):
    """Fig. 2 for EngineReach3D: the same panels on the top view (x, y), no arm drawing."""
    env = environments.make_env("engine3d")
    episodes = [straight_line_episode(env, seed) for seed in env.train_seeds(6)]
    episode = max(episodes, key=lambda ep: len(ep["q"]))
    assert env.dim == 3 and len(episode["q"]) >= 30
    policy = _tiny_policy(env, [episode])
    unit = envs.median_step(episodes)
    S = _random_covariances(6, env.dof, seed=5) * unit ** 2
    W = 3 * unit
    c = cal.Calibration(
        W=W, r=2.0, fit_note="fit", median_step=unit, sigma_hat=S, sigma_alpha=cal.calibrated_sigma(S, W),
        episode_index=np.zeros(6, dtype=np.int64), timestep=np.arange(6) * 2, pooled=cal.pooled_sigma(S, W),
        blend_beta=np.linspace(0.05, 0.9, 13), blend_s=np.linspace(0.01, 0.98, 13),
        blend_x=np.linspace(0.0, W, 13), blend_kept=np.ones(13, dtype=bool),
        blend_episode=np.zeros(13, dtype=np.int64), blend_start=np.full(13, 5))
    path = tmp_path / "fig2_engine3d.png"
    cal.plot_method_overview(env, episode, c, policy, path, n_samples=2, generator=torch.Generator().manual_seed(1))
    assert path.stat().st_size > 20_000


# ----------------------------------------------------------------------------------------------
# End to end on a policy of known W: the paper's model of the blend (Eqs. 8-11) as a test double
# ----------------------------------------------------------------------------------------------

RAIL_SPEED = 0.02                                                            # rad a step along joint 0


class RailEnv:
    """Test double of an env: three joints that move exactly to the commanded joint targets (no limits, no
    obstacles, one scene for every seed); obs = (q, q_prev). The expert's paths run along joint 0."""
    dof, obs_dim = 3, 6
    paper_median_step = max_parallel = None  # no paper unit; any number in lockstep

    def reset(self, seed=None):
        self.set_state(np.zeros(3), np.zeros(3))

    def make_obs(self, q, q_prev):
        return np.concatenate([q, q_prev], axis=-1).astype(np.float32)      # (..., 6)

    def set_state(self, q, q_prev):
        self.q, self.q_prev = np.array(q, dtype=np.float64), np.array(q_prev, dtype=np.float64)

    def clip_action(self, q, action):
        return np.asarray(action, dtype=np.float64)

    def step(self, action):
        self.set_state(action, self.q)
        return self.make_obs(self.q, self.q_prev), 0.0, False, False, {"collision": False}


def _rail_episode(env, seed, segments, gap=8):
    """An intervention episode on the rail: expert segments of the given lengths (steps) with `gap` policy
    steps between them; the arm moves along joint 0 from 0.1 * seed at RAIL_SPEED a step, joints 1-2 at 0."""
    expert = np.concatenate([np.r_[np.zeros(gap if i else 0, bool), np.ones(n, bool)]
                             for i, n in enumerate(segments)] + [np.zeros(1, bool)])
    q = np.zeros((len(expert), 3))
    q[:, 0] = 0.1 * seed + RAIL_SPEED * np.arange(len(expert))
    q_prev = np.concatenate([q[:1], q[:-1]])
    return {"obs": env.make_obs(q, q_prev), "q": q, "action": np.concatenate([q[1:], q[-1:]]),
            "expert": expert, "seed": seed}


class OffsetPolicy:
    """Test double of a diffusion policy whose settling error is a known W, under the paper's model of the
    blend (Eqs. 8-11), for the real partial_denoise.

    Its own chunk from q keeps the expert's pace along the rail and converges to the rail's offset by W
    (a vector on joints 1-2, across the rail) at `gain` a step: offset (1 - g)^j x + (1 - (1 - g)^j) W at
    chunk step j = 1..H, x = q's offset. Its reverse process is the ideal blend of Eq. (8): a chunk diffused
    from the expert's a* to paper step k_sw comes back as s * own chunk + (1 - s) * a*, s = 1 - alphabar_{k_sw}
    (draw_noise gives zeros, so a* is read off the diffused chunk exactly). The recorded expert chunk is back
    on the rail in one step (K* = 1), so at n_act = 1 the blended loop x' = s ((1 - g) x + g W) settles at
    Eq. (12), x = W s / (s + r (1 - s)), with r = K*/K_theta = 1/g.
    """

    def __init__(self, W, gain, K=20, horizon=20, n_act=1):
        self.W = torch.tensor([0.0, *W], dtype=torch.float64)               # (3,) nothing along the rail
        self.gain = gain
        self.cfg = SimpleNamespace(obs_dim=6, dof=3, horizon=horizon, n_act=n_act, K=K)
        self.schedule = diffusion.make_schedule(K)
        self.device = torch.device("cpu")

    def own_chunk(self, obs):
        q = torch.as_tensor(obs, dtype=torch.float64)[:, :3]                 # (B, 3)
        j = torch.arange(1, self.cfg.horizon + 1, dtype=torch.float64)[None, :, None]   # (1, H, 1)
        keep = (1.0 - self.gain) ** j
        chunk = keep * q[:, None] + (1.0 - keep) * self.W                    # (B, H, 3): the offset -> W
        chunk[..., 0] = q[:, None, 0] + RAIL_SPEED * j[..., 0]               # along the rail: the expert's pace
        return chunk

    def sample(self, obs, generator=None, use_ema=True):
        return self.own_chunk(obs).numpy()

    def normalize_obs(self, obs):
        return obs

    def normalize_actions(self, a, obs=None):
        return a

    def unnormalize_actions(self, a, obs=None):
        return a

    def draw_noise(self, B, generator=None):
        return torch.zeros(B, self.cfg.K + 1, self.cfg.horizon, self.cfg.dof)

    def reverse_process(self, a_k, k_start, obs_norm, z, use_ema=True):
        level = k_start.clamp(min=0)                                         # (B,) code level of a_k
        alphabar = self.schedule.alphas_cumprod[level].double()[:, None, None]
        expert = a_k.double() / self.schedule.sqrt_alphas_cumprod[level].double()[:, None, None]
        blend = (1.0 - alphabar) * self.own_chunk(obs_norm) + alphabar * expert   # Eq. (8), s = 1 - alphabar
        return torch.where((k_start >= 0)[:, None, None], blend, a_k.double())


def test_calibrate_recovers_a_known_W_end_to_end():
    """calibrate (open-loop Sigma_hat, blended rollouts through the real partial_denoise and closed loop,
    settling errors, per-ratio cells, the Eq. (12) fit, Eqs. 14-16) on a policy of known W = 0.2 rad and
    r = 4 (OffsetPolicy): W within 2 %, r within 10 %. Why 2 %: the blended loop settles exactly at Eq. (12);
    the only departure is the transient's remnant in the settling window, (s (1 - g))^13 <= 0.75^13 = 2 %
    of x at the window's first step and far less in its RMS (measured: W off by 0.24 %, r by 0.4 %).
    Catches a settling window that takes in the transient, an s that is not the noise the blend injected
    (noise_fraction against partial_denoise's level), a wrong Eq. (12) in the fit, and W not carried into
    Sigma^alpha."""
    env, W, gain = RailEnv(), np.array([0.12, 0.16]), 0.25                    # ||W|| = 0.2 rad
    policy = OffsetPolicy(W, gain)
    episodes = [_rail_episode(env, 0, [60]), _rail_episode(env, 1, [45, 50]), _rail_episode(env, 2, [41])]
    cfg = cal.CalibrationConfig(n_samples=4, n_act=1)
    c = cal.calibrate(env, policy, episodes, RAIL_SPEED, cfg, torch.Generator().manual_seed(0))
    assert c.fit_note == "fit" and c.blend_kept.all() and len(c.blend_kept) == 13 * 4
    assert c.W == pytest.approx(0.2, rel=0.02)
    assert c.r == pytest.approx(1 / gain, rel=0.1)
    assert c.W_ci[0] <= c.W <= c.W_ci[1] and c.W_ci[1] - c.W_ci[0] < 0.01 * c.W   # the rollouts agree
    # every rollout settled where Eq. (12) puts it, at its own noise fraction
    np.testing.assert_allclose(c.blend_x, cal.equilibrium(c.blend_s, 0.2, 1 / gain), rtol=0.02, atol=1e-9)
    # Eqs. (14)-(16): the open-loop error (g W each step on the expert data) scaled to ||W||^2, W's direction kept
    # (atol: the float32 observations put ~1e-8 rad along the rail)
    Ww = np.r_[0.0, W]
    np.testing.assert_allclose(c.pooled, c.W ** 2 * np.outer(Ww, Ww) / 0.04, atol=1e-6)
    np.testing.assert_allclose(c.sigma_alpha, np.broadcast_to(c.pooled, c.sigma_alpha.shape), atol=1e-6)


def test_the_smoke_profile_calibration_fits_W():
    """CI's run (`python dagger.py --profile smoke`, .ci/run) fits W by Eq. (12) instead of falling back to the
    open-loop error: the smoke profile's calibration config (dagger.calibration_config) on a small round of 4
    intervention segments long enough to keep (the smoke round had 9) and a policy whose rollouts all stay on
    the route (OffsetPolicy at the smoke's K, H and n_act). Catches a smoke profile that starts fewer than
    min_survivors = 3 blended rollouts per ratio (one segment a ratio did: 1 each, W never fitted in CI)."""
    smoke = profiles.PROFILES["smoke"]
    cfg = dagger.calibration_config(smoke)
    env = RailEnv()
    policy = OffsetPolicy([0.12, 0.16], 0.25, K=smoke.K, horizon=smoke.horizon, n_act=smoke.n_act)
    episodes = [_rail_episode(env, 0, [25, 30]), _rail_episode(env, 1, [45]), _rail_episode(env, 2, [22, 12])]
    c = cal.calibrate(env, policy, episodes, RAIL_SPEED, cfg, torch.Generator().manual_seed(0))
    cells = cal.ratio_cells(c.blend_beta, c.blend_s, c.blend_x, c.blend_kept, cfg.min_survivors)
    assert cells.n.min() >= cfg.min_survivors                                 # every ratio can be fitted
    assert c.fit_note == "fit" and c.r is not None and c.W_ci is not None


def test_W_interval_resamples_the_kept_rollouts_within_each_ratio(monkeypatch):
    """Every bootstrap resample of W_interval holds, per ratio, exactly as many rollouts as were kept at that ratio,
    drawn from that ratio's kept rollouts only (with replacement), and the interval holds the point fit. Fails if a
    ratio's group takes other ratios' rollouts (a resample's counts per ratio then drift, and ratios near
    min_survivors drop out of some fits), or if a discarded rollout enters a resample."""
    rng = np.random.default_rng(0)
    betas = np.repeat([0.2, 0.4, 0.6, 0.8], [3, 5, 4, 6])  # 3: exactly min_survivors at the first ratio
    s = 1.0 - (1.0 - betas) ** 2                            # a noise fraction per ratio, rising with beta
    x = cal.equilibrium(s, 0.2, 4.0) * (1.0 + 0.2 * rng.standard_normal(len(betas)))
    kept = np.ones(len(betas), dtype=bool)
    kept[[1, 9]] = False
    x[~kept] = 99.0                                         # a discarded rollout: never resampled
    seen = []
    real = cal.ratio_cells

    def spy(b, *args, **kwargs):
        seen.append(dict(zip(*np.unique(b, return_counts=True))))
        assert 99.0 not in args[1]
        return real(b, *args, **kwargs)
    monkeypatch.setattr(cal, "ratio_cells", spy)
    cfg = cal.CalibrationConfig(n_act=10, bootstrap=50)
    lo, hi = cal.W_interval(betas, s, x, kept, (0.01, 5.0), cfg)
    expected = {b: int(np.sum((betas == b) & kept)) for b in np.unique(betas)}
    assert len(seen) == 50 and all(counts == expected for counts in seen)
    monkeypatch.setattr(cal, "ratio_cells", real)
    cells = real(betas, s, x, kept, cfg.min_survivors)
    W = cal.fit_equilibrium(cells.s[cells.fitted], cells.x[cells.fitted], r_bounds=cfg.r_bounds).W
    assert lo < W < hi
    fits = []  # the interval is the 2.5th and 97.5th percentiles of the resamples' fitted W (a 95 % interval)
    real_fit = cal.fit_equilibrium
    monkeypatch.setattr(cal, "fit_equilibrium", lambda *a, **k: fits.append(real_fit(*a, **k)) or fits[-1])
    assert cal.W_interval(betas, s, x, kept, (0.01, 5.0), cfg) == (lo, hi)
    assert (lo, hi) == tuple(np.percentile(np.clip([f.W for f in fits], 0.01, 5.0), [2.5, 97.5]))


def test_fig4s_legend_is_off_the_data_and_leaves_the_plot_the_figures_width(tmp_path, monkeypatch):
    """Fig. 4's legend (eight long entries) lies wholly outside the axes, and the axes keep at least 70 % of the
    saved picture's width. Fails if the legend is drawn on the data (it hid half of it) or beside the plot, where
    it took half the figure's width and squeezed the plot."""
    import matplotlib.figure
    saved = []
    original = matplotlib.figure.Figure.savefig

    def keep(fig, *args, **kwargs):
        saved.append(fig)
        return original(fig, *args, **kwargs)
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    cal.plot_blend_fit(_calibration(), None, tmp_path / "fig4.png")
    (fig,) = saved
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    renderer = FigureCanvasAgg(fig).get_renderer()                                # (plt.close left a bare canvas)
    ax = fig.axes[0]
    legend = ax.get_legend()
    assert legend is not None and len(legend.get_texts()) >= 6
    box, plot = legend.get_window_extent(renderer), ax.get_window_extent(renderer)
    assert not box.overlaps(plot)                                                 # off the data
    picture = fig.get_tightbbox(renderer)                                         # what bbox_inches="tight" saves
    assert plot.width / (picture.width * fig.dpi) >= 0.7
