"""What the noise buys: on new scenarios, and on the ones HG-DAgger collected on. A study stated before it ran.

The paper evaluates every row on the 100 scenarios the interventions were collected on. Read after the fact, the
committed studies hinted that the noise trades fit to those scenarios for recovery that carries to new ones, more so
the larger sigma. This study tests that on new lineages, with the design below fixed before any of its runs
(benchmarks/README.md, "What the noise buys"):

  lineages     5, 6, ..., 5 + N_LINEAGES - 1 of the table1_strong profile, from its committed start
               (benchmarks/results/table1_strong/start: the same pi_0 and BC row as lineages 0-4), K = 1
  rows         BC (the start's), HG-DAgger, zero_noise (the relabelled pipeline at sigma = 0), fixed sigma 4 / 8 / 16
               (the paper's median steps), pooled Sigma-bar^alpha
  scenario sets  collected: the 100 evaluation scenarios 10000..10099, where each round records the oracle on the
               policy's failures (the paper's protocol; the run's eval/<row>.json);
               new: NEW_SEEDS = 30000..30299, drawn by no stage and not among the runs' unseen 20000..20099,
               every row's round-1 policy (and BC, and pi_0 for its class split) evaluated there like the run's own
               evaluations: 3 repeats, one sampling seed for every row (stage_seed(cfg, "eval_new"))
  tests        one-sided, Holm over the four at 0.05, each a one-sample t over the lineages (df = lineages - 1):
    H1  new:       slope of (row - HG-DAgger) on sigma in {0 = zero_noise, 4, 8, 16}, per lineage   > 0
    H2  new:       pooled - HG-DAgger                                                               > 0
    H3  collected: that slope                                                                       < 0  (the trade)
    H4  (HG-DAgger - BC) on collected - (HG-DAgger - BC) on new                                    > 0
  secondary    (reported as such, two-sided, uncorrected): zero_noise - HG-DAgger on each set; the best fixed sigma on
               the new set (chosen by its mean there: a selection) - pooled; pi_0's class split on both sets
  lineage count  N_LINEAGES from `--design`: the power analysis on lineages 0-4's unseen paired SDs

Commands (a lineage at a time; each step resumes):

    python benchmarks/noise_transfer.py --design                      # the power analysis and the lineage count
    python dagger.py --profile table1_strong --methods hg_dagger,zero_noise,fixed_4,fixed_8,fixed_16,pooled \\
        --lineages 13 --lineage L --out runs/noise_transfer
    python benchmarks/noise_transfer.py --evaluate runs/noise_transfer --lineage L   # the new scenarios
    python dagger.py --profile table1_strong --methods hg_dagger,zero_noise,fixed_4,fixed_8,fixed_16,pooled \\
        --lineages 13 --out runs/noise_transfer --report --export-lineages benchmarks/results/noise_transfer
    python benchmarks/noise_transfer.py                               # every stated test, from the committed files
        # then, after the fact: what H1's slope is made of, the power the study had at the SDs it observed, and
        # each quantity's SE with the scenarios' draw counted (variance components of the lineage x scenario table)
    python benchmarks/noise_transfer.py --figure benchmarks/figures/noise_transfer.png \
        --paired-figure benchmarks/figures/noise_transfer_paired.png  # success against sigma; each row - HG-DAgger
"""
from __future__ import annotations

import argparse
import functools
import hashlib
import math
import os
import shutil
import sys
import time
from types import SimpleNamespace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))
from evaluate_policy import evaluate_file, t_quantile  # noqa: E402
from noise_trade import success  # noqa: E402
from paired_bc import load_lineages, t_test  # noqa: E402

import dagger  # noqa: E402
from experiment import report, run_folder  # noqa: E402

t_quantile = functools.lru_cache(maxsize=None)(t_quantile)  # 200 bisection steps a call: each (p, df) computed once

NEW_SEEDS = tuple(range(30_000, 30_300))
FIRST_LINEAGE = 5
ROWS = ("hg_dagger", "zero_noise", "fixed_4", "fixed_8", "fixed_16", "pooled")
SIGMA_ROWS = ((0, "zero_noise"), (4, "fixed_4"), (8, "fixed_8"), (16, "fixed_16"))  # sigma in paper median steps
NEW = "new_scenarios"  # lineage_<l>/new_scenarios/<row>.json: the study's evaluations, exported with the lineage
RESULTS = os.path.join(HERE, "results", "noise_transfer")
PILOT = os.path.join(HERE, "results", "table1_strong")  # lineages 0-4: the power analysis's SDs
ALPHA, POWER, N_MIN, N_MAX, H2_EFFECT = 0.05, 0.80, 8, 16, 2.0
N_TESTS = 4


