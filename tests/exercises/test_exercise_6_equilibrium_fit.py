"""Exercise 6: the equilibrium of expert and policy (Eqs. 8-12) and its fit for W
(calibrate.equilibrium, calibrate._best_W, calibrate.fit_equilibrium; paper Sec. IV-D, Fig. 4)."""
import numpy as np
import pytest

from calibrate import _best_W, equilibrium, fit_equilibrium
from diffusion import make_schedule
from partial_denoise import noise_fraction

BETAS = np.linspace(0.05, 0.90, 13)                     # the paper's 13 blend ratios (Sec. IV-D)


def test_eq12_is_where_the_blended_control_of_eqs_8_to_10_vanishes():
    rng = np.random.default_rng(0)
    for _ in range(20):
        s, W = rng.uniform(0, 1), rng.uniform(0.1, 3.0)
        k_star, k_theta = rng.uniform(0.1, 5.0, 2)
        x = float(equilibrium(s, W, k_star / k_theta))
        u_blend = s * k_theta * (W - x) + (1 - s) * k_star * (-x)     # Eqs. (8)-(10) at x
        assert abs(u_blend) < 1e-9 * (1 + k_star + k_theta) * W       # Eq. (11)
    s = np.linspace(0, 1, 11)
    x = equilibrium(s, 2.0, 0.5)
    assert x.shape == (11,) and x[0] == 0.0 and x[-1] == pytest.approx(2.0)   # pure expert / pure policy
    assert np.all(np.diff(x) > 0)


def test_closed_form_W_for_a_fixed_gain_ratio():
    s = noise_fraction(make_schedule(100), BETAS)
    x = equilibrium(s, 1.3, 0.7)
    W, sse = _best_W(s, x, np.ones_like(s), np.array([0.7, 2.0]))
    assert W[0] == pytest.approx(1.3, rel=1e-9) and sse[0] < 1e-20     # the true r fits exactly
    g = s / (s + 2.0 * (1 - s))
    assert W[1] == pytest.approx(np.sum(g * x) / np.sum(g * g), rel=1e-9)   # least squares at r = 2
    assert sse[1] == pytest.approx(np.sum((x - W[1] * g) ** 2), rel=1e-9)


@pytest.mark.parametrize("W, r", [(1.7, 0.4), (0.05, 3.0), (4.0, 0.05)])
def test_fit_recovers_W_and_r_at_the_papers_blend_ratios(W, r):
    s = noise_fraction(make_schedule(100), BETAS)                      # sigma^2_{k_sw} of the 13 ratios
    rng = np.random.default_rng(1)
    x = equilibrium(s, W, r) * (1 + 0.01 * rng.standard_normal(len(s)))
    fit = fit_equilibrium(s, x)
    assert fit.W == pytest.approx(W, rel=0.03) and fit.r == pytest.approx(r, rel=0.15)
    assert fit.n_points == 13 and fit.rms_residual < 0.02 * W


def test_fit_is_least_squares_even_with_an_outlier():
    """The run's fit is plain least squares, as the authors' curve_fit: an outlier moves it, and no (W, r) near
    the fit has a smaller sum of squares (a fit left at the grid's point, or a wrong golden section, has)."""
    s = noise_fraction(make_schedule(100), BETAS)
    x = equilibrium(s, 2.0, 0.5)
    x[6] *= 3.0                                                        # one rollout nearly diverged
    fit = fit_equilibrium(s, x)
    sse = lambda W, r: float(np.sum((x - equilibrium(s, W, r)) ** 2))   # noqa: E731
    best = sse(fit.W, fit.r)
    for r in fit.r * np.exp(np.linspace(-0.05, 0.05, 21)):             # the best W of each r nearby
        W = _best_W(s, x, np.ones_like(s), np.array([r]))[0][0]
        assert best <= sse(W, r) + 1e-12
    assert fit.rms_residual == pytest.approx(np.sqrt(best / 13), rel=1e-9)
    assert abs(fit.W - 2.0) > 0.05                                     # the outlier pulled it: not a robust fit
