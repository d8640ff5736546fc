"""What the relabelled chunks cost: the servo as converted up to 6192871 against the paper's PD label (a stated study).

Without noise the noised rows' pipeline cost 1.7 points on new scenarios in the noise-transfer study (zero_noise -
HG-DAgger on 30000..30299), and at sigma = 0 such a row differs from HG-DAgger only in its intervention rows'
labels: the servo's return chunk instead of the recorded one (benchmarks/relabel_diagnostic.py measures how far
apart they are). The servo then was the servo as converted up to 6192871 (its speed cap half the authors' in
radians: its knobs converted with the per-joint median step where the authors' unit is a step's L2 norm over the
joints). This study tests whether the paper's PD label (relabel.pd_return_chunk, Sec. IV-E) removes that cost, and
whether the noise then pays over HG-DAgger. The design (benchmarks/results/relabel_cost/README.md):

  lineages     13, 14, ..., 13 + N_LINEAGES - 1 of the table1_strong profile from its committed start, K = 1
  rows         HG-DAgger and {servo, PD} x {sigma = 0, fixed sigma 8, pooled}: zero_noise, fixed_8, pooled (the old
               servo (up to 6192871), every profile's label then) and zero_noise_pd, fixed_8_pd, pooled_pd (the same
               noise, the PD label). The lineage files keep these names; from 2f55526 the rows zero_noise, fixed_8,
               pooled are made with PD and the _pd rows are gone: the training commands below are e417b0a's
  scenarios    collected: the 100 evaluation scenarios 10000..10099 (the run's eval/<row>.json); new: lineage L's own
               300 scenarios new_seeds(L) = 100000 + 1000 L .. + 299, drawn by no stage and by no other lineage
  tests        one-sided t over lineages (df = lineages - 1), Holm over T1-T3 at 0.05:
    T1  new: zero_noise_pd - zero_noise  > 0   (the label's cost)
    T2  new: fixed_8_pd - HG-DAgger      > 0
    T3  new: pooled_pd - HG-DAgger       > 0
  secondary    two-sided, uncorrected: T1-T3 on the collected scenarios; pooled and pooled_pd against HG-DAgger and
               each other on both sets; the 2 x 3 interaction (the label's effect at sigma 8 and at pooled minus
               its effect at sigma = 0, each, and both at once); printed with Holm's adjusted p over them
  SEs          over lineages. On the collected set (one set of 100 for every lineage, crossed) also the
               variance-components SE over the lineage x scenario table, which counts the scenarios' draw, its t on
               Satterthwaite's df (not lineages - 1: most of it is the scenarios' mean square, C - 1 df). On the new
               set (each lineage its own scenarios, nested) the lineage SE is the SE.
  conditional  on one pi_0: every lineage continues the start's pi_0 and BC row (and D0), here and in the
               noise-transfer study, so no SE of either carries the draw of pi_0

Commands (a lineage at a time; each step resumes; benchmarks/results/relabel_cost/README.md has them whole):

    python benchmarks/relabel_cost.py --design                  # the power analysis, the lineage count, the cost
    python dagger.py --profile table1_strong --methods hg_dagger,zero_noise,fixed_8,pooled,zero_noise_pd,\
        fixed_8_pd,pooled_pd --lineages 26 --lineage L --out runs/relabel_cost
    python benchmarks/relabel_cost.py --evaluate runs/relabel_cost --lineage L   # its new scenarios, its D_1's labels
    python dagger.py --profile table1_strong --methods ... --lineages 26 --out runs/relabel_cost --report \
        --export-lineages benchmarks/results/relabel_cost
    python benchmarks/relabel_cost.py --figure benchmarks/figures/relabel_cost.png   # the table, the tests, the figure
"""
from __future__ import annotations

import argparse
import functools
import hashlib
import math
import os
import sys
import time
from types import SimpleNamespace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))
import noise_transfer  # noqa: E402  (the pilot's files, its power function, its one-sided t and Holm)
from evaluate_policy import evaluate_file, t_quantile  # noqa: E402
from noise_trade import success  # noqa: E402
from paired_bc import load_lineages, t_test  # noqa: E402

import dagger  # noqa: E402
from experiment import run_folder  # noqa: E402

t_quantile = functools.lru_cache(maxsize=None)(t_quantile)