# ---- the power analysis (stated before the runs) ----------------------------------------------------------------
def slope(diffs):
    """Least-squares slope of (row - HG-DAgger) in points on sigma in paper median steps: {sigma: points}."""
    s = sorted(diffs)
    return float(np.polyfit(s, [diffs[x] for x in s], 1)[0])


def pilot_differences(lineages, unseen=True):
    """Per lineage of the pilot (table1_strong, no zero_noise row: HG-DAgger itself stands at sigma = 0):
    {'slope': [...], 'pooled': [...]} in points (per paper median step for the slope)."""
    out = {"slope": [], "pooled": []}
    for l, f in sorted(lineages.items()):
        hg = 100.0 * success(f, l, 1, "hg_dagger", unseen).mean()
        d = {0: 0.0, **{s: 100.0 * success(f, l, 1, f"fixed_{s}", unseen).mean() - hg for s in (4, 8, 16)}}
        out["slope"].append(slope(d))
        out["pooled"].append(100.0 * success(f, l, 1, "pooled", unseen).mean() - hg)
    return out


def power(effect, sd, n, alpha, draws=200_000, seed=0):
    """Power of the one-sided one-sample t test at level alpha with n lineages when the true mean is `effect` and
    the lineages' SD `sd`: P(T' > t_{1-alpha, n-1}), T' noncentral t (delta = effect / sd * sqrt(n)), by Monte Carlo
    (a fixed seed: the same number every time)."""
    rng = np.random.default_rng(seed)
    z = rng.standard_normal(draws) + effect / sd * math.sqrt(n)
    t = z / np.sqrt(rng.chisquare(n - 1, draws) / (n - 1))
    return float((t > t_quantile(1.0 - alpha, n - 1)).mean())


def design(pilot):
    """(N_LINEAGES, lines of text): the smallest n in N_MIN..N_MAX with POWER for H1 at the pilot's mean slope on
    the unseen scenarios and for H2 at +H2_EFFECT, each at alpha / N_TESTS (Holm's first step: the conservative
    bound on every step), SDs from the pilot's lineages."""
    d = pilot_differences(pilot, unseen=True)
    h1 = (float(np.mean(d["slope"])), float(np.std(d["slope"], ddof=1)))
    h2 = (H2_EFFECT, float(np.std(d["pooled"], ddof=1)))
    level = ALPHA / N_TESTS
    lines = [f"pilot: {os.path.relpath(PILOT, os.path.dirname(HERE))} lineages {sorted(pilot)}, round 1, the unseen scenarios (20000..20099)",
             f"  H1 slope: mean {h1[0]:+.3f} points per paper median step, SD {h1[1]:.3f} (d = {h1[0] / h1[1]:.2f})",
             f"  H2 pooled - HG-DAgger: effect +{h2[0]:.1f} points (stated), SD {h2[1]:.3f} (d = {h2[0] / h2[1]:.2f})",
             f"  one-sided t over lineages at {ALPHA} / {N_TESTS} = {level:.4f}; power by Monte Carlo (200,000 draws)",
             "  n   power H1  power H2"]
    chosen = None
    for n in range(4, N_MAX + 1):
        p1, p2 = power(*h1, n, level), power(*h2, n, level)
        lines.append(f"  {n:2d}  {p1:.3f}     {p2:.3f}")
        if chosen is None and n >= N_MIN and min(p1, p2) >= POWER:
            chosen = n
    chosen = chosen or N_MAX
    # the SDs are estimates from five lineages: the power at the chosen n if the true SD were at the upper end of a
    # one-sided 80 % interval (sqrt(4 / chi2_0.2(4)) = 1.56 times the estimate), and the new set's 300 scenarios
    # (against the pilot's 100) only shrink the scenario part of the SD: both said, neither changes the rule
    up = math.sqrt(4 / 1.6488)
    lines.append(f"  sensitivity: at n = {chosen} with both SDs x {up:.2f} (upper 80 % bound of an SD from 5 lineages): "
                 f"power H1 {power(h1[0], h1[1] * up, chosen, level):.3f}, H2 {power(h2[0], h2[1] * up, chosen, level):.3f}")
    lines.append(f"lineages: {chosen} (the smallest n >= {N_MIN} with power >= {POWER} for both, at most {N_MAX}): "
                 f"lineages {FIRST_LINEAGE}..{FIRST_LINEAGE + chosen - 1}")
    return chosen, lines


N_LINEAGES = 8  # `--design` prints how it was chosen; a test checks that it still says so


# ---- the new scenarios' evaluations -------------------------------------------------------------------------------
def study_policies(lineage, rows=ROWS):
    """{row: its policy file, relative to the run folder} of one lineage: pi_0, BC and the round-1 rows."""
    return {"pi0": "checkpoints/bc.pt", "bc": "checkpoints/bc_continued.pt",
            **{m: f"lineage_{lineage}/round_1/checkpoints/{m}.pt" for m in rows}}


