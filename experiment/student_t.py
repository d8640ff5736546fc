"""Student's t distribution without scipy: the p-values of Table I's paired t-test and TOST (dagger.paired_ttest,
dagger.tost) and of the benchmarks' studies. A numerical special function, not the paper's method."""
from __future__ import annotations

import math


def student_t_cdf(t, df):
    """P(T <= t) for Student's t with df > 0 degrees of freedom: 1 - I_{df/(df+t^2)}(df/2, 1/2) / 2."""
    assert df > 0, df
    if math.isinf(t):
        return 1.0 if t > 0 else 0.0
    tail = 0.5 * incomplete_beta(df / 2.0, 0.5, df / (df + t * t))
    return 1.0 - tail if t > 0 else tail


def incomplete_beta(a, b, x):
    """Regularized incomplete beta I_x(a, b) for a, b > 0 and 0 <= x <= 1."""
    assert 0.0 <= x <= 1.0, x
    if x in (0.0, 1.0):
        return x
    log_front = (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
                 + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):  # the continued fraction converges fast here
        return math.exp(log_front) * _betacf(a, b, x) / a
    return 1.0 - math.exp(log_front) * _betacf(b, a, 1.0 - x) / b  # symmetry I_x(a,b) = 1 - I_{1-x}(b,a)


def _betacf(a, b, x):
    """Continued fraction of the regularized incomplete beta function (modified Lentz; 300 terms at most)."""
    tiny = 1e-300  # keeps every denominator off zero

    def lentz(num, c, d):  # one term num of the fraction: the updated (c, d)
        d = 1.0 + num * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + num / c
        return (c if abs(c) > tiny else tiny), d

    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 301):
        c, d = lentz(m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)), c, d)  # even step d_{2m}
        h *= d * c
        c, d = lentz(-(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1)), c, d)  # odd step d_{2m+1}
        h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h
