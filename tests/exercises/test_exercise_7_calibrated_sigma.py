"""Exercise 7: DART's Eq. (2) with alpha = T ||W||^2 (Eq. 13), the per-step Sigma^alpha_t (Eq. 14) and
the pooled Sigma_bar^alpha (Eqs. 15-16) (calibrate.dart_alpha, dart_sigma, calibrated_sigma,
pooled_sigma; paper Sec. III-A and IV-D, Fig. 2c-d)."""
import numpy as np
import pytest

from calibrate import calibrated_sigma, dart_alpha, dart_sigma, pooled_sigma


def covariances(n, d=3, seed=0):
    A = np.random.default_rng(seed).normal(size=(n, d, d))
    return A @ np.swapaxes(A, 1, 2) + 0.01 * np.eye(d)                # (n, d, d) SPD


def test_eq13_alpha():
    assert dart_alpha(np.array([3.0, 4.0]), 10) == pytest.approx(250.0)   # T ||W||^2
    assert dart_alpha(2.0, 7) == pytest.approx(28.0)                       # W given as its norm


def test_eq2_scales_each_matrix_by_alpha_over_T_trace():
    S = covariances(5)
    out = dart_sigma(S, 6.0, 3)
    for o, s in zip(out, S):
        assert np.allclose(o, 6.0 / (3 * np.trace(s)) * s)


def test_eq14_keeps_the_shape_and_sets_the_trace_to_W_squared():
    S = covariances(50)
    W = np.array([0.3, -0.1, 0.2])
    out = calibrated_sigma(S, W)
    assert out.shape == S.shape
    assert np.allclose(np.trace(out, axis1=1, axis2=2), np.sum(W ** 2))
    assert np.allclose(out / np.trace(out, axis1=1, axis2=2)[:, None, None],
                       S / np.trace(S, axis1=1, axis2=2)[:, None, None])  # same shape (direction)
    for T in (1, 40, 1000):                                                # Eq. (2) with Eq. (13): T cancels
        assert np.allclose(out, dart_sigma(S, dart_alpha(W, T), T))
    assert np.allclose(calibrated_sigma(S[0], 0.5), 0.25 / np.trace(S[0]) * S[0])   # one (d, d) matrix


def test_eq14_on_a_step_the_policy_reproduced_exactly():
    S = np.zeros((2, 3, 3))
    S[1] = np.diag([1.0, 2.0, 3.0])
    out = calibrated_sigma(S, 0.6)
    assert np.all(np.isfinite(out))
    assert np.allclose(out[0], 0.36 / 3 * np.eye(3))                       # isotropic, trace ||W||^2
    assert np.allclose(out[1], 0.06 * np.diag([1.0, 2.0, 3.0]))


def test_eqs15_16_pool_first_then_scale():
    S = covariances(20, seed=1)
    S[0] *= 100.0                                                          # one noisy step dominates the mean
    W = 0.4
    pooled = pooled_sigma(S, W)
    mean = S.mean(axis=0)                                                  # Eq. (15)
    assert np.allclose(pooled, W ** 2 / np.trace(mean) * mean)             # Eq. (16)
    assert not np.allclose(pooled, calibrated_sigma(S, W).mean(axis=0))    # not the mean of Eq. (14)
    assert np.trace(pooled) == pytest.approx(W ** 2)