def evaluate_lineage(root, lineage, log=print):
    """Evaluate every study policy of `lineage` in run folder `root` on NEW_SEEDS into
    root/lineage_<l>/new_scenarios/<row>.json (a row already there is kept: the step resumes)."""
    cfg = SimpleNamespace(**run_folder.read_json(os.path.join(root, "config.json")))
    if not str(cfg.name).startswith("table1_strong") or tuple(cfg.methods) != ("bc",) + ROWS:
        raise SystemExit(f"{root}: not the study's run folder (profile {cfg.name!r}, methods {cfg.methods}); run it "
                         f"as this script's docstring says")
    sample_seed = dagger.stage_seed(cfg, "eval_new")
    for row, rel in study_policies(lineage).items():
        out = os.path.join(root, f"lineage_{lineage}", NEW, f"{row}.json")
        if os.path.exists(out):
            continue
        path = os.path.join(root, rel)
        if not os.path.isfile(path):
            raise SystemExit(f"{path}: missing; finish lineage {lineage} first (python dagger.py ... --lineage "
                             f"{lineage})")
        t0 = time.time()
        os.makedirs(os.path.dirname(out), exist_ok=True)
        ok = evaluate_file(path, NEW_SEEDS, cfg.eval_repeats, sample_seed, cfg.env)
        with open(path, "rb") as fh:
            sha = hashlib.sha256(fh.read()).hexdigest()
        run_folder.write_json(out, {"success": ok.tolist(), "seeds": list(NEW_SEEDS), "policy": rel,
                                    "policy_sha256": sha, "sample_seed": sample_seed})
        log(f"lineage {lineage} {row}: {100 * ok.mean():.1f} % on {len(NEW_SEEDS)} new scenarios "
            f"({time.time() - t0:.0f} s)")


def export_policies(root, lineage, folder, rows=ROWS):
    """Copy the round-1 policies `rows` of `lineage` (weights and config, no training state) to
    folder/lineage_<l>/; every policy is read first, and one that is missing or holds a training state stops the
    export before anything is written."""
    sources = [os.path.join(root, f"lineage_{lineage}", "round_1", "checkpoints", f"{row}.pt") for row in rows]
    for src in sources:
        if "train_state" in run_folder.checkpoints.read_checkpoint(src):
            raise SystemExit(f"{src} holds a training state; the study's rows are saved for sampling only")
    dst = os.path.join(folder, f"lineage_{lineage}")
    os.makedirs(dst, exist_ok=True)
    for row, src in zip(rows, sources):
        shutil.copyfile(src, os.path.join(dst, f"{row}.pt"))
        print(f"{src} -> {dst}/{row}.pt")


# ---- the stated tests, from the committed files ------------------------------------------------------------------
def rates(files, lineage, new):
    """{row: success in points} of one lineage on the new (new=True) or the collected scenarios; BC included."""
    out = {}
    for row in ("bc",) + ROWS:
        if (s := per_scenario(files, lineage, row, "new" if new else "collected")) is not None:
            out[row] = float(s.mean())
    return out


def per_scenario(files, lineage, row, scenario_set):
    """(scenarios,) a row's success in points on each scenario of a set (the mean over its repeats), or None if the
    lineage has no such evaluation. Sets: 'collected', 'new' and (read after the fact) 'unseen', the run's own
    20000..20099."""
    if scenario_set == "new":
        key = f"lineage_{lineage}/{NEW}/{row}.json"
        if key not in files:
            return None
        assert files[key]["seeds"] == list(NEW_SEEDS), f"{key}: other seeds than the study's"
        s = files[key]["success"]
    elif scenario_set not in ("collected", "unseen"):
        raise ValueError(f"scenario set {scenario_set!r}: 'collected', 'new' or 'unseen'")
    elif row == "bc":
        s = files["eval/bc.json" if scenario_set == "collected" else "eval/bc_unseen.json"]["success"]
    elif (s := success(files, lineage, 1, row, unseen=scenario_set == "unseen")) is None:
        return None
    return 100.0 * np.asarray(s, float).mean(axis=1)


def complete(lineages):
    """The lineages holding every row on both sets."""
    return {l: f for l, f in sorted(lineages.items())
            if all(set(("bc",) + ROWS) <= set(rates(f, l, new)) for new in (False, True))}


