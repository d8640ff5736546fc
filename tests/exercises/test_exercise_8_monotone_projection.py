"""Exercise 8: the monotone closest-point projection that associates a noised state with a step of
the expert trajectory (relabel.monotone_projection; paper Sec. IV-E, Fig. 1)."""
import numpy as np

from relabel import monotone_projection


def brute_force(q, trajectory, t_start, window, t_end):
    stop = t_end if window is None else min(t_start + window, t_end)
    d = [np.sum((trajectory[t] - q) ** 2) for t in range(t_start, stop)]
    return t_start + int(np.argmin(d))                                  # argmin: the earliest of ties


def test_never_goes_back_in_time():
    """A path that passes the same place twice (a U-turn): the earlier visit is closer, but a state
    noised around step 30 must be associated with step 30 or later."""
    s = np.linspace(0, 1, 50)
    trajectory = np.stack([np.where(s < 0.5, s, 1 - s), np.where(s < 0.5, 0.0, 0.02)], axis=1)  # (50, 2)
    q = trajectory[19] + np.array([0.0, -0.001])                        # right on top of the first pass
    assert monotone_projection(q, trajectory, 0) == 19
    t = monotone_projection(q, trajectory, 30)
    assert isinstance(t, int) and t >= 30 and t == brute_force(q, trajectory, 30, None, 50)


def test_matches_brute_force_with_window_and_segment_end():
    rng = np.random.default_rng(0)
    trajectory = np.cumsum(rng.normal(0, 0.1, (80, 3)), axis=0)
    q = trajectory[rng.integers(0, 80, 200)] + rng.normal(0, 0.3, (200, 3))
    t_start = rng.integers(0, 60, 200)
    t_end = np.minimum(80, t_start + rng.integers(1, 30, 200))
    for window in (None, 1, 5, 12):
        got = monotone_projection(q, trajectory, t_start, window=window, t_end=t_end)
        assert got.shape == (200,) and got.dtype == np.int64
        want = [brute_force(q[i], trajectory, t_start[i], window, t_end[i]) for i in range(200)]
        assert np.array_equal(got, want), f"window={window}"
        assert np.all(got >= t_start) and np.all(got < t_end)


def test_ties_go_to_the_earliest_step():
    trajectory = np.array([[0.0], [1.0], [1.0], [1.0], [3.0]])           # the arm waited at 1.0
    assert monotone_projection(np.array([1.2]), trajectory, 0) == 1
    assert monotone_projection(np.array([[1.2], [5.0]]), trajectory, [2, 0]).tolist() == [2, 4]
