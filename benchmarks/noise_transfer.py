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
                                      # (then, after the fact, the scenarios' part of each SE: a two-way bootstrap)
    python benchmarks/noise_transfer.py --figure benchmarks/figures/noise_transfer.png
"""
from __future__ import annotations

import argparse
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
def study_policies(lineage):
    """{row: its policy file, relative to the run folder} of one lineage: pi_0, BC and the round-1 rows."""
    return {"pi0": "checkpoints/bc.pt", "bc": "checkpoints/bc_continued.pt",
            **{m: f"lineage_{lineage}/round_1/checkpoints/{m}.pt" for m in ROWS}}


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


def export_policies(root, lineage, folder):
    """Copy the round-1 policies of `lineage` (weights and config, no training state) to folder/lineage_<l>/."""
    dst = os.path.join(folder, f"lineage_{lineage}")
    os.makedirs(dst, exist_ok=True)
    for row in ROWS:
        src = os.path.join(root, f"lineage_{lineage}", "round_1", "checkpoints", f"{row}.pt")
        payload = run_folder.checkpoints.read_checkpoint(src)
        if "train_state" in payload:
            raise SystemExit(f"{src} holds a training state; the study's rows are saved for sampling only")
        shutil.copyfile(src, os.path.join(dst, f"{row}.pt"))
        print(f"{src} -> {dst}/{row}.pt")


# ---- the stated tests, from the committed files ------------------------------------------------------------------
def rates(files, lineage, new):
    """{row: success in points} of one lineage on the new (new=True) or the collected scenarios; BC included."""
    out = {}
    for row in ("bc",) + ROWS:
        if (s := per_scenario(files, lineage, row, new)) is not None:
            out[row] = float(s.mean())
    return out


def per_scenario(files, lineage, row, new):
    """(scenarios,) a row's success in points on each scenario of a set (the mean over its repeats), or None if the
    lineage has no such evaluation."""
    if new:
        key = f"lineage_{lineage}/{NEW}/{row}.json"
        if key not in files:
            return None
        assert files[key]["seeds"] == list(NEW_SEEDS), f"{key}: other seeds than the study's"
        s = files[key]["success"]
    elif row == "bc":
        s = files["eval/bc.json"]["success"]
    elif (s := success(files, lineage, 1, row)) is None:
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


# ---- after the fact: the scenarios' part of each SE (not a stated test) --------------------------------------------
BOOT_DRAWS = 2000


def slope_weights():
    """{row: w} with slope() = sum of w * (row - HG-DAgger): least squares is linear in what it fits."""
    s = np.array([x for x, _ in SIGMA_ROWS], float)
    w = (s - s.mean()) / ((s - s.mean()) ** 2).sum()
    return {row: float(wi) for (_, row), wi in zip(SIGMA_ROWS, w)}


def scenario_terms(lineages, key):
    """per_lineage()[key] spread over the scenarios: {new?: (lineages, scenarios) array} whose means over the
    scenarios, summed over the sets, are each lineage's value."""
    ls = list(lineages)

    def diff(row, base, new):
        return np.array([per_scenario(lineages[l], l, row, new) - per_scenario(lineages[l], l, base, new) for l in ls])

    def slope_on(new):
        return sum(w * diff(row, "hg_dagger", new) for row, w in slope_weights().items())

    if key == "hg_bc_gap":
        return {False: diff("hg_dagger", "bc", False), True: -diff("hg_dagger", "bc", True)}
    name, set_name = key.rsplit("_", 1)                 # slope_new, slope_collected, pooled_new, zero_new, ...
    new = set_name == "new"
    if name == "slope":
        return {new: slope_on(new)}
    return {new: diff("pooled" if name == "pooled" else "zero_noise", "hg_dagger", new)}


def two_way_bootstrap(terms, draws=BOOT_DRAWS, seed=0):
    """(SE, 2.5 %, 97.5 %) of the mean over lineages when the lineages and, apart, each set's scenarios are drawn
    again with replacement. The stated tests' SE is over lineages on fixed scenario sets: it leaves out which
    scenarios were drawn, which this puts in. On the collected set it is an approximation: another draw of those
    scenarios would also have changed the interventions recorded on them, which this holds fixed."""
    rng = np.random.default_rng(seed)
    n = len(next(iter(terms.values())))
    values = np.empty(draws)
    for d in range(draws):
        i = rng.integers(0, n, n)
        values[d] = sum(m[i][:, rng.integers(0, m.shape[1], m.shape[1])].mean() for m in terms.values())
    low, high = np.percentile(values, [2.5, 97.5])
    return float(values.std(ddof=1)), float(low), float(high)


def scenario_part(lineages):
    """Markdown lines: each stated and secondary quantity's SE over lineages beside its SE with the scenarios drawn
    again too."""
    q = per_lineage(lineages)
    lines = ["| quantity | mean | SE over lineages | SE, scenarios drawn again too | 95 % bootstrap interval |",
             "|---|---|---|---|---|"]
    named = [("H1 slope, new", "slope_new"), ("H2 pooled − HG-DAgger, new", "pooled_new"),
             ("H3 slope, collected", "slope_collected"), ("H4 (HG-DAgger − BC) collected − new", "hg_bc_gap"),
             ("zero_noise − HG-DAgger, new", "zero_new"), ("zero_noise − HG-DAgger, collected", "zero_collected")]
    for name, key in named:
        v = np.asarray(q[key])
        se, low, high = two_way_bootstrap(scenario_terms(lineages, key))
        lines.append(f"| {name} | {v.mean():+.3f} | {v.std(ddof=1) / math.sqrt(len(v)):.3f} | {se:.3f} | "
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


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--design", action="store_true", help="print the power analysis and the lineage count")
    p.add_argument("--evaluate", metavar="RUN", help="evaluate lineage --lineage of run folder RUN on the new set")
    p.add_argument("--export-policies", metavar="RUN", help="copy lineage --lineage's round-1 policies of RUN to "
                   "benchmarks/results/noise_transfer/policies/")
    p.add_argument("--lineage", type=int, help="the lineage for --evaluate / --export-policies")
    p.add_argument("--results", default=RESULTS, help="the committed lineage files (default %(default)s)")
    p.add_argument("--figure", metavar="PNG", help="also draw the figure to PNG")
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
        print(f"\nafter the fact, not a stated test: the scenarios' part of each SE (a two-way bootstrap, "
              f"{BOOT_DRAWS} draws: the lineages and each set's scenarios drawn again with replacement)")
        print("\n".join(scenario_part(lineages)))
    if a.figure:
        figure(lineages, a.figure)
        print(f"figure: {a.figure}")


if __name__ == "__main__":
    main()