def per_lineage(lineages):
    """{quantity: [one value a lineage]} for the tests, from complete lineages."""
    q = {k: [] for k in ("slope_new", "pooled_new", "slope_collected", "hg_bc_gap", "zero_new", "zero_collected")}
    for l, f in lineages.items():
        r = {new: rates(f, l, new) for new in (False, True)}
        for new, name in ((True, "new"), (False, "collected")):
            hg = r[new]["hg_dagger"]
            q[f"slope_{name}"].append(slope({s: r[new][m] - hg for s, m in SIGMA_ROWS}))
            q[f"zero_{name}"].append(r[new]["zero_noise"] - hg)
        q["pooled_new"].append(r[True]["pooled"] - r[True]["hg_dagger"])
        q["hg_bc_gap"].append((r[False]["hg_dagger"] - r[False]["bc"]) - (r[True]["hg_dagger"] - r[True]["bc"]))
    return q


def one_sided(values, side):
    """(mean, SE, t, df, one-sided p) of mean(values) `side` 0 ('>' or '<')."""
    mean, se, t, df, _ = t_test(values)
    p_upper = 1.0 - dagger.student_t_cdf(t, df) if math.isfinite(t) else float(t < 0)
    return mean, se, t, df, (p_upper if side == ">" else 1.0 - p_upper)


def holm(pvalues, alpha=ALPHA):
    """Holm's step-down: [rejected?] in the order given."""
    order = sorted(range(len(pvalues)), key=lambda i: pvalues[i])
    rejected, going = [False] * len(pvalues), True
    for rank, i in enumerate(order):
        going = going and pvalues[i] <= alpha / (len(pvalues) - rank)
        rejected[i] = going
    return rejected


HYPOTHESES = (("H1", "new: slope of (row − HG-DAgger) on σ ∈ {0, 4, 8, 16}, points per median step", "slope_new", ">"),
              ("H2", "new: pooled − HG-DAgger, points", "pooled_new", ">"),
              ("H3", "collected: that slope, points per median step", "slope_collected", "<"),
              ("H4", "(HG-DAgger − BC) collected − (HG-DAgger − BC) new, points", "hg_bc_gap", ">"))


def stated_tests(lineages):
    """[(name, words, side, (mean, SE, t, df, p), Holm's verdict)] of H1-H4 over complete lineages."""
    q = per_lineage(lineages)
    res = [(name, words, side, one_sided(q[key], side)) for name, words, key, side in HYPOTHESES]
    verdicts = holm([r[3][4] for r in res])
    return [(*r, v) for r, v in zip(res, verdicts)]


def table(lineages):
    """Markdown lines: every row, mean ± SE over lineages, on both sets."""
    lines = ["| row | collected (10000..10099) | new (30000..30299) |", "|---|---|---|"]
    for row in ("bc",) + ROWS:
        cells = []
        for new in (False, True):
            v = [rates(f, l, new)[row] for l, f in lineages.items()]
            cells.append(f"{np.mean(v):.1f} ± {np.std(v, ddof=1) / math.sqrt(len(v)):.1f}" if len(v) > 1
                         else f"{v[0]:.1f}")
        lines.append(f"| {row} | {cells[0]} | {cells[1]} |")
    return lines


def secondary(lineages):
    """Lines of the secondary results (two-sided, uncorrected)."""
    q, lines = per_lineage(lineages), []
    for name in ("collected", "new"):
        m, se, t, df, p = t_test(q[f"zero_{name}"])
        lines.append(f"zero_noise − HG-DAgger on {name}: {m:+.1f} ± {se:.1f} points, t({df}) = {t:.2f}, p = {p:.2g}")
    new = {row: [rates(f, l, True)[row] for l, f in lineages.items()] for row in ROWS}
    best = max(("fixed_4", "fixed_8", "fixed_16"), key=lambda r: np.mean(new[r]))
    m, se, t, df, p = t_test(np.subtract(new[best], new["pooled"]))
    lines.append(f"best fixed σ on new ({best}, chosen by its mean there) − pooled: {m:+.1f} ± {se:.1f} points, "
                 f"t({df}) = {t:.2f}, p = {p:.2g}")
    for name, new_set in (("collected", False), ("new", True)):
        lines.append(f"pi_0's class split on {name}: " + class_split(lineages, new_set))
    return lines


# ---- after the fact, not stated tests: what H1's slope is made of, the power the study had, each SE's scenarios ---
def slope_weights():
    """{row: w} with slope() = sum of w * (row - HG-DAgger): least squares is linear in what it fits."""
    s = np.array([x for x, _ in SIGMA_ROWS], float)
    w = (s - s.mean()) / ((s - s.mean()) ** 2).sum()
    return {row: float(wi) for (_, row), wi in zip(SIGMA_ROWS, w)}


