"""What the relabelled chunks cost: the authors' servo label against the paper's PD label. A study stated before it runs.

Without noise the noised rows' pipeline cost 1.7 points on new scenarios in the noise-transfer study (zero_noise -
HG-DAgger on 30000..30299), and at sigma = 0 such a row differs from HG-DAgger only in its intervention rows'
labels: the servo's return chunk instead of the recorded one (benchmarks/relabel_diagnostic.py measures how far
apart they are). This study tests whether the paper's PD label (relabel.pd_return_chunk, Sec. IV-E) removes that
cost, and whether the noise then pays over HG-DAgger. The design (benchmarks/results/relabel_cost/README.md):

  lineages     13, 14, ..., 13 + N_LINEAGES - 1 of the table1_strong profile from its committed start, K = 1
  rows         HG-DAgger and {servo, PD} x {sigma = 0, fixed sigma 8, pooled}: zero_noise, fixed_8, pooled (the
               servo, today's rows) and zero_noise_pd, fixed_8_pd, pooled_pd (the same noise, the PD label)
  scenarios    collected: the 100 evaluation scenarios 10000..10099 (the run's eval/<row>.json); new: lineage L's own
               300 scenarios new_seeds(L) = 100000 + 1000 L .. + 299, drawn by no stage and by no other lineage
  tests        one-sided t over lineages (df = lineages - 1), Holm over T1-T3 at 0.05:
    T1  new: zero_noise_pd - zero_noise  > 0   (the label's cost)
    T2  new: fixed_8_pd - HG-DAgger      > 0
    T3  new: pooled_pd - HG-DAgger       > 0
  secondary    two-sided, uncorrected: T1-T3 on the collected scenarios; pooled and pooled_pd against HG-DAgger and
               each other on both sets; the 2 x 3 interaction (the label's effect at sigma 8 and at pooled minus
               its effect at sigma = 0, each, and both at once)
  every quantity with its SE over lineages and its variance-components SE over the lineage x scenario table

`--design` prints the power analysis (from the noise-transfer study's committed lineage files) and the cost per
lineage (from their recorded stage times). The study's evaluation, table, tests and figure come with its rows.
"""
from __future__ import annotations

import argparse
import math
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))
import noise_transfer  # noqa: E402  (the pilot's files, its per-scenario rates and its power function)
from paired_bc import load_lineages  # noqa: E402

FIRST_LINEAGE = 13  # lineages 0-4 are table1_strong's, 5-12 the noise-transfer study's
SERVO_ROWS = ("zero_noise", "fixed_8", "pooled")
PD_ROWS = tuple(f"{row}_pd" for row in SERVO_ROWS)
ROWS = ("hg_dagger",) + SERVO_ROWS + PD_ROWS
NEW_PER_LINEAGE = 300  # new scenarios a lineage draws
NEW_SEED_START, NEW_SEED_STRIDE = 100_000, 1_000  # lineage L: 100000 + 1000 L .. + 299
ALPHA, POWER, N_MIN, N_MAX, N_TESTS = 0.05, 0.80, 8, 16, 3
EFFECT = 1.5  # points on the new scenarios: the smallest effect stated for T1, T2 and T3 (of a 1.7 cost)
PILOT = noise_transfer.RESULTS  # lineages 5-12: the SDs and the stage times
# the pilot's per-lineage difference standing in for each test's: (test, the study's rows, the pilot's rows)
PROXIES = (("T1", "zero_noise_pd − zero_noise", ("zero_noise", "hg_dagger")),
           ("T2", "fixed_8_pd − HG-DAgger", ("fixed_8", "hg_dagger")),
           ("T3", "pooled_pd − HG-DAgger", ("pooled", "hg_dagger")))


def new_seeds(lineage):
    """Lineage `lineage`'s own new scenarios: 300 seeds from 100000 + 1000 * lineage. No stage draws a seed there
    (training 0..9999, collected 10000..10099, unseen 20000..20099, the noise-transfer study's 30000..30299), and
    the ranges of two lineages never meet (300 < 1000)."""
    if lineage < 0:
        raise ValueError(f"lineage {lineage}: lineages are numbered from 0")
    start = NEW_SEED_START + NEW_SEED_STRIDE * lineage
    return tuple(range(start, start + NEW_PER_LINEAGE))