CONDITIONAL = ("every SE here, and every SE of the noise-transfer study (benchmarks/noise_transfer.py), is conditional "
               "on one π0: each lineage continues the start's π0 and BC row (benchmarks/results/table1_strong/start), "
               "so no SE carries the draw of π0 or of D0; another start may move every row")
FIRST_LINEAGE = 13  # lineages 0-4 are table1_strong's, 5-12 the noise-transfer study's
SERVO_ROWS = ("zero_noise", "fixed_8", "pooled")
PD_ROWS = tuple(f"{row}_pd" for row in SERVO_ROWS)
ROWS = ("hg_dagger",) + SERVO_ROWS + PD_ROWS
NEW_PER_LINEAGE = 300  # new scenarios a lineage draws
NEW_SEED_START, NEW_SEED_STRIDE = 100_000, 1_000  # lineage L: 100000 + 1000 L .. + 299
NEW = "new_scenarios"  # lineage_<l>/new_scenarios/<row>.json: the study's evaluations, exported with the lineage
DIAGNOSTIC = "relabel_diagnostic.json"  # lineage_<l>/relabel_diagnostic.json: the offline labels of its D_1
RESULTS = os.path.join(HERE, "results", "relabel_cost")
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
    'var_error', 'se', 'df', 'lineage_se'}. se² = var_lineage / R + var_scenario / C + var_error / (R C), each component
    floored at 0, which is (MS_L + MS_S − MS_E) / (R C) where both floors are inactive: the SE of the grand mean when
    the lineages and the scenarios are both drawn again. df: Satterthwaite's effective degrees of freedom of that se²
    (satterthwaite_df), the df of its t; not R − 1. lineage_se: the SD of the lineage means / √R (the scenarios held
    fixed). Where each lineage has its own scenarios (the new set), column j is each lineage's j-th scenario: no
    scenario effect is shared, MS_S estimates MS_E, and the lineage SE is the SE (this one, floored, only checks it)."""
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
            "df": satterthwaite_df(ms_l, ms_s, ms_e, R, C, lineage=ms_l > ms_e, scenario=ms_s > ms_e),
            "lineage_se": float(row_means.std(ddof=1) / math.sqrt(R))}


def satterthwaite_df(ms_l, ms_s, ms_e, R, C, lineage=True, scenario=True):
    """Satterthwaite's effective df of se² = Σ c_i MS_i / (R C): (Σ c_i MS_i)² / Σ (c_i MS_i)² / df_i, with df
    R − 1, C − 1 and (R − 1)(C − 1) for MS_L, MS_S, MS_E. Both components in: c = (1, 1, −1); a component floored at
    0 drops its MS and gives its −MS_E back (var_L out: se² = MS_S / (R C); both out: MS_E / (R C)). On the collected
    set MS_S (C − 1 df) carries most of se², so the df lies far above the lineages' R − 1."""
    parts = [(c * ms, df) for c, ms, df in ((float(lineage), ms_l, R - 1), (float(scenario), ms_s, C - 1),
                                           (1.0 - lineage - scenario, ms_e, (R - 1) * (C - 1))) if c]
    total = sum(v for v, _ in parts)
    spread = sum(v * v / df for v, df in parts)
    return total * total / spread if spread > 0 else math.inf


def vc_t(mean, se):
    """mean / se, or 0 / ±inf where the SE is 0."""
    return mean / se if se > 0 else (0.0 if mean == 0 else math.copysign(math.inf, mean))


def vc_p(mean, se, df, side):
    """The p of mean `side` 0 ('>', '<' or 'two-sided') by t = mean / se on `df` (Satterthwaite's)."""
    t = vc_t(mean, se)
    upper = 0.5 if t == 0 else 1.0 - dagger.student_t_cdf(t, df)
    return {">": upper, "<": 1.0 - upper}.get(side, 2.0 * min(upper, 1.0 - upper))


def holm_adjusted(pvalues):
    """Holm's adjusted p in the order given: the k-th smallest times (m − k + 1), running maximum, capped at 1."""
    order = sorted(range(len(pvalues)), key=lambda i: pvalues[i])
    out, running = [1.0] * len(pvalues), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(pvalues) - rank) * pvalues[i]))
        out[i] = running
    return out


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


# ---- the study's own evaluations: each lineage's new scenarios, and the offline labels of its D_1 ------------------
def study_policies(lineage):
    """{row: its policy file, relative to the run folder} of one lineage: pi_0, BC and the round-1 rows."""
    return noise_transfer.study_policies(lineage, rows=ROWS)