def slopes(lineages, new):
    """{variant: [one slope a lineage]} on a set: 'stated' (zero_noise at sigma = 0, as H1 and H3 name it),
    'hg_at_0' (HG-DAgger itself at sigma = 0, as the pilot and the power analysis defined it) and 'fixed_only'
    (sigma 4 / 8 / 16 alone)."""
    out = {"stated": [], "hg_at_0": [], "fixed_only": []}
    for l, f in lineages.items():
        r = rates(f, l, new)
        d = {s: r[row] - r["hg_dagger"] for s, row in SIGMA_ROWS}
        fixed = {s: v for s, v in d.items() if s > 0}
        out["stated"].append(slope(d))
        out["hg_at_0"].append(slope({0: 0.0, **fixed}))
        out["fixed_only"].append(slope(fixed))
    return out


def slope_parts(lineages):
    """Markdown lines and sentences: each sigma's weight in the slope, each row - HG-DAgger (mean ± SE over lineages)
    and its part of the slope on both sets, then the slope defined without zero_noise (two ways), one-sided on the
    side of H1 (new, > 0) and H3 (collected, < 0)."""
    w = slope_weights()
    diff = {new: {row: [rates(f, l, new)[row] - rates(f, l, new)["hg_dagger"] for l, f in lineages.items()]
                  for row in w} for new in (True, False)}
    lines = ["| σ | row | weight | new: row − HG-DAgger | its part of the slope | collected: row − HG-DAgger | "
             "its part |", "|---|---|---|---|---|---|---|"]
    for s, row in SIGMA_ROWS:
        cells = [f"{np.mean(diff[new][row]):+.2f} ± {t_test(diff[new][row])[1]:.2f} | "
                 f"{w[row] * np.mean(diff[new][row]):+.3f}" for new in (True, False)]
        lines.append(f"| {s} | {row} | {w[row]:+.3f} | {cells[0]} | {cells[1]} |")
    total = {new: float(np.mean(slopes(lineages, new)["stated"])) for new in (True, False)}
    lines.append(f"| | the stated slope | | | {total[True]:+.3f} | | {total[False]:+.3f} |")
    share = w["zero_noise"] * np.mean(diff[True]["zero_noise"])
    lines.append(f"zero_noise's part of the slope on new: {share:+.3f} of {total[True]:+.3f}"
                 + (f" ({100 * share / total[True]:.0f} %)" if total[True] else ""))
    for variant, words in (("hg_at_0", "with HG-DAgger at σ = 0 (the pilot's slope)"),
                           ("fixed_only", "over σ 4 / 8 / 16 alone")):
        parts = []
        for new, name, side in ((True, "new", ">"), (False, "collected", "<")):
            m, se, t, df, p = one_sided(slopes(lineages, new)[variant], side)
            parts.append(f"{name} {m:+.3f} ± {se:.3f}, t({df}) = {t:.2f}, p = {p:.2g} ({side} 0)")
        lines.append(f"the slope {words}: " + "; ".join(parts))
    return lines


def lineages_needed(effect, sd, level, target=POWER, n_max=60):
    """The smallest n (2..n_max) whose one-sided t test at `level` has power >= target, or None."""
    return next((n for n in range(2, n_max + 1) if power(effect, sd, n, level) >= target), None)


def observed_power(lineages, pilot):
    """Lines: H1's and H2's power at the design's effects and level with the SDs the study observed, beside the
    pilot's SDs the design used."""
    d, q, n, level = pilot_differences(pilot, unseen=True), per_lineage(lineages), len(lineages), ALPHA / N_TESTS
    h1_effect = float(np.mean(d["slope"]))
    h1_sd, h1_pilot = float(np.std(q["slope_new"], ddof=1)), float(np.std(d["slope"], ddof=1))
    h2_sd, h2_pilot = float(np.std(q["pooled_new"], ddof=1)), float(np.std(d["pooled"], ddof=1))
    p1, p2 = power(h1_effect, h1_sd, n, level), power(H2_EFFECT, h2_sd, n, level)
    need = lineages_needed(h1_effect, h1_sd, level)
    return [f"the power the study had (the design's effects and level {ALPHA} / {N_TESTS} = {level:.4f}, the SDs "
            f"observed over these {n} lineages):",
            f"  H1: the design sized the pilot's slope (HG-DAgger at σ = 0), +{h1_effect:.3f} points per median step; "
            f"the stated slope's SD is {h1_sd:.3f}, {h1_sd / h1_pilot:.2f} × the pilot's {h1_pilot:.3f}: power "
            f"{p1:.2f} at {n} lineages; {100 * POWER:.0f} % needs {need if need else 'more than 60'}",
            f"  H2: +{H2_EFFECT:.1f} points, SD {h2_sd:.3f} (the pilot's {h2_pilot:.3f}): power "
            f"{'> 0.99' if p2 > 0.99 else f'{p2:.2f}'} at {n} lineages"]