# ---- the SEs: over lineages, and from the variance components of the lineage x scenario table ----------------------
def variance_components(table):
    """Two-way random-effects ANOVA of a (lineages R, scenarios C) table of per-scenario values (a row's success, or
    a difference of two rows, in points): {'ms_lineage', 'ms_scenario', 'ms_error', 'var_lineage', 'var_scenario',
    'var_error', 'se', 'lineage_se'}. se² = var_lineage / R + var_scenario / C + var_error / (R C), each component
    floored at 0, which is (MS_L + MS_S − MS_E) / (R C) where both floors are inactive: the SE of the grand mean when
    the lineages and the scenarios are both drawn again. lineage_se: the SD of the lineage means / √R (the scenarios
    held fixed). Where each lineage has its own scenarios (the new set), column j is each lineage's j-th scenario:
    no scenario effect is shared, MS_S estimates MS_E and both SEs estimate the same thing."""
    x = np.asarray(table, dtype=np.float64)
    if x.ndim != 2 or min(x.shape) < 2:
        raise ValueError(f"need a lineages x scenarios table with at least 2 of each, got shape {x.shape}")
    R, C = x.shape
    grand, row_means, col_means = x.mean(), x.mean(axis=1), x.mean(axis=0)
    ms_l = C * ((row_means - grand) ** 2).sum() / (R - 1)
    ms_s = R * ((col_means - grand) ** 2).sum() / (C - 1)
    ms_e = ((x - row_means[:, None] - col_means[None, :] + grand) ** 2).sum() / ((R - 1) * (C - 1))
    var_l, var_s, var_e = max((ms_l - ms_e) / C, 0.0), max((ms_s - ms_e) / R, 0.0), ms_e
    return {"ms_lineage": ms_l, "ms_scenario": ms_s, "ms_error": ms_e, "var_lineage": var_l, "var_scenario": var_s,
            "var_error": var_e, "se": math.sqrt(var_l / R + var_s / C + var_e / (R * C)),
            "lineage_se": float(row_means.std(ddof=1) / math.sqrt(R))}


# ---- the power analysis (stated before the runs) ------------------------------------------------------------------
def pilot_table(lineages, row, base, new=True):
    """(lineages, scenarios) row − base in points per scenario (the mean over its repeats), new or collected set."""
    which = "new" if new else "collected"
    return np.array([noise_transfer.per_scenario(f, l, row, which) - noise_transfer.per_scenario(f, l, base, which)
                     for l, f in sorted(lineages.items())])


def design_sd(lineage_sd, components, pilot_scenarios, scenarios=NEW_PER_LINEAGE):
    """The SD over lineages of a per-lineage mean (points) when each lineage draws its own `scenarios` scenarios,
    from a pilot on one fixed set of `pilot_scenarios`: the fixed set's variance over lineages, the larger of its
    direct estimate (lineage_sd², 7 df from 8 lineages) and the components' var_L + var_E / C (the repeats' and the
    lineage x scenario noise alone), then the scenarios' own part var_S / C on top."""
    fixed_set = max(lineage_sd ** 2, components["var_lineage"] + components["var_error"] / pilot_scenarios)
    return math.sqrt(fixed_set + components["var_scenario"] / scenarios)


def chi2_quantile(p, df, draws=2_000_000, seed=0):
    """The p quantile of chi-square(df), by Monte Carlo (a fixed seed: the same number every time)."""
    return float(np.quantile(np.random.default_rng(seed).chisquare(df, draws), p))


def pilot_inputs(pilot):
    """[(test, words, the pilot's difference, its mean, its SD over lineages, its variance components, the design's
    SD with fresh scenarios)] on the pilot's new set."""
    out = []
    for test, words, (row, base) in PROXIES:
        table = pilot_table(pilot, row, base)
        vc = variance_components(table)
        sd = float(table.mean(axis=1).std(ddof=1))
        out.append((test, words, f"{row} − {base}", float(table.mean()), sd, vc,
                    design_sd(sd, vc, table.shape[1])))
    return out