def study_config(root, lineage):
    """The run folder's config (a namespace) if it is the study's and `lineage` one of its lineages; else SystemExit
    naming what is wrong, before anything is written."""
    path = os.path.join(root, "config.json")
    if not os.path.isfile(path):
        raise SystemExit(f"{root}: no config.json; give the study's run folder (python dagger.py --profile "
                         f"table1_strong --methods {','.join(ROWS)} --lineages 26 --lineage L --out RUN)")
    cfg = SimpleNamespace(**run_folder.read_json(path))
    if not str(cfg.name).startswith("table1_strong") or tuple(cfg.methods) != ("bc",) + ROWS:
        raise SystemExit(f"{root}: not the study's run folder (profile {cfg.name!r}, methods {cfg.methods}); run it "
                         f"as this script's docstring says")
    if not FIRST_LINEAGE <= lineage < cfg.lineages:
        raise SystemExit(f"--lineage {lineage}: the study's lineages are {FIRST_LINEAGE}..{cfg.lineages - 1} of {root}")
    return cfg


def evaluate_lineage(root, lineage, log=print):
    """Evaluate every study policy of `lineage` in run folder `root` on the lineage's own new scenarios into
    root/lineage_<l>/new_scenarios/<row>.json (3 repeats, one sampling seed for every row: stage_seed(cfg,
    "eval_new", lineage)), then its D_1's offline labels (diagnose_lineage). A file already there is kept: the step
    resumes. A missing policy stops it before anything is written."""
    cfg = study_config(root, lineage)
    policies = study_policies(lineage)
    missing = [rel for rel in policies.values() if not os.path.isfile(os.path.join(root, rel))]
    if missing:
        raise SystemExit(f"{root}: {', '.join(missing)} missing; finish lineage {lineage} first (python dagger.py ... "
                         f"--lineage {lineage} --out {root})")
    write_new_evaluations(root, lineage, cfg, policies, log)
    diagnose_lineage(root, lineage, cfg, log)


def write_new_evaluations(root, lineage, cfg, policies, log=print):
    """root/lineage_<l>/NEW/<name>.json for each policy {name: path under root}: its success on the lineage's own
    new scenarios (new_seeds), cfg.eval_repeats each, one sampling seed for every policy of the lineage
    (stage_seed(cfg, "eval_new", L): the rows pair), with the policy's path and SHA-256. A file already there is
    kept: the step resumes. Shared by the studies that evaluate on new scenarios (benchmarks/table1_pd.py too)."""
    seeds, sample_seed = new_seeds(lineage), dagger.stage_seed(cfg, "eval_new", lineage)
    t0 = time.time()
    for i, (name, rel) in enumerate(policies.items()):
        out = os.path.join(root, f"lineage_{lineage}", NEW, f"{name}.json")
        if os.path.exists(out):
            continue
        t1 = time.time()
        os.makedirs(os.path.dirname(out), exist_ok=True)
        ok = evaluate_file(os.path.join(root, rel), seeds, cfg.eval_repeats, sample_seed, cfg.env)
        with open(os.path.join(root, rel), "rb") as fh:
            sha = hashlib.sha256(fh.read()).hexdigest()
        run_folder.write_json(out, {"success": ok.tolist(), "seeds": list(seeds), "policy": rel,
                                    "policy_sha256": sha, "sample_seed": sample_seed})
        left = (time.time() - t0) / (i + 1) * (len(policies) - i - 1)
        log(f"lineage {lineage} {name}: {100 * ok.mean():.1f} % on its {len(seeds)} new scenarios {seeds[0]}.."
            f"{seeds[-1]} ({time.time() - t1:.0f} s; {i + 1}/{len(policies)}, ~{left / 60:.0f} min left)")