def scenario_terms(lineages, key):
    """per_lineage()[key] spread over the scenarios: {set: (lineages, scenarios) array} whose means over the
    scenarios, summed over the sets, are each lineage's value. After the fact, also 'hg_bc_new_unseen' and
    'zero_new_unseen': (HG-DAgger - BC) and (zero_noise - HG-DAgger) on new minus the same on the run's unseen set."""
    ls = list(lineages)

    def diff(row, base, scenario_set):
        return np.array([per_scenario(lineages[l], l, row, scenario_set) - per_scenario(lineages[l], l, base,
                                                                                        scenario_set) for l in ls])

    if key == "hg_bc_gap":
        return {"collected": diff("hg_dagger", "bc", "collected"), "new": -diff("hg_dagger", "bc", "new")}
    if key.endswith("_new_unseen"):
        row, base = ("hg_dagger", "bc") if key.startswith("hg_bc") else ("zero_noise", "hg_dagger")
        return {"new": diff(row, base, "new"), "unseen": -diff(row, base, "unseen")}
    name, set_name = key.rsplit("_", 1)                 # slope_new, slope_collected, pooled_new, zero_new, ...
    if name == "slope":
        return {set_name: sum(w * diff(row, "hg_dagger", set_name) for row, w in slope_weights().items())}
    return {set_name: diff("pooled" if name == "pooled" else "zero_noise", "hg_dagger", set_name)}


def mean_squares(table):
    """(MS_L, MS_S, MS_E): the lineage, scenario and residual mean squares of a (lineages R, scenarios C) table,
    the two-way analysis of variance with one value a cell (df R - 1, C - 1, (R - 1)(C - 1))."""
    y = np.asarray(table, float)
    r, c = y.shape
    grand, lineage, scenario = y.mean(), y.mean(axis=1), y.mean(axis=0)
    residual = y - lineage[:, None] - scenario[None, :] + grand          # (R, C)
    return (c * ((lineage - grand) ** 2).sum() / (r - 1), r * ((scenario - grand) ** 2).sum() / (c - 1),
            (residual ** 2).sum() / ((r - 1) * (c - 1)))


def components_se(terms, level=0.95):
    """(mean, SE, low, high) of the mean over lineages and scenarios of `terms` ({set: (R, C_set) table}, the sets'
    means summed) when the lineages and each set's scenarios are both drawn: by variance components. For one set,
    SE^2 = (MS_L + MS_S - MS_E) / (R C): the lineages' SE^2, MS_L / (R C), plus the scenarios' part,
    (MS_S - MS_E) / (R C), an estimate of a variance taken as 0 where it falls below. Over several sets, the
    lineages' SE^2 of the summed values plus each set's scenario part. A t interval on the lineages' df, R - 1."""
    tables = [np.asarray(m, float) for m in terms.values()]
    r = tables[0].shape[0]
    values = sum(m.mean(axis=1) for m in tables)                        # (R,) each lineage's quantity
    se2 = values.var(ddof=1) / r
    for m in tables:
        _, ms_s, ms_e = mean_squares(m)
        se2 += max(ms_s - ms_e, 0.0) / (r * m.shape[1])
    mean, se = float(values.mean()), math.sqrt(se2)
    half = t_quantile(0.5 + level / 2, r - 1) * se
    return mean, se, mean - half, mean + half


def scenario_part(lineages):
    """Markdown lines: each stated and secondary quantity's SE over lineages on fixed scenario sets beside its SE with
    the scenarios drawn too (variance components), the mean squares it rests on, and the t interval; then two
    differences between the new set and the run's unseen one."""
    lines = ["| quantity | mean | SE over lineages | MS_L / MS_S / MS_E | SE, variance components | 95 % t interval |",
             "|---|---|---|---|---|---|"]
    named = [("H1 slope, new", "slope_new"), ("H2 pooled − HG-DAgger, new", "pooled_new"),
             ("H3 slope, collected", "slope_collected"), ("H4 (HG-DAgger − BC) collected − new", "hg_bc_gap"),
             ("zero_noise − HG-DAgger, new", "zero_new"), ("zero_noise − HG-DAgger, collected", "zero_collected"),
             ("(HG-DAgger − BC) new − unseen (20000..20099)", "hg_bc_new_unseen"),
             ("(zero_noise − HG-DAgger) new − unseen", "zero_new_unseen")]
    for name, key in named:
        terms = scenario_terms(lineages, key)
        mean, se, low, high = components_se(terms)
        per_lineage_values = sum(m.mean(axis=1) for m in terms.values())
        ms = "; ".join((f"{s} " if len(terms) > 1 else "") + " / ".join(f"{x:.0f}" if x >= 100 else f"{x:.2f}"
                                                                         for x in mean_squares(m))
                       for s, m in terms.items())
        lines.append(f"| {name} | {mean:+.3f} | {t_test(per_lineage_values)[1]:.3f} | {ms} | {se:.3f} | "
                     f"{low:+.3f} … {high:+.3f} |")
    return lines


