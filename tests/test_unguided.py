"""Tests of experiment/unguided.py: the unguided closed-loop control (Sigma_bar from unguided rollouts, Eq. 16)."""

import math

import numpy as np
import pytest
import torch

import calibrate as cal
import diffusion
import envs
from experiment import unguided


@pytest.fixture(scope="module")
def planar():
    """The planar env, 4 stand-in expert episodes (all expert, >= 32 steps), a tiny untrained policy (normalizer
    fitted) and its calibration."""
    env = envs.make_env("planar")
    episodes = [envs.straight_line_episode(env, seed, expert_from=0) for seed in env.train_seeds(40)]
    episodes = [ep for ep in episodes if len(ep["q"]) >= 32][:4]
    policy = diffusion.DiffusionPolicy(diffusion.PolicyConfig(
        obs_dim=env.obs_dim, dof=env.dof, horizon=16, n_act=8, K=10, down_dims=(8, 16), n_groups=4,
        step_embed_dim=16))
    policy.fit_normalizer(*diffusion.chunk_dataset(episodes, 16))
    unit = envs.median_step(episodes)
    c = cal.calibrate(env, policy, episodes, unit, cal.CalibrationConfig(n_samples=2, n_act=10, stride=4, bootstrap=5),
                      torch.Generator().manual_seed(0))
    return env, episodes, policy, unit, c


def test_unguided_pooled_is_scaled_to_W_and_deterministic(planar):
    env, episodes, policy, unit, c = planar
    said = []
    pooled = unguided.unguided_pooled(env, policy, episodes, c, 10, torch.Generator().manual_seed(0), unit,
                                      n_segments=3, log=said.append)
    assert pooled.shape == (3, 3) and all(math.isfinite(v) for v in pooled.ravel())
    assert np.trace(pooled) == pytest.approx(c.W ** 2)                       # Eq. (16): scaled to ||W||^2
    np.testing.assert_allclose(pooled, pooled.T)
    assert any("per-joint sigma" in line and "paper median steps" in line for line in said)
    again = unguided.unguided_pooled(env, policy, episodes, c, 10, torch.Generator().manual_seed(0), unit,
                                     n_segments=3, log=lambda msg: None)
    np.testing.assert_array_equal(again, pooled)


def test_unguided_sigma_pools_the_deviations_before_divergence(planar):
    """A policy that replays the expert chunk plus a constant offset: Sigma_bar is the mean of d d^T over the
    executed steps, uncentered; a rollout is cut at its first diverged step."""
    env, episodes, _, _, _ = planar

    class Replay:
        cfg = type("cfg", (), {"horizon": 16})

        def sample(self, obs, generator=None):
            return np.repeat(env_q(obs)[:, None], 16, axis=1) + 0.01     # hold still, 0.01 rad off

    def env_q(obs):
        return np.asarray(obs, dtype=np.float64)[:, :3]                  # the planar obs starts with q

    sigma = unguided.unguided_sigma(env, Replay(), episodes, 8, diverge_rad=10.0, max_segments=2)
    assert sigma.shape == (3, 3) and np.all(np.linalg.eigvalsh(sigma) >= -1e-15)
    # every rollout diverges at once: nothing usable
    assert unguided.unguided_sigma(env, Replay(), episodes, 8, diverge_rad=1e-9) is None


def test_unguided_pooled_falls_back_when_every_rollout_diverges(planar, monkeypatch):
    env, episodes, policy, unit, c = planar
    monkeypatch.setattr(cal.CalibrationConfig, "diverge_threshold", 1e-9)
    said = []
    assert unguided.unguided_pooled(env, policy, episodes, c, 10, torch.Generator().manual_seed(0), unit,
                                    n_segments=2, log=said.append) is None
    assert any("stands in" in line for line in said)