def lineage_count(pilot):
    """(N_LINEAGES, lines): the smallest n in N_MIN..N_MAX with POWER for each of T1-T3 at EFFECT points, each at
    ALPHA / N_TESTS (Holm's first step: a bound on every step), the SDs the pilot's with fresh scenarios."""
    inputs = pilot_inputs(pilot)
    level = ALPHA / N_TESTS
    R = len(pilot)
    lines = [f"pilot: {os.path.relpath(PILOT, os.path.dirname(HERE))} lineages {sorted(pilot)} (the noise-transfer "
             f"study), round 1, its new scenarios {noise_transfer.NEW_SEEDS[0]}..{noise_transfer.NEW_SEEDS[-1]} "
             f"(one set for every lineage), per-scenario success the mean of 3 repeats, in points",
             f"  {'test':4s}  {'stands in for':26s}  {'pilot difference':22s}  {'mean':>6s}  {'SD':>6s}  {'var_L':>6s}  "
             f"{'var_S':>7s}  {'var_E':>7s}  {'design SD':>9s}  {'d':>5s}"]
    for test, words, proxy, mean, sd, vc, fresh in inputs:
        lines.append(f"  {test:4s}  {words:26s}  {proxy:22s}  {mean:+6.2f}  {sd:6.3f}  {vc['var_lineage']:6.3f}  "
                     f"{vc['var_scenario']:7.2f}  {vc['var_error']:7.2f}  {fresh:9.3f}  {EFFECT / fresh:5.2f}")
    lines.append("  (SD: of the per-lineage differences, over lineages; var_*: the variance components of the lineage x "
                 "scenario table, points²; design SD: the SD over "
                 f"lineages with {NEW_PER_LINEAGE} fresh scenarios each, sqrt(max(SD², var_L + var_E / C) + var_S / "
                 f"{NEW_PER_LINEAGE}); d = effect / design SD)")
    lines += [f"  smallest effect stated: +{EFFECT:.1f} points for each of T1-T3; one-sided t over lineages at "
              f"{ALPHA} / {N_TESTS} = {level:.4f}; power by Monte Carlo (200,000 draws)",
              "   n  " + "  ".join(f"power {t}" for t, *_ in inputs)]
    chosen = None
    for n in range(4, N_MAX + 1):
        powers = [noise_transfer.power(EFFECT, fresh, n, level) for *_, fresh in inputs]
        lines.append(f"  {n:2d}  " + "  ".join(f"{p:8.3f}" for p in powers))
        if chosen is None and n >= N_MIN and min(powers) >= POWER:
            chosen = n
    at_min = [noise_transfer.power(EFFECT, fresh, N_MIN, level) for *_, fresh in inputs]
    lines.append(f"  at {N_MIN} lineages: power " + ", ".join(f"{t} {p:.3f}" for (t, *_), p in zip(inputs, at_min)))
    # the SDs are estimates from R lineages: the power at the chosen n were the true SD at the upper end of a
    # one-sided 80 % interval, sqrt((R - 1) / chi2_0.2(R - 1)) times the estimate
    up = math.sqrt((R - 1) / chi2_quantile(0.2, R - 1))
    n_up = chosen or N_MAX
    lines.append(f"  sensitivity: at n = {n_up} with every SD x {up:.2f} (upper 80 % bound of an SD from {R} lineages): "
                 + ", ".join(f"power {t} {noise_transfer.power(EFFECT, fresh * up, n_up, level):.3f}"
                             for t, *_, fresh in inputs))
    if chosen is None:
        lines.append(f"lineages: {N_MAX} (no n <= {N_MAX} reaches power {POWER} for all three; the most the design "
                     f"runs): lineages {FIRST_LINEAGE}..{FIRST_LINEAGE + N_MAX - 1}")
        return N_MAX, lines
    lines.append(f"lineages: {chosen} (the smallest n >= {N_MIN} with power >= {POWER} for all three, at most {N_MAX}): "
                 f"lineages {FIRST_LINEAGE}..{FIRST_LINEAGE + chosen - 1}")
    return chosen, lines


