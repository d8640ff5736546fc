"""Exercise 1: the DDPM noise schedule and the forward process q_sample in closed form (Eq. 5)
(diffusion.make_schedule, diffusion.q_sample; paper Sec. IV-B). Code index k <-> paper step k + 1."""
import math

import numpy as np
import pytest
import torch

from diffusion import make_schedule, q_sample


def squaredcos_alphabar(K, s=0.008):
    """Nichol & Dhariwal's alphabar(t) = f(t) / f(0), f(t) = cos^2((t + s) / (1 + s) pi / 2), t = k / K."""
    f = lambda t: math.cos((t + s) / (1 + s) * math.pi / 2) ** 2
    return np.array([f(k / K) / f(0) for k in range(1, K + 1)])


@pytest.mark.parametrize("K", [10, 100])
def test_squaredcos_schedule(K):
    sch = make_schedule(K)
    betas, abar = sch.betas.double().numpy(), sch.alphas_cumprod.double().numpy()
    assert sch.K == K and np.all(betas > 0) and np.all(betas <= 0.999 + 1e-6)   # float32 storage
    assert np.allclose(abar[:-1], squaredcos_alphabar(K)[:-1], rtol=1e-5, atol=1e-7)   # the capped last step aside
    assert abar[-1] < 1e-3                                                # level K is (almost) pure noise
    assert np.allclose(sch.alphas.double().numpy(), 1 - betas, atol=1e-7)
    assert np.allclose(abar, np.cumprod(1 - betas), rtol=1e-5)
    prev = sch.alphas_cumprod_prev.double().numpy()
    assert prev[0] == 1.0 and np.allclose(prev[1:], abar[:-1])            # alphabar_0 = 1: the clean chunk


def test_q_sample_closed_form_per_row():
    sch = make_schedule(100)
    g = torch.Generator().manual_seed(0)
    a0 = torch.rand(4, 16, 3, generator=g) * 2 - 1
    eps = torch.randn(4, 16, 3, generator=g)
    k = torch.tensor([0, 5, 50, 99])
    out = q_sample(sch, a0, k, eps)
    abar = squaredcos_alphabar(100)
    abar[-1] = sch.alphas_cumprod[-1].item()                              # the capped last step
    for i, ki in enumerate(k.tolist()):
        want = math.sqrt(abar[ki]) * a0[i] + math.sqrt(1 - abar[ki]) * eps[i]
        assert torch.allclose(out[i], want.float(), atol=1e-5)
    assert torch.allclose(q_sample(sch, a0, 7, eps), q_sample(sch, a0, torch.full((4,), 7), eps))   # int k


def test_q_sample_equals_iterating_eq5():
    """k + 1 steps of Eq. (5), a_j = sqrt(alpha_j) a_{j-1} + sqrt(1 - alpha_j) eps_j, have the closed
    form's distribution: mean sqrt(alphabar) a0 and variance 1 - alphabar."""
    sch = make_schedule(100)
    g = torch.Generator().manual_seed(1)
    n, k = 200_000, 30
    a0 = torch.full((n, 1, 1), 0.7)
    a = a0.clone()
    for j in range(k + 1):
        a = sch.alphas[j].sqrt() * a + (1 - sch.alphas[j]).sqrt() * torch.randn(a.shape, generator=g)
    closed = q_sample(sch, a0, torch.full((n,), k), torch.randn(a.shape, generator=g))
    abar = sch.alphas_cumprod[k].item()
    for x in (a, closed):
        assert x.mean().item() == pytest.approx(math.sqrt(abar) * 0.7, abs=3e-3)
        assert x.var().item() == pytest.approx(1 - abar, rel=0.02)