def diagnose_lineage(root, lineage, cfg, log=print):
    """root/lineage_<l>/relabel_diagnostic.json: benchmarks/relabel_diagnostic.py on the lineage's D_1 with the run's
    D0 statistics and H (its LABELS, velocity noise on and off; the committed files, made before 6192871, hold the old
    servo and PD; each {'rows', 'kept', 'masked', 'mean', 'median', 'p90'} in median steps, over all kept rows, those
    whose chunk stays inside its segment and those reaching its end). Descriptive: no test reads it. Kept if already
    there."""
    import relabel_diagnostic as rd
    from experiment import environments
    out = os.path.join(root, f"lineage_{lineage}", DIAGNOSTIC)
    if os.path.exists(out):
        return
    t0 = time.time()
    episodes = run_folder.load_episodes(os.path.join(root, f"lineage_{lineage}", "round_1", "D.npz"))
    stats = rd.run_statistics(cfg.env, run_folder.load_episodes(os.path.join(root, "data", "D0.npz")))
    results = rd.diagnose(episodes, functools.partial(environments.make_env, cfg.env), stats, cfg.horizon)
    run_folder.write_json(out, {
        "episodes": f"lineage_{lineage}/round_1/D.npz", "n_episodes": len(episodes),
        "expert_steps": int(sum(int(e["expert"].sum()) for e in episodes)), "median_step": stats.median_step,
        "horizon": cfg.horizon,
        "labels": [{"label": r.label, "velocity_noise": r.velocity_noise, "all": rd.summary(r),
                    "inside": rd.summary(r, ~r.reaches_end), "to_end": rd.summary(r, r.reaches_end)}
                   for r in results]})
    log(f"lineage {lineage}: its D_1's labels at sigma = 0 measured ({time.time() - t0:.0f} s): {out}")


def export_policies(root, lineage, folder):
    """Copy the round-1 policies of `lineage` (weights and config, no training state) to folder/lineage_<l>/."""
    noise_transfer.export_policies(root, lineage, folder, rows=ROWS)


# ---- the stated tests, from the committed lineage files -----------------------------------------------------------
def per_scenario(files, lineage, row, scenario_set):
    """(scenarios,) a row's success in points on each scenario of a set (the mean over its repeats), or None where
    the lineage has no such evaluation. Rows: 'pi0', 'bc' and ROWS; sets: 'collected' (10000..10099, the run's own
    evaluation) and 'new' (the lineage's own new_seeds)."""
    if scenario_set == "new":
        key = f"lineage_{lineage}/{NEW}/{row}.json"
        if key not in files:
            return None
        seeds, own = files[key]["seeds"], new_seeds(lineage)
        if seeds != list(own):
            raise ValueError(f"{key}: seeds {seeds[0]}..{seeds[-1]}, not lineage {lineage}'s own {own[0]}..{own[-1]}")
        s = files[key]["success"]
    elif scenario_set != "collected":
        raise ValueError(f"scenario set {scenario_set!r}: 'collected' or 'new'")
    elif row in ("pi0", "bc"):
        if f"eval/{row}.json" not in files:
            return None
        s = files[f"eval/{row}.json"]["success"]
    elif (s := success(files, lineage, 1, row)) is None:
        return None
    return 100.0 * np.asarray(s, float).mean(axis=1)


def complete(lineages):
    """The lineages holding BC and every row on both sets."""
    return {l: f for l, f in sorted(lineages.items())
            if all(per_scenario(f, l, row, s) is not None for row in ("bc",) + ROWS for s in ("collected", "new"))}


def combination_table(lineages, combo, scenario_set):
    """(lineages, scenarios): sum of coefficient x the row's per-scenario success (points), {row: coefficient}."""
    return np.array([sum(c * per_scenario(f, l, row, scenario_set) for row, c in combo.items())
                     for l, f in lineages.items()])


def difference(a, b):
    return {a: 1.0, b: -1.0}


def interaction(noise_row):
    """The label's effect at a noise level minus its effect at sigma = 0: (row_pd - row) - (zero_noise_pd -
    zero_noise)."""
    return {f"{noise_row}_pd": 1.0, noise_row: -1.0, "zero_noise_pd": -1.0, "zero_noise": 1.0}


# (name, words, set, {row: coefficient}, side): the stated tests, one-sided, Holm over the three
STATED = (("T1", "zero_noise_pd − zero_noise (PD − the old servo, σ 0)", "new",
           difference("zero_noise_pd", "zero_noise"), ">"),
          ("T2", "fixed_8_pd − HG-DAgger", "new", difference("fixed_8_pd", "hg_dagger"), ">"),
          ("T3", "pooled_pd − HG-DAgger", "new", difference("pooled_pd", "hg_dagger"), ">"))