def pi0_class(files, lineage, new):
    """(scenarios,) pi_0's class (never / sometimes / always solved over its repeats) on a set."""
    ev = files[f"lineage_{lineage}/{NEW}/pi0.json"] if new else files["eval/pi0.json"]
    s = np.asarray(ev["success"], bool)
    solved = s.sum(axis=1)
    return np.where(solved == 0, "never", np.where(solved == s.shape[1], "always", "sometimes"))


def class_split(lineages, new):
    """pooled − HG-DAgger and fixed_16 − HG-DAgger by pi_0's class, mean ± SE over lineages, in a line."""
    parts = []
    for row in ("pooled", "fixed_16"):
        for cls in ("never", "sometimes", "always"):
            d = []
            for l, f in lineages.items():
                c = pi0_class(f, l, new) == cls
                get = (lambda m: np.asarray(f[f"lineage_{l}/{NEW}/{m}.json"]["success"], float)) if new else \
                      (lambda m: success(f, l, 1, m))
                if c.any():
                    d.append(100.0 * (get(row)[c].mean() - get("hg_dagger")[c].mean()))
            n = int((pi0_class(next(iter(lineages.values())), next(iter(lineages)), new) == cls).sum())
            if len(d) > 1:
                parts.append(f"{row} {cls} ({n} sc.) {np.mean(d):+.1f} ± {np.std(d, ddof=1) / math.sqrt(len(d)):.1f}")
    return "; ".join(parts)


def pooled_sigma(files, lineage):
    """The pooled Sigma-bar^alpha's size as an isotropic sigma in the paper's median steps: sqrt(trace / dof)."""
    c = files[f"lineage_{lineage}/round_1/calibration.json"]
    pooled = np.asarray(c["pooled"], float)
    return float(math.sqrt(np.trace(pooled) / pooled.shape[0]) / c["paper_median_step"])


def figure(lineages, path):
    """Success against sigma on the collected and on the new scenarios, mean over lineages with 95 % t intervals
    (experiment/report.py's plot_success_vs_sigma, which a run's report draws for its own two sets)."""
    ls = list(lineages)
    levels = {float(s): row for s, row in SIGMA_ROWS}
    sigma = float(np.mean([pooled_sigma(lineages[l], l) for l in ls]))
    panels = [(title, {row: [rates(lineages[l], l, new)[row] for l in ls] for row in ("bc",) + ROWS}, levels, sigma)
              for new, title in ((False, "collected: the 100 scenarios of the rounds (the paper's protocol)"),
                                 (True, f"new: the {len(NEW_SEEDS)} scenarios {NEW_SEEDS[0]}..{NEW_SEEDS[-1]}"))]
    report.plot_success_vs_sigma(panels, path)


def paired_points(lineages, new):
    """[(row, sigma per lineage, row - HG-DAgger per lineage in points)] on a set: zero_noise at sigma 0, the fixed
    rows at theirs, pooled at each lineage's calibrated sigma (pooled_sigma)."""
    sigma, out = {row: float(s) for s, row in SIGMA_ROWS}, []
    for row in ("zero_noise", "fixed_4", "fixed_8", "fixed_16", "pooled"):
        x, d = [], []
        for l, f in lineages.items():
            r = rates(f, l, new)
            x.append(pooled_sigma(f, l) if row == "pooled" else sigma[row])
            d.append(r[row] - r["hg_dagger"])
        out.append((row, x, d))
    return out


