"""Exercise 3: partial denoising (partial diffusion) as the learned blend f_theta(a*, beta | o) of Eq. (4),
with its index convention (partial_denoise.switch_step, partial_denoise.partial_denoise; paper Sec.
IV-B, IV-C, Fig. 3). Paper level k_sw = ToInteger(beta K) is code index k_sw - 1; k_sw reverse steps run."""
import math

import numpy as np
import pytest
import torch

from diffusion import DiffusionPolicy, PolicyConfig
from partial_denoise import partial_denoise, switch_step


class KnownEpsPolicy(DiffusionPolicy):
    """A DiffusionPolicy whose noise prediction is eps_fn(a_k, k (B,)), with an identity normalizer;
    it records the (level, input) of every network call."""

    def __init__(self, eps_fn, H=4, dof=2, K=100):
        super().__init__(PolicyConfig(obs_dim=2 * dof, dof=dof, horizon=H, n_act=1, K=K, down_dims=(4,), n_groups=4,
                                      step_embed_dim=4))
        self.eps_fn, self.calls = eps_fn, []

    def encode(self, obs_norm, use_ema=True):
        return obs_norm

    def predict_eps(self, a_k_norm, k, features, use_ema=True):
        k = torch.full((a_k_norm.shape[0],), int(k)) if not torch.is_tensor(k) else k
        self.calls.append((k.clone(), a_k_norm.clone()))
        return self.eps_fn(a_k_norm, k)


def zero_eps(a, k):
    return torch.zeros_like(a)


def test_switch_step_is_toInteger_beta_K():
    assert switch_step(0.0, 100) == 0 and switch_step(1.0, 100) == 100 and switch_step(0.3, 10) == 3
    assert switch_step(0.29, 100) == 29              # 0.29 * 100 = 28.999999999999996 in floating point
    assert switch_step(0.005, 100) == 1 and switch_step(0.015, 100) == 2   # halves go up: monotone in beta
    k = switch_step(np.linspace(0, 1, 1001), 100)
    assert k.dtype == np.int64 and np.all(np.diff(k) >= 0) and np.all(np.abs(k - np.linspace(0, 100, 1001)) <= 0.5)
    assert isinstance(switch_step(0.5, 100), int)


def test_the_first_reverse_step_receives_the_level_it_is_told():
    policy = KnownEpsPolicy(zero_eps)
    n, a_star, beta = 20_000, 0.3, 0.03                              # k_sw = 3: neighbouring levels differ a lot
    partial_denoise(policy, np.zeros((n, 4)), np.full((n, 4, 2), a_star), beta,
                    generator=torch.Generator().manual_seed(0))
    assert [int(k[0]) for k, _ in policy.calls] == [2, 1, 0]          # k_sw steps, code levels k_sw - 1 .. 0
    k_first, a_first = policy.calls[0]
    abar = policy.schedule.alphas_cumprod[int(k_first[0])].item()
    assert a_first.mean().item() == pytest.approx(math.sqrt(abar) * a_star, abs=3e-4)
    assert a_first.var().item() == pytest.approx(1 - abar, rel=0.03)  # one level off would be > 20 % off


@pytest.mark.parametrize("beta", [0.03, 0.1])
def test_error_variance_of_a_zero_noise_prediction(beta):
    """With eps_theta = 0 each reverse step is a / sqrt(alpha) + sigma z, so the output error has variance
    (1 - abar_n) / abar_n + sum_{j=2..n} beta~_j / abar_{j-1} per dimension, n = k_sw (paper indices)."""
    policy = KnownEpsPolicy(zero_eps)
    sch, n = policy.schedule, switch_step(beta, 100)
    out = partial_denoise(policy, np.zeros((20_000, 4)), np.zeros((20_000, 4, 2)), beta,
                          generator=torch.Generator().manual_seed(1))
    abar = np.concatenate([[1.0], sch.alphas_cumprod.double().numpy()])
    post = np.concatenate([[0.0], sch.posterior_variance.double().numpy()])
    expected = (1 - abar[n]) / abar[n] + sum(post[j] / abar[j - 1] for j in range(2, n + 1))
    assert out.var() == pytest.approx(expected, rel=0.03) and abs(out.mean()) < 0.01


def test_beta_0_keeps_the_expert_and_a_batch_equals_its_rows():
    pull = lambda a, k: 0.5 * a                                       # a model that pulls toward 0
    policy = KnownEpsPolicy(pull)
    rng = np.random.default_rng(0)
    expert = rng.uniform(-0.8, 0.8, (3, 4, 2))
    betas = np.array([0.0, 0.05, 0.4])
    out = partial_denoise(policy, np.zeros((3, 4)), expert, betas, generator=torch.Generator().manual_seed(2))
    assert np.array_equal(out[0], expert[0])                          # beta = 0: no step, the expert chunk
    gen = torch.Generator().manual_seed(2)
    rows = [partial_denoise(policy, np.zeros((1, 4)), expert[i:i + 1], betas[i], generator=gen) for i in range(3)]
    assert np.allclose(out, np.concatenate(rows), atol=1e-6)
    dist = np.linalg.norm((out - expert).reshape(3, -1), axis=1)
    assert dist[0] == 0 < dist[1] < dist[2]                           # more noise, further from the expert