# the secondary results, two-sided and uncorrected
SECONDARY = tuple((name, words, "collected", combo, "two-sided")
                  for name, words, _, combo, _ in STATED) + tuple(
    (name, words, s, combo, "two-sided") for s in ("collected", "new") for name, words, combo in (
        ("pooled − HG-DAgger", "the calibrated σ, the old servo", difference("pooled", "hg_dagger")),
        ("pooled_pd − HG-DAgger", "the calibrated σ, PD", difference("pooled_pd", "hg_dagger")),
        ("pooled_pd − pooled", "the label at the calibrated σ", difference("pooled_pd", "pooled")),
        ("fixed_8_pd − fixed_8", "the label at σ 8", difference("fixed_8_pd", "fixed_8")),
        ("I_8", "(fixed_8_pd − fixed_8) − (zero_noise_pd − zero_noise)", interaction("fixed_8")),
        ("I_pooled", "(pooled_pd − pooled) − (zero_noise_pd − zero_noise)", interaction("pooled"))))


def estimate(lineages, combo, scenario_set, side):
    """{'values' (one a lineage), 'mean', 'se' (over lineages), 't', 'df', 'p', 'vc_se' (variance components),
    'vc_df' (its Satterthwaite df), 'vc_t', 'vc_p'} of a combination on a set: a one-sample t over lineages, one-sided
    ('>', '<') or 'two-sided', and the same side's t of the mean by the variance-components SE on its own df."""
    table = combination_table(lineages, combo, scenario_set)
    # a lineage's value is a sum of multiples of 1/9 or 1/3 point: rounded off float noise, two equal values have
    # an SD of 0, not 1e-16 (a t of 1e16)
    values = np.round(table.mean(axis=1), 9)
    mean, se, t, df, p = t_test(values) if side == "two-sided" else noise_transfer.one_sided(values, side)
    vc = variance_components(table)
    return {"values": values, "mean": mean, "se": se, "t": t, "df": df, "p": p, "vc_se": vc["se"],
            "vc_df": vc["df"], "vc_t": vc_t(mean, vc["se"]), "vc_p": vc_p(mean, vc["se"], vc["df"], side)}


def stated_tests(lineages):
    """[(name, words, set, side, estimate, Holm's verdict at ALPHA)] of T1-T3 over complete lineages."""
    res = [(name, words, s, side, estimate(lineages, combo, s, side)) for name, words, s, combo, side in STATED]
    return [(*r, v) for r, v in zip(res, noise_transfer.holm([r[4]["p"] for r in res], ALPHA))]


def f_cdf(x, d1, d2):
    """P(F <= x) for Fisher's F with (d1, d2) degrees of freedom: I_{d1 x / (d1 x + d2)}(d1 / 2, d2 / 2)."""
    return 0.0 if x <= 0 else dagger.incomplete_beta(d1 / 2, d2 / 2, d1 * x / (d1 * x + d2))


def hotelling(values):
    """Hotelling's one-sample T² of mean = 0 for (n, k) values (a row a lineage, a column a quantity):
    (T², F, k, n − k, p) with T² = n x̄ᵀ S⁻¹ x̄ (S the sample covariance) and F = (n − k) / (k (n − 1)) T² on (k,
    n − k) df. For k = 1 it is the two-sided t test (T² = t²)."""
    x = np.asarray(values, float)
    n, k = x.shape
    if n <= k:
        raise ValueError(f"{n} lineages for {k} quantities: Hotelling's T² needs more lineages than quantities")
    mean, cov = x.mean(axis=0), np.atleast_2d(np.cov(x, rowvar=False, ddof=1))
    if np.linalg.matrix_rank(cov) < k:
        raise ValueError(f"the {k} quantities' covariance over {n} lineages is singular (rank "
                         f"{np.linalg.matrix_rank(cov)}): one is a fixed combination of the others")
    t2 = float(n * mean @ np.linalg.solve(cov, mean))
    f = (n - k) / (k * (n - 1)) * t2
    return t2, f, k, n - k, 1.0 - f_cdf(f, k, n - k)


def interactions(lineages, scenario_set):
    """Hotelling's T² of (I_8, I_pooled) = 0 on a set: both interactions at once."""
    return hotelling(np.column_stack([combination_table(lineages, interaction(row), scenario_set).mean(axis=1)
                                      for row in ("fixed_8", "pooled")]))


def cell(values, table=None):
    """'mean ± SE over lineages' (and '(VC SE)' where a lineage x scenario table is given), or the value alone."""
    if len(values) < 2:
        return f"{values[0]:.1f}"
    text = f"{np.mean(values):.1f} ± {np.std(values, ddof=1) / math.sqrt(len(values)):.1f}"
    return f"{text} ({variance_components(table)['se']:.1f})" if table is not None else text


