"""Exercise 2: the DDPM posterior q(a_{k-1} | a_k, a_0) and one reverse step p_sample (Eq. 6)
(diffusion.make_schedule's posterior arrays, diffusion.p_sample; paper Sec. IV-B)."""
import numpy as np
import pytest
import torch

from diffusion import make_schedule, p_sample


def test_posterior_is_the_gaussian_product_of_eq5_and_its_closed_form():
    """q(a_{k-1} | a_k, a_0) ~ q(a_k | a_{k-1}) q(a_{k-1} | a_0): precisions add, means weight by them."""
    sch = make_schedule(100)
    beta, alpha = sch.betas.double().numpy(), sch.alphas.double().numpy()
    abar, prev = sch.alphas_cumprod.double().numpy(), sch.alphas_cumprod_prev.double().numpy()
    k = np.arange(1, 100)                                                 # code levels with a noisy a_{k-1}
    var = 1.0 / (alpha[k] / beta[k] + 1.0 / (1.0 - prev[k]))
    assert np.allclose(sch.posterior_variance.double().numpy()[k], var, rtol=1e-4)
    assert np.allclose(sch.posterior_mean_coef1.double().numpy()[k], var * np.sqrt(prev[k]) / (1 - prev[k]), rtol=1e-4)
    assert np.allclose(sch.posterior_mean_coef2.double().numpy()[k], var * np.sqrt(alpha[k]) / beta[k], rtol=1e-4)
    # level 0: the previous level is the clean chunk itself
    assert sch.posterior_variance[0].item() == 0.0
    assert sch.posterior_mean_coef1[0].item() == pytest.approx(1.0) and sch.posterior_mean_coef2[0].item() == 0.0


@pytest.mark.parametrize("k", [1, 10, 60, 99])
def test_p_sample_without_clip_is_eq6(k):
    sch = make_schedule(100)
    g = torch.Generator().manual_seed(k)
    a_k, eps, z = (torch.randn(3, 16, 3, generator=g) for _ in range(3))
    out = p_sample(sch, eps, a_k, torch.full((3,), k), noise=z, clip=False)
    beta, alpha, abar = sch.betas[k], sch.alphas[k], sch.alphas_cumprod[k]
    eq6 = (a_k - beta / (1 - abar).sqrt() * eps) / alpha.sqrt() + sch.posterior_variance[k].sqrt() * z
    assert torch.allclose(out, eq6, atol=2e-4 * max(1.0, eq6.abs().max().item()))


def test_p_sample_clips_the_predicted_clean_chunk_and_adds_no_noise_at_level_0():
    sch = make_schedule(100)
    a_k = torch.full((2, 4, 3), 3.0)                                      # far outside [-1, 1]
    z = torch.randn(2, 4, 3, generator=torch.Generator().manual_seed(0))
    out = p_sample(sch, torch.zeros_like(a_k), a_k, 40, noise=z)
    want = sch.posterior_mean_coef1[40] * 1.0 + sch.posterior_mean_coef2[40] * 3.0 + sch.posterior_variance[40].sqrt() * z
    assert torch.allclose(out, want, atol=1e-5)                           # a0_hat = a_k / sqrt(abar) -> 1
    g = torch.Generator().manual_seed(3)
    eps = torch.randn(2, 4, 3, generator=g) * 0.1
    a0 = torch.rand(2, 4, 3, generator=g) * 1.6 - 0.8
    a_0 = sch.alphas_cumprod[0].sqrt() * a0 + (1 - sch.alphas_cumprod[0]).sqrt() * eps   # at code level 0
    assert torch.allclose(p_sample(sch, eps, a_0, 0, noise=z), a0, atol=1e-5)    # exact eps: the clean chunk
    one = p_sample(sch, eps, a_k, 40, generator=torch.Generator().manual_seed(9))
    assert torch.equal(one, p_sample(sch, eps, a_k, 40, generator=torch.Generator().manual_seed(9)))
