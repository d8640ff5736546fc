"""Exercise 5: the open-loop Sigma_hat_t of DART's Eq. (1), measured along recorded expert data
(calibrate.open_loop_sigma; paper Sec. IV-D, Fig. 2a).

A scripted stand-in for the policy returns the expert's own chunk plus a deviation we choose, so the
covariance Eq. (1) must produce is known exactly (or, with random deviations, in expectation).
"""
from types import SimpleNamespace

import numpy as np
import pytest

from calibrate import expert_chunk, open_loop_sigma

H, DOF, T = 4, 3, 30


def episode(seed=0):
    rng = np.random.default_rng(seed)
    q = np.cumsum(rng.normal(0.0, 0.05, (T, DOF)), axis=0)
    return {"obs": np.arange(T, dtype=np.float32)[:, None],       # obs[t] = [t]: the stand-in reads t back
            "q": q, "action": np.concatenate([q[1:], q[-1:]]), "expert": np.ones(T, dtype=bool), "seed": 0}


class ScriptedPolicy:
    """sample(obs) = the expert chunk at step t = obs[:, 0] plus deviation(t, rng) (H, DOF)."""

    def __init__(self, ep, deviation, seed=0):
        self.cfg = SimpleNamespace(horizon=H)
        self.ep, self.deviation, self.rng = ep, deviation, np.random.default_rng(seed)
        self.rows_seen = []

    def sample(self, obs, generator=None):
        t = np.asarray(obs)[:, 0].astype(int)
        self.rows_seen.append(t)
        actions = np.asarray(self.ep["action"])
        return np.stack([expert_chunk(actions, int(ti), H) + self.deviation(int(ti), self.rng) for ti in t])


def pattern(t, rng):
    """A deterministic deviation per step: Eq. (1) is then exactly mean_h d_h d_h^T."""
    h = np.arange(H)[:, None]
    return 0.01 * np.array([1.0, -2.0, 0.5]) * (h + 1) + 0.002 * t * np.array([0.0, 1.0, 1.0]) * np.cos(h)


def test_eq1_is_the_mean_outer_product_of_the_chunk_deviations():
    ep = episode()
    policy = ScriptedPolicy(ep, pattern)
    steps = open_loop_sigma(policy, [ep], stride=2, n_samples=3)
    assert np.array_equal(steps.timestep, np.arange(0, T, 2))           # every other step (Fig. 2a)
    assert np.all(steps.episode_index == 0)
    seen = np.concatenate(policy.rows_seen)
    assert np.array_equal(np.sort(seen), np.repeat(np.arange(0, T, 2), 3))   # n_samples rows per step
    for sigma, t in zip(steps.sigma, steps.timestep):
        d = pattern(int(t), None)                                       # (H, DOF)
        assert np.allclose(sigma, d.T @ d / H, rtol=1e-9, atol=1e-15)


def test_eq1_is_uncentered_and_averages_over_samples():
    """Random deviations m + L z: Eq. (1) compares with the expert, not with the policy's mean, so
    Sigma_hat -> L L^T + m m^T (a centered covariance would miss m m^T)."""
    L = np.array([[0.03, 0.0, 0.0], [0.01, 0.02, 0.0], [0.0, -0.01, 0.015]])
    m = np.array([0.02, -0.01, 0.0])
    ep = episode(1)
    policy = ScriptedPolicy(ep, lambda t, rng: m + rng.standard_normal((H, DOF)) @ L.T, seed=2)
    steps = open_loop_sigma(policy, [ep], stride=1, n_samples=400)
    assert steps.sigma.shape == (T, DOF, DOF)
    assert np.allclose(steps.sigma, np.swapaxes(steps.sigma, 1, 2))
    expected = L @ L.T + np.outer(m, m)
    assert np.allclose(steps.sigma.mean(axis=0), expected, atol=0.03 * np.trace(expected))
    assert np.abs(steps.sigma[0] - expected).max() < 0.15 * np.trace(expected)   # each step, n*H = 1600 draws


def test_eq1_averages_only_the_executed_steps():
    """Eq. (1) averages over the n_act executed steps of each chunk, not all H: the rest is re-planned before it
    runs. A policy with n_act = 2 < H = 4 (and, the same, an explicit n_act=2 to a policy without one) gives
    mean_{h < 2} d_h d_h^T of the deterministic pattern. Fails on a solution that ignores n_act (averages all H
    steps) or that keeps the first n_act steps but divides by H."""
    ep = episode(2)
    n_act = 2
    expected = lambda t: pattern(t, None)[:n_act].T @ pattern(t, None)[:n_act] / n_act   # (DOF, DOF)
    executing = ScriptedPolicy(ep, pattern)
    executing.cfg = SimpleNamespace(horizon=H, n_act=n_act)
    for policy, kwargs in ((executing, {}), (ScriptedPolicy(ep, pattern), {"n_act": n_act})):
        steps = open_loop_sigma(policy, [ep], stride=3, n_samples=2, **kwargs)
        assert len(steps.timestep) == 10
        for sigma, t in zip(steps.sigma, steps.timestep):
            assert np.allclose(sigma, expected(int(t)), rtol=1e-9, atol=1e-15)
            everything = pattern(int(t), None)
            assert not np.allclose(sigma, everything.T @ everything / H, rtol=1e-3)   # all H steps differ
        assert steps.samples.shape == (10, 2, H, DOF)                   # the whole chunks still come back