def table(lineages):
    """Markdown lines: every row's success in points on both sets, mean ± SE over lineages; on the collected set
    (crossed) the variance-components SE in brackets, on the new set (nested) none: the lineage SE is the SE."""
    lines = ["| row | collected (10000..10099, one set) | new (each lineage its own 300) |", "|---|---|---|"]
    for row in ("pi0", "bc") + ROWS:
        cells = []
        for s in ("collected", "new"):
            got = [per_scenario(f, l, row, s) for l, f in lineages.items()]
            got = [g for g in got if g is not None]
            crossed = s == "collected" and len(got) > 1
            cells.append(cell([g.mean() for g in got], np.array(got) if crossed else None) if got else "—")
        lines.append(f"| {row} | {cells[0]} | {cells[1]} |")
    return lines


def tests_table(lineages):
    """Markdown lines: T1-T3 (every one on the new set, where the lineage SE is the SE) with t, one-sided p and
    Holm's verdict (at the stated lineage count; before it, an interim look, no verdict), then how far the
    variance-components SE lies from the lineage SE there: the design's check, not a second SE."""
    interim = len(lineages) < N_LINEAGES
    lines = [f"| test | set | quantity (points) | side | mean | SE lineages | t | df | p (one-sided) | "
             f"Holm at {ALPHA} |", "|---|---|---|---|---|---|---|---|---|---|"]
    gaps = []
    for name, words, s, side, e, ok in stated_tests(lineages):
        gaps.append(abs(e["vc_se"] - e["se"]))
        lines.append(f"| {name} | {s} | {words} | {side} 0 | {e['mean']:+.2f} | {e['se']:.2f} | "
                     f"{e['t']:.2f} | {e['df']} | {e['p']:.2g} | "
                     f"{'none before ' + str(N_LINEAGES) + ' lineages' if interim else 'rejected' if ok else 'not rejected'} |")
    lines.append(f"(the new set is nested, each lineage its own scenarios: the lineage SE is the SE; the "
                 f"variance-components SE, each component floored at 0, lies within {max(gaps):.2f} of it for "
                 f"T1-T3, the design's check)")
    return lines


def secondary(lineages):
    """Lines of the secondary results (two-sided, uncorrected, with Holm's adjusted p over the t tests beside each).
    On the collected set (crossed: one set of 100 for every lineage) also the variance-components SE, its t on
    Satterthwaite's df and its p: the scenarios' draw counted, which the lineage t leaves out. On the new set
    (nested) the lineage SE is the SE."""
    lines = []
    got = [(name, words, s, estimate(lineages, combo, s, side)) for name, words, s, combo, side in SECONDARY]
    adjusted = holm_adjusted([e["p"] for *_, e in got])
    for (name, words, s, e), adj in zip(got, adjusted):
        text = (f"{name} on {s} ({words}): {e['mean']:+.2f} ± {e['se']:.2f} points, t({e['df']}) = {e['t']:.2f}, "
                f"p = {e['p']:.2g} (Holm over the {len(got)}: {adj:.2g})")
        if s == "collected":
            text += (f"; var. comp. SE {e['vc_se']:.2f}, t({e['vc_df']:.0f}) = {e['vc_t']:.2f}, "
                     f"p = {e['vc_p']:.2g}")
        lines.append(text)
    for s in ("collected", "new"):
        try:
            t2, f, d1, d2, p = interactions(lineages, s)
        except ValueError as err:
            lines.append(f"I_8 and I_pooled at once on {s}: no Hotelling's T² ({err})")
            continue
        lines.append(f"I_8 and I_pooled at once on {s}: Hotelling's T² = {t2:.2f}, F({d1}, {d2}) = {f:.2f}, p = {p:.2g}")
    return lines


# after the fact, not stated: the quantities the readings quote that the stated and secondary lists leave out
AFTER = (("zero_noise − HG-DAgger", "new", difference("zero_noise", "hg_dagger"),
          "σ 0 with the old servo against the recorded chunks; the noise-transfer pilot's −1.69 ± 0.31, one set"),
         ("fixed_8 − HG-DAgger", "new", difference("fixed_8", "hg_dagger"), "σ 8 with the old servo"),
         ("zero_noise_pd − HG-DAgger", "collected", difference("zero_noise_pd", "hg_dagger"), "σ 0 with PD"))