N_LINEAGES = 13  # `--design` prints how it was chosen; a test checks that it still says so


# ---- the cost of a lineage, from the pilot's recorded stage times --------------------------------------------------
def stage_seconds(files):
    """{stage: seconds} of a lineage file's timings/ (every stage one torch thread: seconds of a core)."""
    return {v["stage"]: float(v["seconds"]) for k, v in files.items() if k.startswith("timings/")}


def lineage_cost(files):
    """{'collect', 'calibrate', 'train' (per row, list), 'evaluate' (per 100-scenario evaluation, list), 'total'}."""
    t = stage_seconds(files)
    return {"collect": sum(v for k, v in t.items() if k.startswith("collect")),
            "calibrate": sum(v for k, v in t.items() if k.startswith("calibrate")),
            "train": [v for k, v in t.items() if k.startswith("train_")],
            "evaluate": [v for k, v in t.items() if k.startswith("evaluate")],
            "total": sum(t.values())}


def cost_per_lineage(pilot, rows=len(ROWS), new_policies=len(ROWS) + 2):
    """Lines: each pilot lineage's core-hours, and a study lineage projected: collection and calibration, `rows`
    trainings and their collected and unseen evaluations at the pilot's medians, and `new_policies` (the rows, BC
    and pi_0) on 300 new scenarios, each 3 x a 100-scenario evaluation's median."""
    per = {l: lineage_cost(f) for l, f in sorted(pilot.items())}
    lines = ["pilot's recorded stage times (timings/ of each lineage file; seconds of one core each), Intel Xeon "
             "(family 6, model 167), 2 cores shared, load as benchmarks/results/noise_transfer/README.md records it:",
             "  lineage  rows  train s/row (median)  evaluations  total core-h"]
    for l, c in per.items():
        lines.append(f"  {l:7d}  {len(c['train']):4d}  {np.median(c['train']):20.0f}  {len(c['evaluate']):11d}  "
                     f"{c['total'] / 3600:12.2f}")
    train = float(np.median([s for c in per.values() for s in c["train"]]))
    evaluation = float(np.median([s for c in per.values() for s in c["evaluate"]]))
    fixed = float(np.median([c["collect"] + c["calibrate"] for c in per.values()]))
    projected = fixed + rows * (train + 2 * evaluation) + new_policies * 3 * evaluation
    quiet = min(per.values(), key=lambda c: c["total"])
    scale = quiet["total"] / float(np.median([c["total"] for c in per.values()]))
    lines += [f"  medians: a row's training {train:.0f} s, a 100-scenario evaluation {evaluation:.0f} s, collection "
              f"and calibration {fixed:.0f} s",
              f"projected study lineage: {fixed:.0f} + {rows} rows x ({train:.0f} + 2 x {evaluation:.0f}) + "
              f"{new_policies} policies x 3 x {evaluation:.0f} on the new set = {projected:.0f} s = "
              f"{projected / 3600:.2f} core-hours at the pilot's median load ({projected * scale / 3600:.2f} at its "
              f"quietest lineage's)"]
    return lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--design", action="store_true", help="print the power analysis, the lineage count and the cost")
    args = p.parse_args(argv)
    if not args.design:
        p.error("the study's evaluation and tests come with its rows; today: --design")
    pilot = load_lineages(PILOT)
    n, lines = lineage_count(pilot)
    print("\n".join(lines))
    print()
    print("\n".join(cost_per_lineage(pilot)))
    print(f"\nnew scenarios: lineage L draws {NEW_PER_LINEAGE} seeds from {NEW_SEED_START} + {NEW_SEED_STRIDE} L, "
          f"e.g. lineage {FIRST_LINEAGE}: {new_seeds(FIRST_LINEAGE)[0]}..{new_seeds(FIRST_LINEAGE)[-1]}, lineage "
          f"{FIRST_LINEAGE + n - 1}: {new_seeds(FIRST_LINEAGE + n - 1)[0]}..{new_seeds(FIRST_LINEAGE + n - 1)[-1]}")


if __name__ == "__main__":
    main()
