"""The study on the stronger recipe: the seven tests stated before it ran, from committed files only.

The design (benchmarks/HISTORY.md, "The study on the stronger recipe"): the `table1_strong` profile, K = 1,
five lineages, rows BC, HG-DAgger, the authors' HG-DAgger, fixed sigma 4 / 8 / 16, pooled Sigma-bar^alpha, against the
committed `table1` lineages (benchmarks/results/table1, K = 1). Seven two-sided tests, Bonferroni over the seven
(a p counts at 0.05 / 7 = 0.0071):

  (a1) strong BC row - table1 BC row, paired over the 100 scenarios (each row one policy evaluated once)
  (a2) strong HG-DAgger - table1 HG-DAgger, paired over the lineages (lineage i of both: the same lineage seed)
  (b1) pooled - HG-DAgger on the strong recipe, paired over lineages (the paper's ordering: > 0)
  (b2-b4) fixed sigma - HG-DAgger for sigma 4, 8, 16 on the strong recipe, paired over lineages (> 0 for the best)
  (c)  on pi_0's *never* class (each folder's own pi_0), the per-lineage slope of (fixed sigma - HG-DAgger) on
       sigma in {4, 8, 16}: strong - table1, Welch's t over the two folders' five slopes (less negative: > 0)

    python benchmarks/strength_study.py [--strong benchmarks/results/table1_strong] [--base benchmarks/results/table1]

It prints the tests' table, then the class split of both folders (benchmarks/noise_trade.py's table).
"""
from __future__ import annotations

import argparse
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from noise_trade import class_differences, class_table, pi0_classes, success  # noqa: E402
from paired_bc import load_lineages, student_t_cdf, t_test  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
SIGMAS = (4, 8, 16)
N_TESTS = 7


def bc_rates(lineages):
    """(scenario seeds, per-scenario BC-row success, mean over repeats) of a folder's shared BC row."""
    e = next(iter(lineages.values()))["eval/bc.json"]
    return list(e["seeds"]), np.asarray(e["success"], float).mean(axis=1)


def rate(lineages, method, k=1):
    """{lineage: the row's success in points at round k} for the lineages that hold it."""
    return {l: 100.0 * s.mean() for l, f in lineages.items() if (s := success(f, l, k, method)) is not None}


def paired_over_lineages(a, b):
    """t_test of a[l] - b[l] over the lineages holding both ({lineage: points} each)."""
    both = sorted(set(a) & set(b))
    return (*t_test([a[l] - b[l] for l in both]), len(both))


def never_slopes(lineages, k=1):
    """Per lineage, the least-squares slope of (fixed sigma - HG-DAgger) on sigma in SIGMAS, points per paper
    median step, over pi_0's never class of that folder; lineages lacking a row are left out."""
    diffs = {s: class_differences(lineages, k, f"fixed_{s}") for s in SIGMAS}
    n = min(len(diffs[s]["never"]) for s in SIGMAS)
    complete = [l for l, f in sorted(lineages.items())
                if all(success(f, l, k, m) is not None for m in ["hg_dagger"] + [f"fixed_{s}" for s in SIGMAS])]
    assert n == len(complete), "a lineage holds some fixed rows and not others"
    return [float(np.polyfit(SIGMAS, [diffs[s]["never"][i] for s in SIGMAS], 1)[0]) for i in range(n)]


def welch(a, b):
    """Welch's two-sample t of mean(a) - mean(b): (difference, SE, t, df, two-sided p)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    se = math.sqrt(va + vb)
    t = (a.mean() - b.mean()) / se
    df = (va + vb) ** 2 / (va ** 2 / (a.size - 1) + vb ** 2 / (b.size - 1))
    return float(a.mean() - b.mean()), se, t, df, 2.0 * (1.0 - student_t_cdf(abs(t), df))


def tests(strong, base):
    """[(name, what, (difference, SE, t, df, p), n)] of the seven stated tests."""
    out = []
    seeds, bc_s = bc_rates(strong)
    base_seeds, bc_b = bc_rates(base)
    assert seeds == base_seeds, "the two folders' BC rows were evaluated on other scenarios"
    out.append(("a1", "BC row: strong − table1 (paired over 100 scenarios)", t_test(100.0 * (bc_s - bc_b)), len(seeds)))
    hg_s, hg_b = rate(strong, "hg_dagger"), rate(base, "hg_dagger")
    *r, n = paired_over_lineages(hg_s, hg_b)
    out.append(("a2", "HG-DAgger K = 1: strong − table1 (paired over lineages)", tuple(r), n))
    for name, m in [("b1", "pooled")] + [(f"b{i + 2}", f"fixed_{s}") for i, s in enumerate(SIGMAS)]:
        *r, n = paired_over_lineages(rate(strong, m), hg_s)
        out.append((name, f"{m} − HG-DAgger, strong (paired over lineages)", tuple(r), n))
    slopes_s, slopes_b = never_slopes(strong), never_slopes(base)
    out.append(("c", f"never class: slope of (fixed σ − HG) on σ ∈ {list(SIGMAS)}, strong − table1 (Welch)",
                welch(slopes_s, slopes_b), f"{len(slopes_s)} + {len(slopes_b)}"))
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--strong", default=os.path.join(HERE, "results", "table1_strong"))
    p.add_argument("--base", default=os.path.join(HERE, "results", "table1"))
    a = p.parse_args(argv)
    strong, base = load_lineages(a.strong), load_lineages(a.base)
    print(f"strong: {a.strong} (lineages {sorted(strong)}); base: {a.base} (lineages {sorted(base)}); K = 1")
    for label, lin in (("strong", strong), ("base", base)):
        cls = pi0_classes(next(iter(lin.values())))
        rows = {m: rate(lin, m) for m in ("hg_dagger", "authors_hg_dagger", "pooled", *[f"fixed_{s}" for s in SIGMAS])}
        cells = ", ".join(f"{m} {np.mean(list(v.values())):.1f} ({len(v)})" for m, v in rows.items() if v)
        print(f"  {label}: BC row {bc_rates(lin)[1].mean() * 100:.1f}; {cells}; pi_0 classes never "
              f"{int((cls == 'never').sum())}, sometimes {int((cls == 'sometimes').sum())}, always "
              f"{int((cls == 'always').sum())}")
    print(f"\n| test | difference (points) | SE | t | df | p | p × {N_TESTS} (Bonferroni) | n |")
    print("|---|---|---|---|---|---|---|---|")
    for name, what, (d, se, t, df, pv), n in tests(strong, base):
        print(f"| {name}: {what} | {d:+.1f} | {se:.1f} | {t:.2f} | {df:.1f} | {pv:.2g} | {min(1.0, N_TESTS * pv):.2g} "
              f"| {n} |")
    print()
    print(class_table("strong", strong, 1))
    print()
    print(class_table("table1", base, 1))


if __name__ == "__main__":
    main()