def after_the_fact(lineages):
    """Lines: each stated test's power at the stated effect and at the effect seen (its observed SD, the level of
    the Holm step it was read at), its one-sided 95 % confidence bound; then the differences of AFTER."""
    res = stated_tests(lineages)
    n = len(lineages)
    order = sorted(range(len(res)), key=lambda i: res[i][4]["p"])
    level = {i: ALPHA / (len(res) - rank) for rank, i in enumerate(order)}
    lines = [f"the power the stated tests had ({n} lineages, each at the level of its Holm step, the SD observed "
             f"over the lineages; Monte Carlo, 200,000 draws) and the one-sided 95 % confidence bound:"]
    for i, (name, words, _, _, e, _) in enumerate(res):
        sd = float(np.std(e["values"], ddof=1))
        bound = e["mean"] - t_quantile(0.95, n - 1) * e["se"]
        stated, seen = (noise_transfer.power(effect, sd, n, level[i]) for effect in (EFFECT, abs(e["mean"])))
        lines.append(f"  {name} ({words}): SD {sd:.2f}, level {level[i]:.4f}: power {stated:.2f} at the stated "
                     f"+{EFFECT:.1f}, {seen:.2f} at the {e['mean']:+.2f} seen; one-sided 95 % bounds: > {bound:+.2f}, "
                     f"< {2 * e['mean'] - bound:+.2f}")
    lines.append("differences not in the stated lists (two-sided, lineage t; on the collected set also by the "
                 "variance components on Satterthwaite's df):")
    for name, s, combo, words in AFTER:
        e = estimate(lineages, combo, s, "two-sided")
        text = (f"  {name} on {s} ({words}): {e['mean']:+.2f} ± {e['se']:.2f}, t({e['df']}) = {e['t']:.2f}, "
                f"p = {e['p']:.2g}")
        if s == "collected":
            text += f"; var. comp. SE {e['vc_se']:.2f}, df {e['vc_df']:.0f}, p = {e['vc_p']:.2g}"
        lines.append(text)
    return lines


def diagnostics(lineages):
    """Markdown lines: the offline labels of each lineage's D_1 (descriptive), mean over lineages of each statistic."""
    got = [f[f"lineage_{l}/{DIAGNOSTIC}"] for l, f in lineages.items() if f"lineage_{l}/{DIAGNOSTIC}" in f]
    if not got:
        return []
    lines = ["| label | velocity noise | masked | mean | median | p90 | inside its segment: mean | to its end: mean |",
             "|---|---|---|---|---|---|---|---|"]
    for i, first in enumerate(got[0]["labels"]):
        def avg(part, key):
            return np.mean([g["labels"][i][part][key] for g in got])
        noise = f"on ({first['velocity_noise']:g})" if first["velocity_noise"] else "off"
        lines.append(f"| {first['label']} | {noise} | {avg('all', 'masked'):.1%} | {avg('all', 'mean'):.2f} | "
                     f"{avg('all', 'median'):.2f} | {avg('all', 'p90'):.2f} | {avg('inside', 'mean'):.2f} | "
                     f"{avg('to_end', 'mean'):.2f} |")
    return [f"the labels at σ = 0 against the recorded chunks on each lineage's D_1 (benchmarks/relabel_diagnostic.py; "
            f"median steps of D0; means over {len(got)} lineage(s) of each lineage's statistic; 'servo' in a file made "
            f"before 6192871 is the old servo):"] + lines


