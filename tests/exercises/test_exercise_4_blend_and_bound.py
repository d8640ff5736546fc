"""Exercise 4: the linear blend of Eq. (3), the noise fraction sigma^2_{k_sw} = 1 - alphabar_{k_sw} that
calibrate.py puts into Eqs. (8)-(12), and the SDEdit bound of Eq. (7) (partial_denoise.lerp_blend,
noise_fraction, sdedit_bound; paper Sec. IV-B, IV-D)."""
import math

import numpy as np
import pytest

from diffusion import make_schedule
from partial_denoise import lerp_blend, noise_fraction, sdedit_bound


def test_eq3_lerp():
    a_pol, a_exp = np.array([[1.0, 2.0]]), np.array([[3.0, -2.0]])
    assert np.array_equal(lerp_blend(a_pol, a_exp, 0.0), a_exp)      # beta = 0: the expert
    assert np.array_equal(lerp_blend(a_pol, a_exp, 1.0), a_pol)      # beta = 1: the policy
    assert np.allclose(lerp_blend(a_pol, a_exp, 0.25), [[2.5, -1.0]])
    both = lerp_blend(np.zeros((2, 3, 2)), np.ones((2, 3, 2)), np.array([0.0, 0.5]))   # a beta per row
    assert both.shape == (2, 3, 2) and np.allclose(both[0], 1.0) and np.allclose(both[1], 0.5)


def test_noise_fraction_is_one_minus_alphabar_at_the_switch_step():
    sch = make_schedule(100)
    betas = sch.betas.double().numpy()
    assert noise_fraction(sch, 0.0) == 0.0                             # k_sw = 0: alphabar_0 = 1
    for beta, k_sw in ((0.05, 5), (0.29, 29), (0.9, 90), (1.0, 100)):
        assert noise_fraction(sch, beta) == pytest.approx(1 - np.prod(1 - betas[:k_sw]), rel=1e-5)
    s = noise_fraction(sch, np.linspace(0.05, 0.90, 13))               # the paper's 13 blend ratios
    assert s.shape == (13,) and np.all(np.diff(s) > 0)
    assert s[0] == pytest.approx(0.0080, abs=1e-4) and s[-1] == pytest.approx(0.9759, abs=1e-4)


def test_eq7_formula():
    s2, bound, d, delta = 0.1, 3.0, 8, 0.05
    want = s2 * (bound * s2 + d + 2 * math.sqrt(-d * math.log(delta)) - 2 * math.log(delta))
    assert sdedit_bound(s2, bound, d, delta) == pytest.approx(want)
    assert sdedit_bound(0.0, bound, d, delta) == 0.0
    assert np.allclose(sdedit_bound(np.array([0.1, 0.2]), bound, d, delta),
                       [want, sdedit_bound(0.2, bound, d, delta)])


def test_eq7_leading_term_is_a_chi_square_tail():
    """With bound 0, Eq. (7) is sigma^2 times the (1 - delta) tail bound of a chi-square with d degrees
    of freedom (Laurent & Massart): the forward noise sigma z stays inside it with probability >= 1 - delta."""
    rng = np.random.default_rng(0)
    for d, delta in ((8, 0.05), (48, 0.01)):
        z2 = np.sum(rng.standard_normal((100_000, d)) ** 2, axis=1) * 0.3
        inside = np.mean(z2 <= sdedit_bound(0.3, 0.0, d, delta))
        assert 1 - delta <= inside <= 1 - delta / 100                  # a bound, but not a vacuous one