def paired_figure(lineages, path):
    """What the tests compare: each row - HG-DAgger per lineage (points), their mean with its paired 95 % t interval
    (none for one lineage), against sigma; HG-DAgger at sigma = 0 and 0. One panel a set, each with its own y-axis."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(lineages)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5), layout="constrained")
    for ax, new, title in ((axes[0], False, "collected: the 100 scenarios of the rounds (the paper's protocol)"),
                           (axes[1], True, f"new: the {len(NEW_SEEDS)} scenarios {NEW_SEEDS[0]}..{NEW_SEEDS[-1]}")):
        ax.axhline(0.0, color="gray", lw=0.8)
        ax.plot([0.0], [0.0], "s", color="k", mfc="none", markersize=10, mew=1.5, zorder=5,
                label="HG-DAgger at σ = 0 (0 by definition)")
        for row, x, d in paired_points(lineages, new):
            colour = "C3" if row == "pooled" else "C0"
            jitter = np.linspace(-0.3, 0.3, n) if row != "pooled" else np.zeros(n)   # the lineages side by side
            ax.scatter(np.add(x, jitter), d, s=14, color=colour, alpha=0.45, lw=0,
                       label="one lineage" if row == "zero_noise" else None)
            half = t_quantile(0.975, n - 1) * np.std(d, ddof=1) / math.sqrt(n) if n > 1 else 0.0
            ax.errorbar([np.mean(x)], [np.mean(d)], yerr=[half], marker="*" if row == "pooled" else "o",
                        markersize=11 if row == "pooled" else 6, capsize=4, color=colour, lw=1.6, ls="none",
                        label=(rf"pooled $\bar\Sigma^\alpha$ at its calibrated σ (≈ {np.mean(x):.1f}): mean, 95 % t "
                               "interval") if row == "pooled" else
                        ("zero_noise (σ = 0) and fixed σ: mean, 95 % t interval" if row == "zero_noise" else None))
        ax.set_title(f"{title}\n{n} lineages, each row minus its lineage's HG-DAgger" if n > 1 else
                     f"{title}\n1 lineage: no interval", fontsize=9)
        ax.set_xticks([0, 4, 8, 16])
        ax.set_xlabel("noise σ (the paper's median steps)")
        ax.grid(alpha=0.3)
        ax.set_ylabel("row − HG-DAgger (success, points)")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=2, fontsize=8, frameon=False)  # below both panels
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--design", action="store_true", help="print the power analysis and the lineage count")
    p.add_argument("--evaluate", metavar="RUN", help="evaluate lineage --lineage of run folder RUN on the new set")
    p.add_argument("--export-policies", metavar="RUN", help="copy lineage --lineage's round-1 policies of RUN to "
                   "benchmarks/results/noise_transfer/policies/")
    p.add_argument("--lineage", type=int, help="the lineage for --evaluate / --export-policies")
    p.add_argument("--results", default=RESULTS, help="the committed lineage files (default %(default)s)")
    p.add_argument("--figure", metavar="PNG", help="also draw success against sigma to PNG")
    p.add_argument("--paired-figure", metavar="PNG", help="also draw each row - HG-DAgger per lineage to PNG")
    a = p.parse_args(argv)
    if a.design:
        n, lines = design(load_lineages(PILOT))
        print("\n".join(lines))
        return
    if a.evaluate or a.export_policies:
        if a.lineage is None or a.lineage < FIRST_LINEAGE:
            p.error(f"--lineage {a.lineage}: give the study's lineage (>= {FIRST_LINEAGE})")
        if a.evaluate:
            evaluate_lineage(a.evaluate, a.lineage)
        else:
            export_policies(a.export_policies, a.lineage, os.path.join(RESULTS, "policies"))
        return
    lineages = complete(load_lineages(a.results))
    print(f"{a.results}: {len(lineages)} complete lineage(s) {sorted(lineages)} of the stated {N_LINEAGES} "
          f"({FIRST_LINEAGE}..{FIRST_LINEAGE + N_LINEAGES - 1})")
    print("\n".join(table(lineages)))
    if len(lineages) >= 2:
        print(f"\n| test | side | mean | SE | t | df | p (one-sided) | Holm at {ALPHA} |\n|---|---|---|---|---|---|---|---|")
        for name, words, side, (m, se, t, df, pv), ok in stated_tests(lineages):
            print(f"| {name}: {words} | {side} 0 | {m:+.3f} | {se:.3f} | {t:.2f} | {df} | {pv:.2g} | "
                  f"{'rejected' if ok else 'not rejected'} |")
        if len(lineages) < N_LINEAGES:
            print(f"(an interim look at {len(lineages)} lineages: the stated tests are read at {N_LINEAGES})")
        print("\nsecondary (two-sided, uncorrected):")
        print("\n".join("  " + line for line in secondary(lineages)))
        print("\nafter the fact, not stated tests:")
        print("\nwhat H1's slope is made of (least squares is linear in what it fits: the slope is the sum over σ "
              "of weight × (row − HG-DAgger), mean ± SE over lineages):")
        print("\n".join(slope_parts(lineages)))
        print()
        print("\n".join(observed_power(lineages, load_lineages(PILOT))))
        print("\nthe scenarios' part of each SE, by variance components: the lineage, scenario and residual mean "
              "squares (MS_L, MS_S, MS_E) of each lineage × scenario table, SE² = (MS_L + MS_S − MS_E) / (R·C) "
              "(over two sets, each set's scenario part added), a t interval on the lineages' df (R − 1)")
        print("\n".join(scenario_part(lineages)))
    if a.figure:
        figure(lineages, a.figure)
        print(f"figure: {a.figure}")
    if a.paired_figure:
        paired_figure(lineages, a.paired_figure)
        print(f"figure: {a.paired_figure}")


if __name__ == "__main__":
    main()
