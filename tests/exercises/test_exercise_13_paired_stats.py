"""Exercise 13: the paired t-test and the TOST equivalence test behind Table I's claims
(dagger.paired_ttest, dagger.tost; paper Sec. V: "improves on HG-DAgger by 2.8 points (t(4) = 5.75,
p = 0.005) and is equivalent within a +-2 point margin to the best fixed noise level (TOST, p <= 0.01)")."""
import math

import numpy as np
import pytest

from dagger import paired_ttest, tost

T_975_DF4 = 2.776445   # Student t quantiles, df = 4 (any statistics table)
T_95_DF4 = 2.131847
UNIT = np.array([-2.0, -1.0, 0.0, 1.0, 2.0]) / math.sqrt(2.5)    # mean 0, sample sd 1, n = 5


def test_paired_ttest_reproduces_the_papers_numbers():
    """Five lineages whose round-averaged gains over HG-DAgger have mean 2.8 and t(4) = 5.75."""
    sd = 2.8 * math.sqrt(5) / 5.75
    hg = np.array([81.0, 83.5, 82.2, 84.0, 82.9])
    ours = hg + 2.8 + sd * UNIT
    t, df, p = paired_ttest(ours, hg)
    assert df == 4 and t == pytest.approx(5.75, rel=1e-9)
    assert p == pytest.approx(0.0045, abs=2e-4)                      # the paper rounds to 0.005
    t2, _, p2 = paired_ttest(hg, ours)
    assert t2 == pytest.approx(-t) and p2 == pytest.approx(p)        # two-sided


def test_paired_ttest_at_the_critical_value_and_the_degenerate_cases():
    _, _, p = paired_ttest(T_975_DF4 / math.sqrt(5) + UNIT, np.zeros(5))   # t = 2.776: p = 0.05
    assert p == pytest.approx(0.05, abs=1e-5)
    assert paired_ttest([3.0, 4.0], [1.0, 2.0])[1:] == (1, 0.0)       # every pair differs by exactly 2
    assert paired_ttest([3.0, 4.0], [1.0, 2.0])[0] == math.inf
    assert paired_ttest([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == (0.0, 2, 1.0)


def test_tost_is_the_larger_of_two_one_sided_p_values():
    se = 2.0 / T_95_DF4                                              # (0 + 2) / se = t_{0.95, 4}
    d = se * math.sqrt(5) * UNIT                                     # mean 0, standard error se
    p, t_lower, t_upper = tost(d, np.zeros(5), margin=2.0)
    assert t_lower == pytest.approx(T_95_DF4) and t_upper == pytest.approx(-T_95_DF4)
    assert p == pytest.approx(0.05, abs=1e-5)                        # both one-sided tests at 0.05
    p_shift, tl, tu = tost(d + 0.5, np.zeros(5), margin=2.0)         # closer to +2: the upper test decides
    assert tl == pytest.approx((0.5 + 2.0) / se) and tu == pytest.approx((0.5 - 2.0) / se)
    assert 0.05 < p_shift < 0.5
    assert tost(d + 2.0, np.zeros(5), margin=2.0)[0] == pytest.approx(0.5)   # mean on the margin
    assert tost(0.1 * UNIT + 0.3, np.zeros(5), margin=2.0)[0] < 1e-4        # tight and inside: equivalent


def test_tost_without_spread():
    assert tost([1.0, 1.0], [0.0, 0.0], margin=2.0)[0] == 0.0
    assert tost([3.0, 3.0], [0.0, 0.0], margin=2.0)[0] == 1.0
