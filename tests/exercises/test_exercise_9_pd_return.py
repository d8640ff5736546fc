"""Exercise 9: the critically damped PD return chunk with clamped accelerations
(relabel.critically_damped_gains, relabel.pd_return_chunk; paper Sec. IV-E, Fig. 1)."""
import numpy as np
import pytest

from relabel import critically_damped_gains, pd_return_chunk

SPEED = np.array([0.02, -0.01, 0.015])                                # rad/step along a straight path
TRAJ = np.outer(np.arange(120), SPEED)                                 # (120, 3)


@pytest.mark.parametrize("settle", [4.0, 8.0, 30.0])
def test_gains_place_a_discrete_double_pole_that_settles_in_time(settle):
    kp, kd = critically_damped_gains(settle)
    A = np.array([[1 - kp, 1 - kd], [-kp, 1 - kd]])                    # (e, e') -> next (e, e')
    p = np.exp(-5.83 / settle)
    assert np.trace(A) == pytest.approx(2 * p) and np.linalg.det(A) == pytest.approx(p * p)  # double pole p
    e = np.array([1.0, 0.0])
    for _ in range(int(np.ceil(settle))):
        e = A @ e
    assert abs(e[0]) < 0.05                                            # settled (to a few %) in settle steps
    kp, kd = critically_damped_gains(300.0)
    assert kd == pytest.approx(2 * np.sqrt(kp), rel=0.01)              # the continuous-time limit


def test_unclamped_error_follows_the_critically_damped_map():
    """With generous clamps the chunk is the reference plus the error of the linear map (e, e' = v - u),
    also on a curved path: the reference's own acceleration is fed forward."""
    kp, kd = critically_damped_gains(8.0)
    t = np.arange(60)[:, None]
    curved = SPEED * t + 0.5 * np.array([-4e-4, 3e-4, 1e-4]) * t ** 2       # constant acceleration
    e0 = np.array([0.05, -0.03, 0.02])
    chunk = pd_return_chunk(curved[10] + e0, curved[10] - curved[9], curved, 10, 16, 0, 1.0, 1.0)
    e, de = e0.copy(), np.zeros(3)
    for k in range(16):
        e, de = (1 - kp) * e + (1 - kd) * de, -kp * e + (1 - kd) * de
        np.testing.assert_allclose(chunk[k], curved[11 + k] + e, atol=1e-12)
    assert np.all(np.abs(chunk[-1] - curved[26]) < 0.01 * np.abs(e0))     # rejoined, then follows the path


def test_clamps_hold_and_the_saturated_return_does_not_overshoot_much():
    e0 = np.array([0.3, 0.2, -0.25])
    q0, v0 = TRAJ[10] + e0, SPEED
    chunk = pd_return_chunk(q0, v0, TRAJ, 10, 16, 0, 0.004, 0.05)
    q = np.concatenate([[q0 - v0, q0], chunk])                          # finite differences from v0 on
    v, a = np.diff(q, axis=0), np.diff(q, n=2, axis=0)
    assert np.all(np.abs(v) <= 0.05 + 1e-12) and np.all(np.abs(a) <= 0.004 + 1e-12)
    err = chunk - TRAJ[11:27]
    assert np.all(np.abs(err[-1]) < 0.5 * np.abs(e0))                   # heading home under the clamp
    overshoot = np.max(-err * np.sign(e0), axis=0)                      # how far past the path a joint goes
    assert np.all(overshoot < 0.12 * np.abs(e0))                        # a plain saturated PD: ~25 %


def test_batched_lookahead_segment_end_and_joint_limits():
    q0 = np.stack([TRAJ[20] + 0.04, TRAJ[5] - 0.02])
    out = pd_return_chunk(q0, np.zeros((2, 3)), TRAJ, [20, 5], 16, [3, 0], 1.0, 1.0, t_end=[120, 9])
    assert out.shape == (2, 16, 3)
    np.testing.assert_allclose(out[0], pd_return_chunk(q0[0], np.zeros(3), TRAJ, 23, 16, 0, 1.0, 1.0))
    np.testing.assert_allclose(out[1, -1], TRAJ[8], atol=1e-4)             # held at the segment's last point
    assert pd_return_chunk(q0[0], np.zeros(3), TRAJ, 20, 16, 0, 1.0, 1.0).shape == (16, 3)
    lo, hi = np.full(3, -0.1), np.full(3, 0.1)
    far = np.full((1, 3), 3.0)
    chunk = pd_return_chunk(np.zeros(3), np.zeros(3), far, 0, 16, 0, 1.0, 1.0, limits=(lo, hi))
    assert np.all(chunk <= hi) and np.all(chunk >= lo) and np.allclose(chunk[-1], hi)
