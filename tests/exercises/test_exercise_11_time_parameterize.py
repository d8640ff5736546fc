"""Exercise 11: time parameterization under speed, acceleration and jerk limits, without TOPP-RA
(oracle.filter_kernel and the limit check of oracle.time_parameterize; paper Sec. V)."""
import math

import numpy as np
import pytest

from oracle import filter_kernel, time_parameterize

DT = 0.1
V, A, J = np.array([0.5, 0.4, 0.6]), np.array([1.25, 1.0, 1.5]), np.array([6.25, 5.0, 7.5])


def finite_differences(samples, v0, dt):
    """Velocity, acceleration, jerk the env sees: sample -1 = q0 - v0 dt, at rest after the end."""
    q = np.concatenate([[samples[0] - v0 * dt], samples, [samples[-1]]])
    v = np.diff(q, axis=0) / dt
    a = np.diff(v, axis=0) / dt
    return v, a, np.diff(a, axis=0) / dt


def within(x, limit):
    return np.all(np.abs(x) <= limit * (1 + 1e-6))


# Joints whose limits need ramps of different, non-whole numbers of steps (v / (a dt) = 3.57, 3, 3 and
# a / (j dt) = 2.8, 2.2, 2.2): a kernel sized for the wrong joint, or truncated instead of rounded up, breaks
# a limit here (V, A, J above give whole numbers of steps, the same for every joint).
UNEVEN = (np.array([0.5, 0.3, 0.6]), np.array([1.4, 1.0, 2.0]), np.array([5.0, 4.5, 9.0]))


@pytest.mark.parametrize("v_max, a_max, j_max", [(V, A, J), UNEVEN], ids=["even", "uneven"])
def test_kernel_is_two_moving_averages_that_bound_acceleration_and_jerk(v_max, a_max, j_max):
    k = filter_kernel(v_max, a_max, j_max, DT)
    w = np.concatenate([np.zeros((5, 3)), np.tile(v_max, (20, 1)), np.zeros((20, 3))])   # a full-speed pulse
    y = np.stack([np.convolve(w[:, j], k) for j in range(3)], axis=1)
    a = np.diff(y, axis=0) / DT
    assert within(y, v_max) and within(a, a_max) and within(np.diff(a, axis=0) / DT, j_max)
    n_acc = math.ceil(np.max(v_max / (a_max * DT)) - 1e-9)          # even: 4 steps from 0 to v_max
    n_jerk = math.ceil(np.max(a_max / (j_max * DT)) - 1e-9)         # even: 2 steps from 0 to a_max
    assert len(k) == n_acc + n_jerk - 1 and k.sum() == pytest.approx(1.0) and np.all(k > 0)   # and no longer


def test_straight_rest_to_rest_move_is_an_s_curve():
    path = np.array([[0.0, 0.0, 0.0], [1.0, -0.4, 0.3]])
    samples = time_parameterize(path, V, A, J, DT)
    assert np.array_equal(samples[0], path[0]) and np.allclose(samples[-1], path[-1], atol=1e-12)
    v, a, j = finite_differences(samples, np.zeros(3), DT)
    assert within(v, V) and within(a, A) and within(j, J)
    n = len(filter_kernel(V, A, J, DT))
    s_curve = 1.0 / 0.5 + (n - 1) * DT                              # L / v_max + (n_acc + n_jerk - 2) dt
    assert abs((len(samples) - 1) * DT - s_curve) <= 1.01 * DT


def test_corners_and_a_moving_handoff_stay_within_every_limit():
    path = np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [0.6, 0.5, -0.2], [0.1, 0.9, 0.4]])
    v0 = np.array([-0.5, 0.2, 0.0])                                  # the arm moves AWAY from the path at handoff
    samples = time_parameterize(path, V, A, J, DT, v0=v0)
    v, a, j = finite_differences(samples, v0, DT)
    assert np.allclose(v[0], v0)                                     # the handoff velocity is matched
    assert within(v, V) and within(a, A) and within(j, J)
    assert np.allclose(samples[-1], path[-1], atol=1e-12) and np.all(v[-1] == 0)


def test_colliding_corner_cuts_are_slowed_down_until_free():
    path = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])

    def corner_cut(q):                                               # forbids cutting the corner by > 0.005
        q = np.atleast_2d(q)
        return (q[:, 0] < 0.995) & (q[:, 1] > 0.005)

    assert corner_cut(time_parameterize(path, V, A, J, DT)).any()     # at full speed the filter cuts it
    samples = time_parameterize(path, V, A, J, DT, in_collision=corner_cut, resolution=0.002)
    assert not corner_cut(samples).any()
    v, a, j = finite_differences(samples, np.zeros(3), DT)
    assert within(v, V) and within(a, A) and within(j, J)