def figure(lineages, path):
    """What the tests compare, per set: each relabelled row − HG-DAgger per lineage (points), the old servo and PD
    side by side at sigma 0, 8 and pooled, their mean with a paired 95 % t interval (none for one lineage)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(lineages)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5), layout="constrained")
    for ax, s, title in ((axes[0], "collected", "collected: the 100 scenarios of the round (the paper's protocol)"),
                         (axes[1], "new", "new: each lineage's own 300 scenarios")):
        ax.axhline(0.0, color="gray", lw=0.8)
        for label, rows, shift, colour, marker in (("servo as converted up to 6192871", SERVO_ROWS, -0.12, "C0", "o"),
                                                   ("PD (the paper's Sec. IV-E)", PD_ROWS, 0.12, "C3", "s")):
            for x, row in enumerate(rows):
                d = combination_table(lineages, difference(row, "hg_dagger"), s).mean(axis=1)
                ax.scatter(x + shift + np.linspace(-0.04, 0.04, n), d, s=14, color=colour, alpha=0.45, lw=0,
                           label="one lineage" if (x, shift) == (0, -0.12) else None)
                half = t_quantile(0.975, n - 1) * np.std(d, ddof=1) / math.sqrt(n) if n > 1 else 0.0
                ax.errorbar([x + shift], [np.mean(d)], yerr=[half], marker=marker, markersize=7, capsize=4,
                            color=colour, lw=1.6, ls="none",
                            label=f"{label}: mean, 95 % t interval" if x == 0 else None)
        ax.set_xticks([0, 1, 2], ["σ = 0", "fixed σ 8", r"pooled $\bar\Sigma^\alpha$"])
        ax.set_title(f"{title}\n{n} lineage{'s' if n > 1 else ''}, each row minus its lineage's HG-DAgger"
                     + ("" if n > 1 else ": no interval"), fontsize=9)
        ax.set_ylabel("row − HG-DAgger (success, points)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=3, fontsize=8, frameon=False)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--design", action="store_true", help="print the power analysis, the lineage count and the cost")
    p.add_argument("--evaluate", metavar="RUN", help="evaluate lineage --lineage of run folder RUN on its own new "
                   "scenarios and measure its D_1's labels")
    p.add_argument("--export-policies", metavar="RUN", help="copy lineage --lineage's round-1 policies of RUN to "
                   "benchmarks/results/relabel_cost/policies/")
    p.add_argument("--lineage", type=int, help="the lineage for --evaluate / --export-policies")
    p.add_argument("--results", default=RESULTS, help="the committed lineage files (default %(default)s)")
    p.add_argument("--figure", metavar="PNG", help="also draw each relabelled row - HG-DAgger per lineage to PNG")
    a = p.parse_args(argv)
    if a.design:
        pilot = load_lineages(PILOT)
        n, lines = lineage_count(pilot)
        print("\n".join(lines))
        print()
        print("\n".join(cost_per_lineage(pilot)))
        print(f"\nnew scenarios: lineage L draws {NEW_PER_LINEAGE} seeds from {NEW_SEED_START} + {NEW_SEED_STRIDE} L, "
              f"e.g. lineage {FIRST_LINEAGE}: {new_seeds(FIRST_LINEAGE)[0]}..{new_seeds(FIRST_LINEAGE)[-1]}, lineage "
              f"{FIRST_LINEAGE + n - 1}: {new_seeds(FIRST_LINEAGE + n - 1)[0]}..{new_seeds(FIRST_LINEAGE + n - 1)[-1]}")
        return
    if a.evaluate or a.export_policies:
        if a.lineage is None or a.lineage < FIRST_LINEAGE:
            p.error(f"--lineage {a.lineage}: give one of the study's lineages (>= {FIRST_LINEAGE})")
        if a.evaluate:
            evaluate_lineage(a.evaluate, a.lineage)
        else:
            export_policies(a.export_policies, a.lineage, os.path.join(RESULTS, "policies"))
        return
    lineages = complete(load_lineages(a.results))
    print(f"{a.results}: {len(lineages)} complete lineage(s) {sorted(lineages)} of the stated {N_LINEAGES} "
          f"({FIRST_LINEAGE}..{FIRST_LINEAGE + N_LINEAGES - 1})")
    if not lineages:
        return
    print(f"\n{CONDITIONAL}")
    print("\nsuccess in points, mean ± SE over lineages (collected: the variance-components SE in brackets; new, "
          "nested: the lineage SE is the SE):")
    print("\n".join(table(lineages)))
    if len(lineages) >= 2:
        print()
        print("\n".join(tests_table(lineages)))
        if len(lineages) < N_LINEAGES:
            print(f"(an interim look at {len(lineages)} lineages: the stated tests are read at {N_LINEAGES})")
        print("\nsecondary (two-sided, uncorrected; Holm's adjusted p beside each, over the t tests):")
        print("\n".join("  " + line for line in secondary(lineages)))
        print("\nafter the fact, not stated tests:")
        print("\n".join(after_the_fact(lineages)))
    if lines := diagnostics(lineages):
        print()
        print("\n".join(lines))
    if a.figure:
        print(f"\nfigure: {figure(lineages, a.figure)}")


if __name__ == "__main__":
    main()
