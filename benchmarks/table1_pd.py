"""Table I again, every noised row labelled by the paper's PD return: a stated study, its tests named before it runs.

The committed Table I (benchmarks/results/table1: lineages 0-4 of the table1 profile) was made when every noised row
was relabelled by the servo as converted up to 6192871 (its speed cap half the authors' in radians). Every profile
now labels with the paper's PD (relabel.pd_return_chunk, Sec. IV-E), so that table is no longer this code's Table I.
This study makes it again. The design (benchmarks/results/table1_pd/README.md, fixed before any of its lineages):

  lineages     5, 6, ..., 5 + N_LINEAGES - 1 of the table1 profile, from its committed start (benchmarks/results/
               table1/start: lineages 0-4's pi_0 and BC row), K = 1..5. Numbered afresh: every collection, gate,
               planner, calibration and training seed is keyed by the lineage, and HG-DAgger's chain (its collections,
               D_k, its rows) never reads the return label, so lineages 0-4 again would redraw the old table's
               HG-DAgger bit for bit on the same kind of machine; lineages 5.. draw new collections
  rows         Table I's ten (bc, hg_dagger, fixed_2/4/8/12/16, pooled, per_step, closed_loop) and zero_noise (the
               relabelled pipeline at sigma = 0: the label's control), every one at every round
  scenario sets  collected: the 100 evaluation scenarios 10000..10099 that each round collects on (Table I's, the
               run's eval/<row>.json); new: lineage L's own 300 scenarios relabel_cost.new_seeds(L) = 100000 + 1000 L
               .. + 299, drawn by no stage, every row of every round (and pi_0 and BC) there x 3 repeats, one
               sampling seed for every policy of a lineage (stage_seed(cfg, "eval_new", L))
  stated tests Holm over P1-P3 at 0.05; "over rounds": each lineage's mean over K = 1..5, then a test over lineages:
    P1  collected: pooled - HG-DAgger over rounds                           > 0, one-sided t (df = lineages - 1)
    P2  new:       pooled - HG-DAgger over rounds                           > 0, one-sided t
    P3  collected: pooled - the best fixed sigma in hindsight over rounds   within +-2 points, TOST (its larger p)
  secondary    two-sided, uncorrected: every row - HG-DAgger at every round on both sets; per_step and closed_loop
               as P1 and P2; zero_noise - HG-DAgger, HG-DAgger - BC per round; HG-DAgger's K = 5 - K = 1
  described    why HG-DAgger levels off: per round and lineage, the scenarios collected on, what D_k kept, and
               HG-DAgger's success on the scenarios it collected on against the others (--collection)

Commands (a lineage at a time; each step resumes; the README has them whole):

    python benchmarks/table1_pd.py --design             # the power analysis, the lineage count, the cost
    python dagger.py --profile table1 --methods METHODS --lineages 21 --lineage L --out runs/table1_pd --workers 2
    python benchmarks/table1_pd.py --evaluate runs/table1_pd --lineage L            # its own 300 new scenarios
    python dagger.py --profile table1 --methods METHODS --lineages 21 --out runs/table1_pd --report \\
        --export-lineages benchmarks/results/table1_pd
    python benchmarks/table1_pd.py --figure benchmarks/figures/table1_pd.png        # the table, P1-P3, the figure
    python benchmarks/table1_pd.py --collection benchmarks/results/table1_pd        # why HG-DAgger levels off

with METHODS = hg_dagger,fixed_2,fixed_4,fixed_8,fixed_12,fixed_16,pooled,per_step,closed_loop,zero_noise (BC runs
always; the same string every time: the run folder's config is named after it).
"""
from __future__ import annotations

import argparse
import functools
import itertools
import math
import os
import shutil
import sys
from types import SimpleNamespace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))
import noise_transfer  # noqa: E402  (its power function, one-sided t and Holm)
import relabel_cost  # noqa: E402  (each lineage's new scenarios, its pilot's SDs, a lineage file's stage times)
from evaluate_policy import t_quantile  # noqa: E402
from paired_bc import load_lineages, t_test  # noqa: E402

import dagger  # noqa: E402
import diffusion  # noqa: E402
from experiment import profiles, report, run_folder  # noqa: E402

t_quantile = functools.lru_cache(maxsize=None)(t_quantile)

FIRST_LINEAGE = 5  # the table1 profile's lineages 0-4 are the committed table's (and table1_k1_controls')
ROUNDS = 5
FIXED_ROWS = tuple(f"fixed_{s}" for s in dagger.FIXED_SIGMAS)  # Table I's sweep, the paper's median steps
ROWS = ("hg_dagger",) + FIXED_ROWS + ("pooled", "per_step", "closed_loop", "zero_noise")  # the run's, BC aside
METHODS = ",".join(ROWS)  # --methods: one string for every lineage (cli.folder_name makes the config's name of it)
LINEAGES_ARG = 21  # --lineages: above the last lineage the design may run (5 + N_MAX - 1; a folder-free field)
NEW = relabel_cost.NEW  # lineage_<l>/new_scenarios/{pi0,bc}.json and .../round_<k>/<row>.json
RESULTS = os.path.join(HERE, "results", "table1_pd")
PILOT = os.path.join(HERE, "results", "table1")  # the old servo's Table I: the SDs on the collected set, the costs
START_PI0 = "3cab671964e705f6da97cf82d302d274770b9536cf478363620bbcd4412732f5"  # table1/start's pi_0 (its weights)
ALPHA, POWER, N_MIN, N_MAX, N_TESTS = 0.05, 0.80, 5, 16, 3
MARGIN = dagger.TOST_MARGIN  # Table I's equivalence margin, +-2 success points
EFFECT, PAPER_EFFECT = 1.5, 2.8  # points: the smallest effect stated for P1 and P2; the paper's (t(4) = 5.75)
POLICY_PICKS = (("hg_dagger", "pooled", "fixed_4"), (1, 5))  # lineage 5's policies to commit: rows x rounds
WALL_PER_CORE = 6480 / 9648  # table1 lineage 0: 1 h 48 min of wall with --workers 2 for 2.68 core-h of stages
SETS = ("collected", "new")
SET_WORDS = {"collected": "collected (10000..10099, Table I's)", "new": "new (each lineage its own 300)"}


# ---- a lineage file's evaluations ---------------------------------------------------------------------------------
def evaluation_key(lineage, row, k, scenario_set):
    """The lineage file's key of a row's evaluation at round k on a set (pi_0 and BC: one policy for every K)."""
    if scenario_set == "collected":
        return f"eval/{row}.json" if row in ("pi0", "bc") else f"lineage_{lineage}/round_{k}/eval/{row}.json"
    if scenario_set == "new":
        return f"lineage_{lineage}/{NEW}/" + (f"{row}.json" if row in ("pi0", "bc") else f"round_{k}/{row}.json")
    raise ValueError(f"scenario set {scenario_set!r}: 'collected' or 'new'")


def per_scenario(files, lineage, row, k, scenario_set):
    """(scenarios,) a row's success in points per scenario (the mean of its repeats) at round k, or None where the
    lineage has no such evaluation; a new-set file on other seeds than the lineage's own is refused."""
    key = evaluation_key(lineage, row, k, scenario_set)
    if key not in files:
        return None
    if scenario_set == "new" and files[key]["seeds"] != list(relabel_cost.new_seeds(lineage)):
        raise ValueError(f"{key}: seeds {files[key]['seeds'][0]}..{files[key]['seeds'][-1]}, not lineage "
                         f"{lineage}'s own new scenarios")
    return 100.0 * np.asarray(files[key]["success"], float).mean(axis=1)


def missing(files, lineage):
    """What a lineage file lacks for the study: [its missing evaluations, or why it is not the study's]."""
    record = files.get(f"lineage_{lineage}/lineage.json")
    if record is None:
        return ["its lineage.json"]
    why = []
    if run_folder.label_of(record) != run_folder.RETURN_LABEL:
        why.append(f"the PD label (made with {run_folder.label_of(record)!r})")
    if record["pi0_sha256"] != START_PI0:
        why.append(f"the committed start's pi_0 (its {record['pi0_sha256'][:12]}...)")
    keys = [evaluation_key(lineage, row, k, s) for s in SETS for row in ("pi0", "bc") + ROWS
            for k in range(1, ROUNDS + 1)]
    absent = sorted({key for key in keys if key not in files})
    return why + ([f"{len(absent)} evaluations (e.g. {absent[0]})"] if absent else [])


def complete(lineages, log=print):
    """The lineages holding every row at every round on both sets, made with PD from the committed start."""
    out = {}
    for lineage, files in sorted(lineages.items()):
        lacks = missing(files, lineage)
        if lacks:
            log(f"lineage {lineage}: left out, it lacks " + "; ".join(lacks))
        else:
            out[lineage] = files
    return out


def round_table(lineages, row, scenario_set):
    """(lineages, K) a row's success in points per lineage and round (pi_0's and BC's the same at every K)."""
    return np.array([[per_scenario(f, l, row, k, scenario_set).mean() for k in range(1, ROUNDS + 1)]
                     for l, f in lineages.items()])


def over_rounds(lineages, row, base, scenario_set):
    """(lineages,) row - base in points, each lineage's mean over K = 1..5; float noise rounded off (a lineage's
    value is a multiple of 1/45 point on the collected set: two equal values must have no spread, not 1e-16)."""
    return np.round((round_table(lineages, row, scenario_set) - round_table(lineages, base, scenario_set))
                    .mean(axis=1), 9)


# ---- the stated tests ---------------------------------------------------------------------------------------------
def hindsight(lineages):
    """(the best fixed sigma in hindsight, report.paired_statistics' result): Table I's rule, as a run's report
    applies it over rounds: of fixed_2 .. fixed_16, the row whose success averaged over K = 1..5 on the collected
    set has the highest mean over lineages (a tie: the first of 2, 4, 8, 12, 16). Chosen on the data it is then
    compared on: the largest of five noisy means, biased up, so pooled - best is biased down (toward the fixed
    row) -- the design gives the bias's size."""
    values = {row: dict(zip(lineages, round_table(lineages, row, "collected").mean(axis=1))) for row in FIXED_ROWS}
    stats = report.paired_statistics(SimpleNamespace(methods=("bc",) + ROWS), lambda m: values.get(m, {}))
    return stats["best_fixed"], stats


def stated_tests(lineages):
    """[{'name', 'words', 'set', 'side', 'values', 'mean', 'se', 't', 'df', 'p', 'holm_level', 'rejected'}] of
    P1-P3 over complete lineages; Holm's step-down over the three p at ALPHA (noise_transfer.holm)."""
    best, _ = hindsight(lineages)
    out = []
    for name, s in (("P1", "collected"), ("P2", "new")):
        values = over_rounds(lineages, "pooled", "hg_dagger", s)
        mean, se, t, df, p = noise_transfer.one_sided(values, ">")
        out.append(dict(name=name, words="pooled − HG-DAgger, over rounds", set=s, side="> 0", values=values,
                        mean=mean, se=se, t=t, df=df, p=p))
    values = over_rounds(lineages, "pooled", best, "collected")
    p, t_lower, t_upper = dagger.tost(round_table(lineages, "pooled", "collected").mean(axis=1),
                                      round_table(lineages, best, "collected").mean(axis=1), MARGIN)
    out.append(dict(name="P3", words=f"pooled − the best fixed σ in hindsight ({best}), over rounds", set="collected",
                    side=f"within ±{MARGIN:g}", values=values, mean=float(values.mean()),
                    se=float(values.std(ddof=1) / math.sqrt(len(values))), t=min(t_lower, -t_upper),
                    df=len(values) - 1, p=p))
    pvalues = [r["p"] for r in out]
    order = sorted(range(len(out)), key=lambda i: pvalues[i])
    for rank, i in enumerate(order):
        out[i]["holm_level"] = ALPHA / (len(out) - rank)
    for r, verdict in zip(out, noise_transfer.holm(pvalues, ALPHA)):
        r["rejected"] = verdict
    return out


def tests_table(lineages):
    """Markdown lines: P1-P3 with t (P3: the smaller of its two one-sided t), the p of the stated side and Holm's
    verdict; before the stated count of lineages an interim look, no verdict."""
    interim = len(lineages) < N_LINEAGES
    lines = [f"| test | set | quantity (points) | side | mean | SE | t | df | p | Holm level | verdict at {ALPHA} |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in stated_tests(lineages):
        verdict = (f"none before {N_LINEAGES} lineages" if interim else "rejected" if r["rejected"] else
                   "not rejected")
        lines.append(f"| {r['name']} | {r['set']} | {r['words']} | {r['side']} | {r['mean']:+.2f} | {r['se']:.2f} | "
                     f"{r['t']:.2f} | {r['df']} | {r['p']:.2g} | {r['holm_level']:.4f} | {verdict} |")
    lines.append("(P1, P2: one-sided t over lineages; P3: TOST at ±2, its p the larger of its two one-sided p, its t "
                 "the smaller of (mean + 2) / SE and (2 − mean) / SE; H0 of P3: the difference lies outside ±2)")
    return lines


def paired(a, b):
    """'mean ± SE (p)' of a - b over lineages, two-sided (paired_bc.t_test); float noise rounded off."""
    mean, se, t, df, p = t_test(np.round(np.asarray(a) - np.asarray(b), 9))
    return f"{mean:+.1f} ± {se:.1f} " + (f"(p {p:.2g})" if se > 0 else "(no spread)")


def secondary(lineages):
    """Markdown lines of the secondary results (two-sided, uncorrected): each row - HG-DAgger at each round and
    over rounds on each set; zero_noise - HG-DAgger and HG-DAgger - BC by round; HG-DAgger's K = 5 - K = 1."""
    lines = []
    for s in SETS:
        hg = round_table(lineages, "hg_dagger", s)
        lines += [f"row − HG-DAgger on {SET_WORDS[s]}, mean ± SE over lineages (two-sided p):", "",
                  "| row | " + " | ".join(f"K={k}" for k in range(1, ROUNDS + 1)) + " | over rounds |",
                  "|---|" + "---|" * (ROUNDS + 1)]
        for row in ROWS[1:]:
            cells = round_table(lineages, row, s)
            lines.append(f"| {row} | " + " | ".join(paired(cells[:, k], hg[:, k]) for k in range(ROUNDS)) +
                         f" | {paired(cells.mean(axis=1), hg.mean(axis=1))} |")
        bc = round_table(lineages, "bc", s)
        lines += ["", f"HG-DAgger − BC on {s}: " + "; ".join(f"K={k + 1} {paired(hg[:, k], bc[:, k])}"
                                                          for k in range(ROUNDS)),
                  f"HG-DAgger K = 5 − K = 1 on {s}: {paired(hg[:, -1], hg[:, 0])}", ""]
    lines += ["named among them: per_step and closed_loop − HG-DAgger over rounds (as P1, P2), zero_noise − HG-DAgger "
              "by round (the label at σ = 0). HG-DAgger − BC: on the collected set BC is one evaluation shared by "
              "every lineage, taken as exact (benchmarks/paired_bc.py pairs over the scenarios instead); on the new "
              "set each lineage evaluates BC on its own scenarios. About 120 tests: at 5 % some six fall under "
              "p = 0.05 by chance alone."]
    return lines


# ---- the table and the figure -------------------------------------------------------------------------------------
def cell(values):
    """'mean ± SE' over lineages (the value alone for one lineage)."""
    v = np.asarray(values, float)
    return f"{v.mean():.1f}" if v.size < 2 else f"{v.mean():.1f} ± {v.std(ddof=1) / math.sqrt(v.size):.1f}"


def table(lineages):
    """Markdown lines: every row's success in points at K = 1..5 and over rounds, mean ± SE over lineages, a block
    per set (pi_0 and BC: one policy, one value for every K)."""
    lines = []
    for s in SETS:
        lines += [f"{SET_WORDS[s]}:", "", "| row | " + " | ".join(f"K={k}" for k in range(1, ROUNDS + 1)) +
                  " | over rounds |", "|---|" + "---|" * (ROUNDS + 1)]
        for row in ("pi0", "bc") + ROWS:
            v = round_table(lineages, row, s)
            ks = [cell(v[:, 0])] + ["″"] * (ROUNDS - 1) if row in ("pi0", "bc") else [cell(v[:, k]) for k in
                                                                                       range(ROUNDS)]
            lines.append(f"| {row} | " + " | ".join(ks) + f" | {cell(v.mean(axis=1))} |")
        lines.append("")
    return lines


def figure(lineages, path):
    """Each row - HG-DAgger per round (and over rounds, right), the mean over lineages with its paired 95 % t
    interval (none for one lineage); one panel a set, each with its own y-axis. BC (some 10 points under on the
    collected set) is left to the table: it would set the scale."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(lineages)
    shown = ROWS[1:]
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5), layout="constrained")
    for ax, s in zip(axes, SETS):
        hg = round_table(lineages, "hg_dagger", s)
        ax.axhline(0.0, color="gray", lw=0.8)
        for i, row in enumerate(shown):
            d = np.column_stack([round_table(lineages, row, s) - hg, (round_table(lineages, row, s) - hg)
                                 .mean(axis=1)])                                # (lineages, K + 1)
            half = (t_quantile(0.975, n - 1) * d.std(axis=0, ddof=1) / math.sqrt(n) if n > 1 else np.zeros(d.shape[1]))
            x = np.r_[np.arange(1, ROUNDS + 1), ROUNDS + 1.5] + (i - (len(shown) - 1) / 2) * 0.07
            style = (dict(marker="*", markersize=10, lw=1.8) if row == "pooled" else
                     dict(marker="o", markersize=4, lw=1.0))
            ax.errorbar(x, d.mean(axis=0), yerr=half, capsize=2, ls="none", color=f"C{i}", label=row, **style)
        ax.set_xticks(list(range(1, ROUNDS + 1)) + [ROUNDS + 1.5],
                      [f"K={k}" for k in range(1, ROUNDS + 1)] + ["over rounds"])
        ax.set_title(f"{SET_WORDS[s]}\n{n} lineage{'s' if n > 1 else ''}, each row minus its lineage's HG-DAgger"
                     + (", mean and paired 95 % t interval" if n > 1 else ": no interval"), fontsize=9)
        ax.set_ylabel("row − HG-DAgger (success, points)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(shown), fontsize=8, frameon=False)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# ---- the power analysis (stated before the runs) ------------------------------------------------------------------
def tost_power(delta, row_sd, n, alpha, selection=True, margin=MARGIN, draws=50_000, seed=0):
    """Power of P3 by Monte Carlo (a fixed seed): each of n lineages draws the five fixed rows and pooled, each a
    row's true mean + row_sd x N(0, 1) over rounds (what the lineages share cancels in every difference); the fixed
    rows' true means are equal, pooled's is delta above them. selection: the best fixed row chosen in hindsight from
    the draws as `hindsight` chooses it; else one named fixed row. Returns P(TOST at +-margin rejects at alpha)."""
    rng, crit, rejected = np.random.default_rng(seed), t_quantile(1.0 - alpha, n - 1), 0
    for start in range(0, draws, 10_000):
        x = rng.standard_normal((min(10_000, draws - start), n, len(FIXED_ROWS) + 1)) * row_sd   # (draws, n, 6)
        x[:, :, -1] += delta
        best = x[:, :, :-1].mean(axis=1).argmax(axis=1) if selection else np.zeros(len(x), int)
        d = x[:, :, -1] - x[np.arange(len(x)), :, best]                                      # (draws, n)
        mean, se = d.mean(axis=1), d.std(axis=1, ddof=1) / math.sqrt(n)
        rejected += int((((mean + margin) / se > crit) & ((mean - margin) / se < -crit)).sum())
    return rejected / draws


def selection_bias(row_sd, n, draws=200_000, seed=0):
    """E[mean of pooled - the best fixed in hindsight] when every row's true mean is the same, in points."""
    x = np.random.default_rng(seed).standard_normal((draws, len(FIXED_ROWS))) * row_sd / math.sqrt(n)
    return float(-x.max(axis=1).mean())


def pilot_inputs(pilot, rc_pilot, nt_pilot):
    """The SDs the design rests on, in points (a dict; the lines of `design` say where each comes from)."""
    d1 = round_table(pilot, "pooled", "collected") - round_table(pilot, "hg_dagger", "collected")   # (5, K)
    du = unseen_table(pilot, "pooled") - unseen_table(pilot, "hg_dagger")
    best, _ = hindsight(pilot)
    avg = {row: round_table(pilot, row, "collected").mean(axis=1) for row in FIXED_ROWS + ("pooled",)}
    pairs = list(itertools.combinations(avg, 2))
    rc_new = relabel_cost.combination_table(rc_pilot, relabel_cost.difference("pooled_pd", "hg_dagger"), "new")
    rc_collected = relabel_cost.combination_table(rc_pilot, relabel_cost.difference("pooled_pd", "hg_dagger"),
                                                  "collected")
    nt_new = relabel_cost.pilot_table(nt_pilot, "pooled", "hg_dagger")
    sd = lambda v: float(np.std(v, ddof=1))  # noqa: E731
    out = {"p1_mean": float(d1.mean()), "p1_sd": sd(d1.mean(axis=1)), "p1_sd_k": [sd(d1[:, k]) for k in range(ROUNDS)],
           "unseen_sd": sd(du.mean(axis=1)), "unseen_sd_k1": sd(du[:, 0]),
           "rc_new_sd": sd(rc_new.mean(axis=1)), "rc_new_mean": float(rc_new.mean()),
           "rc_collected_sd": sd(rc_collected.mean(axis=1)), "rc_n": len(rc_pilot), "nt_n": len(nt_pilot),
           "nt_design_sd": relabel_cost.design_sd(sd(nt_new.mean(axis=1)), relabel_cost.variance_components(nt_new),
                                                  nt_new.shape[1]),
           "best": best, "p3_mean": float((avg["pooled"] - avg[best]).mean()), "p3_sd": sd(avg["pooled"] - avg[best]),
           "pair_sd": math.sqrt(np.mean([np.var(avg[a] - avg[b], ddof=1) / 2 for a, b in pairs]))}
    # how much averaging over K = 1..5 shrinks a K = 1 SD: the largest of the collected set's, the unseen set's and
    # independent rounds' 1 / sqrt(5) (the new set's SD is known at K = 1 only)
    out["shrink"] = max(out["p1_sd"] / out["p1_sd_k"][0], out["unseen_sd"] / out["unseen_sd_k1"], 1 / math.sqrt(ROUNDS))
    out["p2_sd"] = out["rc_new_sd"] * out["shrink"]
    out["row_sd"] = max(out["pair_sd"], out["p3_sd"] / math.sqrt(2))
    return out


def unseen_table(pilot, row):
    """(lineages, K) a pilot row's success in points on the run's unseen scenarios 20000..20099."""
    return np.array([[100.0 * np.mean(f[f"lineage_{l}/round_{k}/eval/{row}_unseen.json"]["success"])
                      for k in range(1, ROUNDS + 1)] for l, f in pilot.items()])


def design(pilot, rc_pilot, nt_pilot):
    """(N_LINEAGES, lines): the smallest n in N_MIN..N_MAX with POWER at Holm's first step (ALPHA / N_TESTS, a bound
    on every step) for P1 and P2 at +EFFECT and for P3 at a true difference of 0 with the selection included."""
    q = pilot_inputs(pilot, rc_pilot, nt_pilot)
    level = ALPHA / N_TESTS
    rel = lambda p: os.path.relpath(p, os.path.dirname(HERE))  # noqa: E731
    lines = [
        f"pilot, collected set: {rel(PILOT)} lineages {sorted(pilot)} (table1, the old servo), success on 10000..10099",
        f"  P1 pooled − HG-DAgger over rounds: mean {q['p1_mean']:+.2f}, SD {q['p1_sd']:.3f} over lineages "
        f"(per round: {', '.join(f'{v:.2f}' for v in q['p1_sd_k'])})",
        f"  averaging over rounds shrinks K = 1's SD {q['p1_sd_k'][0]:.3f} to {q['p1_sd']:.3f} here, x "
        f"{q['p1_sd'] / q['p1_sd_k'][0]:.3f} (on the unseen 20000..20099 {q['unseen_sd_k1']:.3f} to "
        f"{q['unseen_sd']:.3f}, x {q['unseen_sd'] / q['unseen_sd_k1']:.3f}; independent rounds x "
        f"{1 / math.sqrt(ROUNDS):.3f}): P2 takes the largest, x {q['shrink']:.3f}",
        f"  P3 pooled − the best fixed in hindsight ({q['best']}) over rounds: mean {q['p3_mean']:+.2f}, SD "
        f"{q['p3_sd']:.3f}; the rows' SD about their lineage's mean (the 15 pairs of fixed_2..16 and pooled, "
        f"var(a − b) / 2) {q['pair_sd']:.3f}: the larger of it and {q['p3_sd']:.3f} / sqrt(2) = "
        f"{q['p3_sd'] / math.sqrt(2):.3f} is each row's SD in P3's Monte Carlo: {q['row_sd']:.3f}",
        f"pilot, new set: {rel(relabel_cost.RESULTS)} lineages {min(rc_pilot)}..{max(rc_pilot)} ({q['rc_n']}, "
        f"table1_strong, K = 1, each lineage its own 300), pooled_pd − HG-DAgger: mean {q['rc_new_mean']:+.2f}, SD "
        f"{q['rc_new_sd']:.3f} (on its collected set SD {q['rc_collected_sd']:.3f}, table1's K = 1 "
        f"{q['p1_sd_k'][0]:.3f}: the recipes spread alike)",
        f"  P2's SD: {q['rc_new_sd']:.3f} x {q['shrink']:.3f} = {q['p2_sd']:.3f}; the noise-transfer study's "
        f"({rel(noise_transfer.RESULTS)}, {q['nt_n']} lineages, one set, the old servo) design SD with fresh "
        f"scenarios {q['nt_design_sd']:.3f} at K = 1, for comparison",
        f"one-sided t over lineages at Holm's first step {ALPHA} / {N_TESTS} = {level:.4f} and at {ALPHA}; P3 a TOST "
        f"at ±{MARGIN:g}, true difference 0, the best fixed chosen in hindsight from the draws (sel.) or named "
        f"before (named); power by Monte Carlo (P1, P2: 200,000 draws; P3: 50,000)",
        "   n  P1 +2.8 α/3  α     P1 +1.5 α/3  α     P2 +2.8 α/3  P2 +1.5 α/3  α     P3 sel. α/3  α     "
        "P3 named α/3"]
    chosen = None
    for n in range(N_MIN, N_MAX + 1):
        p1 = [noise_transfer.power(e, q["p1_sd"], n, a) for e in (PAPER_EFFECT, EFFECT) for a in (level, ALPHA)]
        p2 = [noise_transfer.power(PAPER_EFFECT, q["p2_sd"], n, level)] + [
            noise_transfer.power(EFFECT, q["p2_sd"], n, a) for a in (level, ALPHA)]
        p3 = [tost_power(0.0, q["row_sd"], n, a) for a in (level, ALPHA)] + [
            tost_power(0.0, q["row_sd"], n, level, selection=False)]
        lines.append(f"  {n:2d}  {p1[0]:6.3f}  {p1[1]:6.3f}    {p1[2]:6.3f}  {p1[3]:6.3f}    {p2[0]:6.3f}       "
                     f"{p2[1]:6.3f}  {p2[2]:6.3f}    {p3[0]:6.3f}  {p3[1]:6.3f}    {p3[2]:6.3f}")
        if chosen is None and min(p1[2], p2[1], p3[0]) >= POWER:
            chosen = n
    n = chosen or N_MAX
    # the SDs are estimates (P1's and P3's from 5 lineages): the power at n were they at the upper end of a
    # one-sided 80 % interval, sqrt((R - 1) / chi2_0.2(R - 1)) times the estimate
    up = math.sqrt((len(pilot) - 1) / relabel_cost.chi2_quantile(0.2, len(pilot) - 1))
    lines += [f"  sensitivity at n = {n}, every SD x {up:.2f} (upper 80 % bound of an SD from {len(pilot)} lineages): "
              f"P1 +1.5 {noise_transfer.power(EFFECT, q['p1_sd'] * up, n, level):.3f}, P2 +1.5 "
              f"{noise_transfer.power(EFFECT, q['p2_sd'] * up, n, level):.3f}, P3 "
              f"{tost_power(0.0, q['row_sd'] * up, n, level):.3f}; P2 with no shrink over rounds (SD "
              f"{q['rc_new_sd']:.3f}) {noise_transfer.power(EFFECT, q['rc_new_sd'], n, level):.3f}, at the noise-"
              f"transfer SD {q['nt_design_sd']:.3f} {noise_transfer.power(EFFECT, q['nt_design_sd'], n, level):.3f}",
              f"  P3's selection: with equal true means, pooled − the best of five in hindsight averages "
              f"{selection_bias(q['row_sd'], n):+.2f} points at n = {n} ({selection_bias(q['row_sd'], N_MIN):+.2f} "
              f"at {N_MIN}): toward the fixed row, against equivalence when pooled sits at the fixed rows' level"]
    rule = (f"the smallest n >= {N_MIN} with power >= {POWER} at {level:.4f} for P1 and P2 at +{EFFECT} and for P3 at "
            "0, selection included" if chosen else
            f"no n <= {N_MAX} reaches power {POWER} for all three; the most the design runs")
    lines.append(f"lineages: {n} ({rule}): lineages {FIRST_LINEAGE}..{FIRST_LINEAGE + n - 1}")
    return n, lines


N_LINEAGES = 11  # `--design` prints how it was chosen; a test checks that it still says so


# ---- the cost of a lineage, per machine, from recorded stage times ------------------------------------------------
def study_lineage_seconds(train, evaluation, fixed):
    """(core-seconds of a study lineage's run, of its new-set evaluation): collection and calibration `fixed`, the
    ten rows x K trainings, two evaluations each (collected, unseen), then 10 x K + 2 (pi_0, BC) policies on 300
    new scenarios x 3, each 3 x a 100-scenario evaluation."""
    cells = (len(ROWS)) * ROUNDS
    return fixed + cells * (train + 2 * evaluation), (cells + 2) * 3 * evaluation


def cost_lines(pilot, rc_pilot):
    """Lines: a study lineage's core-hours and wall on each machine a pilot ran on, at its recorded medians."""
    c = {l: relabel_cost.lineage_cost(f) for l, f in sorted(pilot.items())}
    per = lambda ls, key: float(np.median([s for l in ls for s in c[l][key]]))  # noqa: E731
    fixed = {l: c[l]["collect"] + c[l]["calibrate"] for l in c}
    rc = [relabel_cost.lineage_cost(f) for f in rc_pilot.values()]
    scale = profiles.PROFILES["table1"].finetune_steps / profiles.PROFILES["table1_strong"].finetune_steps
    machines = [("Zen 5 (table1 lineage 0, 2026-11-25, --workers 2)", [0]),
                ("AVX2 EPYC (table1 lineages 1-4, 2026-11-26/27, two lineages side by side)", [1, 2, 3, 4])]
    lines = ["pilot stage times (timings/ of each lineage file; one torch thread a stage: core-seconds):",
             "  lineage  trainings  s each (median)  evaluations  s each (median)  collect + calibrate s  total core-h"]
    for l in c:
        lines.append(f"  {l:7d}  {len(c[l]['train']):9d}  {np.median(c[l]['train']):15.0f}  {len(c[l]['evaluate']):11d}"
                     f"  {np.median(c[l]['evaluate']):15.1f}  {fixed[l]:21.0f}  {c[l]['total'] / 3600:12.2f}")
    lines.append("a study lineage: 50 trainings (table1's 45 and zero_noise's 5), 100 evaluations of 300 episodes, "
                 f"52 of 900 on the new set; wall with --workers 2 on 2 cores ~ {WALL_PER_CORE:.2f} x the run's core "
                 "time (lineage 0's 1 h 48 min for 2.68 core-h) + the new set's (one process):")
    rows = [(name, per(ls, "train"), per(ls, "evaluate"), float(np.median([fixed[l] for l in ls])))
            for name, ls in machines]
    rows.append((f"Intel Xeon 6/167 (relabel_cost lineages {min(rc_pilot)}-{max(rc_pilot)}, projected: their "
                 f"30k-step rows x {scale:.2f}, collect + calibrate as Zen 5's)",
                 float(np.median([s for x in rc for s in x["train"]])) * scale,
                 float(np.median([s for x in rc for s in x["evaluate"]])), fixed[0]))
    for name, train, evaluation, fix in rows:
        run, new = study_lineage_seconds(train, evaluation, fix)
        lines.append(f"  {name}: training {train:.0f} s, evaluation {evaluation:.1f} s -> run {run / 3600:.2f} + new "
                     f"set {new / 3600:.2f} = {(run + new) / 3600:.2f} core-h a lineage, wall ~ "
                     f"{(WALL_PER_CORE * run + new) / 3600:.1f} h; {N_LINEAGES} lineages {N_LINEAGES * (run + new) / 3600:.0f} "
                     f"core-h")
    return lines


# ---- the study's own evaluations: each lineage's new scenarios, and its policies to commit -------------------------
def study_policies(lineage):
    """{name: its policy file, relative to the run folder}: pi_0, BC, and 'round_<k>/<row>' of every row and round."""
    return {"pi0": run_folder.PI0_FILE, "bc": "checkpoints/bc_continued.pt",
            **{f"round_{k}/{row}": f"lineage_{lineage}/round_{k}/checkpoints/{row}.pt"
               for k in range(1, ROUNDS + 1) for row in ROWS}}


def study_config(root, lineage):
    """The run folder's config (a namespace) if it is the study's -- table1's recipe, every row, the PD label -- and
    `lineage` one of its lineages; else SystemExit naming what is wrong, before anything is written."""
    command = (f"python dagger.py --profile table1 --methods {METHODS} --lineages {LINEAGES_ARG} --lineage "
               f"{lineage} --out {root}")
    path = os.path.join(root, "config.json")
    if not os.path.isfile(path):
        raise SystemExit(f"{root}: no config.json; give the study's run folder ({command})")
    cfg, table1 = SimpleNamespace(**run_folder.read_json(path)), profiles.PROFILES["table1"]
    differ = [key for key in ("env", "recipe", "n_demos", "rounds", "K", "network", "bc_steps", "finetune_steps",
                              "batch_size", "eval_scenarios", "eval_repeats", "seed")
              if getattr(cfg, key, None) != getattr(table1, key)]
    if differ or set(cfg.methods) != {"bc", *ROWS}:
        raise SystemExit(f"{root}: not the study's run folder ({', '.join(differ) or 'its methods'} differ from the "
                         f"table1 profile with --methods {METHODS}); run it as: {command}")
    if not FIRST_LINEAGE <= lineage < cfg.lineages:
        raise SystemExit(f"--lineage {lineage}: the study's lineages are {FIRST_LINEAGE}..{cfg.lineages - 1} of {root}")
    record = os.path.join(root, f"lineage_{lineage}", "lineage.json")
    if os.path.isfile(record) and run_folder.label_of(run_folder.read_json(record)) != run_folder.RETURN_LABEL:
        raise SystemExit(f"{record}: made with {run_folder.label_of(run_folder.read_json(record))!r}, not the PD label")
    return cfg


def evaluate_lineage(root, lineage, log=print):
    """Evaluate every study policy of `lineage` in run folder `root` on the lineage's own new scenarios into
    root/lineage_<l>/new_scenarios/ (3 repeats, one sampling seed for every policy: stage_seed(cfg, "eval_new", L),
    relabel_cost's). A file already there is kept: the step resumes. A missing policy stops it before anything is
    written."""
    cfg = study_config(root, lineage)
    policies = study_policies(lineage)
    absent = [rel for rel in policies.values() if not os.path.isfile(os.path.join(root, rel))]
    if absent:
        raise SystemExit(f"{root}: {len(absent)} policies missing (e.g. {absent[0]}); finish lineage {lineage} first "
                         f"(python dagger.py --profile table1 --methods {METHODS} --lineages {LINEAGES_ARG} "
                         f"--lineage {lineage} --out {root})")
    relabel_cost.write_new_evaluations(root, lineage, cfg, policies, log)


def export_policies(root, lineage, folder, picks=POLICY_PICKS):
    """Copy the policies `picks` (rows x rounds) of `lineage` (weights and config, no training state) to
    folder/lineage_<l>/round_<k>/<row>.pt; every policy is read first, and one that is missing or holds a training
    state stops the export before anything is written."""
    rows, rounds = picks
    pairs = [(k, row) for k in rounds for row in rows]
    sources = [os.path.join(root, f"lineage_{lineage}", f"round_{k}", "checkpoints", f"{row}.pt") for k, row in pairs]
    for src in sources:
        if "train_state" in run_folder.checkpoints.read_checkpoint(src):
            raise SystemExit(f"{src} holds a training state; the study's rows are saved for sampling only")
    for (k, row), src in zip(pairs, sources):
        dst = os.path.join(folder, f"lineage_{lineage}", f"round_{k}")
        os.makedirs(dst, exist_ok=True)
        shutil.copyfile(src, os.path.join(dst, f"{row}.pt"))
        print(f"{src} -> {dst}/{row}.pt")


# ---- why HG-DAgger levels off: what each round collected, from the lineage files (and a run folder's D_k) ---------
def anchors_in_round(files, lineage, k):
    """(kept episodes, kept segments, calibration anchors) of D_k from round k's calibration.json, or None. The
    calibration reads D_1..D_k in order and anchors Sigma_hat at every other labelled chunk start of every expert
    segment (calibrate.open_loop_sigma): every kept episode holds an anchor, so D_1..D_k hold max(episode_index) + 1
    episodes; two anchors of one segment lie 2 steps apart and two segments' more than H (a segment's last chunk
    start is H before its end), so a gap over 2 starts a segment. D_k's: those past D_1..D_(k-1)'s."""
    def read(j):
        c = files.get(f"lineage_{lineage}/round_{j}/calibration.json")
        return None if c is None else (np.asarray(c["episode_index"], int), np.asarray(c["timestep"], int))
    now = read(k)
    if now is None:
        return None
    before = 0 if k == 1 else (None if read(k - 1) is None else int(read(k - 1)[0].max()) + 1)
    if before is None:
        return None
    episode, step = now
    mine = episode >= before
    new_segment = np.r_[True, (np.diff(episode[mine]) != 0) | (np.diff(step[mine]) > 2)]
    return int(episode.max()) + 1 - before, int(new_segment.sum()), int(mine.sum())


def episodes_in_round(root, lineage, k, horizon):
    """{'takeovers', 'frames', 'chunks', 'solved'} of a run folder's D_k (round_<k>/D.npz): the expert's takeovers
    as recorded (the label rule then drops the segments under H), expert frames and labelled chunk starts kept, and
    the share of D_k's episodes that reached the goal with the expert's help; None without the file."""
    path = os.path.join(root, f"lineage_{lineage}", f"round_{k}", "D.npz")
    if not os.path.isfile(path):
        return None
    episodes = run_folder.load_episodes(path)
    return {"takeovers": sum(int(e["interventions"]) for e in episodes),
            "frames": sum(int(np.sum(e["expert"])) for e in episodes),
            "chunks": sum(int(diffusion.label_mask(e["expert"], horizon).sum()) for e in episodes),
            "solved": 100.0 * float(np.mean([bool(e["success"]) for e in episodes]))}


def collection_rows(lineages, root=None):
    """[(k, lineage, {column: value})] of the main chain's rounds (the closed-loop row's own chain aside): the
    collector (pi_0 at K = 1, else HG-DAgger of K - 1) and its success on the 100 scenarios, the scenarios it
    collected on (those its own evaluation did not solve 3 of 3: dagger.collect_interventions) and how many of them
    an earlier round collected on too, its success there, D_k from the calibration (anchors_in_round), HG-DAgger_K's
    success on the scenarios collected on and on the others, and BC's on both (the start's BC row: a policy the
    split was not drawn from); from run folder `root`'s D.npz also episodes_in_round's columns."""
    out = []
    for lineage, files in sorted(lineages.items()):
        horizon = files[f"lineage_{lineage}/lineage.json"]["config"]["horizon"]
        bc = 100.0 * np.asarray(files["eval/bc.json"]["success"], float).mean(axis=1)
        earlier = np.zeros(len(bc), bool)
        for k in range(1, ROUNDS + 1):
            collector = "eval/pi0.json" if k == 1 else f"lineage_{lineage}/round_{k - 1}/eval/hg_dagger.json"
            hg_key = f"lineage_{lineage}/round_{k}/eval/hg_dagger.json"
            if collector not in files or hg_key not in files:
                break
            before = np.asarray(files[collector]["success"], bool)             # (100, repeats)
            hg = 100.0 * np.asarray(files[hg_key]["success"], float).mean(axis=1)
            on = ~before.all(axis=1)
            others = (lambda v: float(v[~on].mean())) if (~on).any() else (lambda v: math.nan)
            row = {"collector": "π0" if k == 1 else f"HG K={k - 1}", "collector_all": 100.0 * before.mean(),
                   "collected_on": int(on.sum()), "before": int((on & earlier).sum()) if k > 1 else None,
                   "collector_there": 100.0 * before[on].mean(), "hg_there": float(hg[on].mean()),
                   "hg_others": others(hg), "bc_there": float(bc[on].mean()), "bc_others": others(bc)}
            earlier |= on
            kept = anchors_in_round(files, lineage, k)
            row.update(zip(("episodes", "segments", "anchors"), kept or (None,) * 3))
            if root is not None:
                row.update(episodes_in_round(root, lineage, k, horizon) or {})
            out.append((k, lineage, row))
    return out


def collection_table(source):
    """Markdown lines of collection_rows for a folder of lineage files or a run folder (which adds D.npz's
    columns), per round and lineage, then the mean over lineages of each round."""
    if os.path.isfile(os.path.join(source, "config.json")):
        lineage_ids = sorted(int(n.split("_")[1]) for n in os.listdir(source)
                             if n.startswith("lineage_") and os.path.isfile(os.path.join(source, n, "lineage.json")))
        run = SimpleNamespace(root=source, path=lambda *parts: os.path.join(source, *parts))
        lineages, root = {l: run_folder.lineage_results(run, l) for l in lineage_ids}, source
    else:
        lineages, root = load_lineages(source), None
    rows = collection_rows(lineages, root)
    exact = root is not None
    head = (["K", "lineage", "collector", "collector on the 100", "collected on (before)", "collector there",
             "kept episodes", "kept segments", "chunk starts"] +
            (["takeovers", "expert frames", "kept reaching the goal"] if exact else []) +
            ["HG-DAgger_K there (− BC)", "HG-DAgger_K on the others (− BC)"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def fmt(k, lineage, r, count="{:.0f}"):
        number = lambda key, form=count: "—" if r.get(key) is None else form.format(r[key])  # noqa: E731
        chunks = (number("chunks") if "chunks" in r else "—" if r["anchors"] is None else
                  f"{count.format(2 * r['anchors'] - r['segments'])}–{count.format(2 * r['anchors'])}")
        on = number("collected_on") + ("" if r.get("before") is None else f" ({number('before')})")
        cells = [str(k), str(lineage), r["collector"], f"{r['collector_all']:.1f}", on,
                 f"{r['collector_there']:.1f}", number("episodes"), number("segments"), chunks]
        if exact:
            cells += [number("takeovers"), number("frames"), number("solved", "{:.1f}")]
        cells += [f"{r['hg_there']:.1f} ({r['hg_there'] - r['bc_there']:+.1f})",
                  f"{r['hg_others']:.1f} ({r['hg_others'] - r['bc_others']:+.1f})"]
        return "| " + " | ".join(cells) + " |"

    lines += [fmt(k, lineage, r) for k, lineage, r in rows]
    lines += ["", "mean over lineages:", "", lines[0], lines[1]]
    for k in sorted({k for k, _, _ in rows}):
        at = [r for j, _, r in rows if j == k]
        mean = {key: float(np.mean([r[key] for r in at])) if all(r.get(key) is not None for r in at) else None
                for key in at[0] if key != "collector"}
        lines.append(fmt(k, f"mean of {len(at)}", {**mean, "collector": at[0]["collector"]}, "{:.1f}"))
    return lines


COLLECTION_NOTE = (
    "columns: the collector drives round K (π0 at K = 1, then the lineage's HG-DAgger of K − 1) on the scenarios its "
    "own evaluation did not solve 3 of 3 ('collected on'; in brackets, how many of them an earlier round collected "
    "on too); 'collector there': its success on them, 'on the 100': on all; kept episodes and segments: D_K's, the "
    "interventions of at least H steps the label rule kept (exact, from round K's calibration.json); chunk starts: "
    "the labelled chunks those segments give (from the calibration's anchors, every other one: a range, exact with a "
    "run folder's D.npz); takeovers, expert frames, kept episodes reaching the goal: from D.npz only (a run folder); "
    "HG-DAgger_K there / on the others: the round's HG-DAgger on the scenarios collected on and on the rest, the "
    "start's BC row subtracted in brackets. Not the collector: the split is made of its own 3 repeats, so against it "
    "the scenarios collected on gain and the others lose by regression to the mean alone; BC's evaluation is no part "
    "of the split. HG-DAgger's chain never reads the return label: the columns are the same under either label.")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--design", action="store_true", help="print the power analysis, the lineage count and the cost")
    p.add_argument("--evaluate", metavar="RUN", help="evaluate lineage --lineage of run folder RUN on its own new "
                   "scenarios (every row of every round, pi_0 and BC)")
    p.add_argument("--export-policies", metavar="RUN", help="copy lineage --lineage's HG-DAgger, pooled and fixed_4 at "
                   "K = 1 and 5 of RUN to benchmarks/results/table1_pd/policies/")
    p.add_argument("--lineage", type=int, help="the lineage for --evaluate / --export-policies")
    p.add_argument("--results", default=RESULTS, help="the committed lineage files (default %(default)s)")
    p.add_argument("--figure", metavar="PNG", help="also draw each row - HG-DAgger per round to PNG")
    p.add_argument("--collection", metavar="FOLDER", help="print what each round collected: a folder of lineage files "
                   "(e.g. benchmarks/results/table1) or a run folder (adds its D.npz's columns)")
    a = p.parse_args(argv)
    if a.design:
        pilots = (load_lineages(PILOT), relabel_cost.complete(load_lineages(relabel_cost.RESULTS)),
                  load_lineages(noise_transfer.RESULTS))
        print("\n".join(design(*pilots)[1]))
        print()
        print("\n".join(cost_lines(pilots[0], pilots[1])))
        print(f"\nnew scenarios: lineage L's own relabel_cost.new_seeds(L), e.g. lineage {FIRST_LINEAGE}: "
              f"{relabel_cost.new_seeds(FIRST_LINEAGE)[0]}..{relabel_cost.new_seeds(FIRST_LINEAGE)[-1]}")
        return
    if a.evaluate or a.export_policies:
        if a.lineage is None or a.lineage < FIRST_LINEAGE:
            p.error(f"--lineage {a.lineage}: give one of the study's lineages (>= {FIRST_LINEAGE})")
        if a.evaluate:
            evaluate_lineage(a.evaluate, a.lineage)
        else:
            export_policies(a.export_policies, a.lineage, os.path.join(RESULTS, "policies"))
        return
    if a.collection:
        if not os.path.isdir(a.collection):
            p.error(f"--collection {a.collection}: no such folder")
        print("\n".join(collection_table(a.collection)))
        print(f"\n{COLLECTION_NOTE}")
        return
    if not os.path.isdir(a.results) or not any(n.startswith("lineage_") and n.endswith(".json.gz")
                                               for n in os.listdir(a.results)):
        print(f"{a.results}: no lineage file yet (lineage_<l>.json.gz, l = {FIRST_LINEAGE}.."
              f"{FIRST_LINEAGE + N_LINEAGES - 1}): the study has not run. Its design: "
              f"benchmarks/results/table1_pd/README.md; python benchmarks/table1_pd.py --design prints the power "
              f"analysis")
        return
    lineages = complete(load_lineages(a.results))
    print(f"{a.results}: {len(lineages)} complete lineage(s) {sorted(lineages)} of the stated {N_LINEAGES} "
          f"({FIRST_LINEAGE}..{FIRST_LINEAGE + N_LINEAGES - 1})")
    if not lineages:
        return
    print("\nevery SE here is conditional on one π0: each lineage continues the start's π0 and BC row "
          "(benchmarks/results/table1/start), so no SE carries the draw of π0 or of D0")
    print("\nsuccess in points, mean ± SE over lineages:\n")
    print("\n".join(table(lineages)))
    if len(lineages) >= 2:
        print("\n".join(tests_table(lineages)))
        if len(lineages) < N_LINEAGES:
            print(f"(an interim look at {len(lineages)} lineages: the stated tests are read at {N_LINEAGES})")
        print("\nsecondary (two-sided, uncorrected):\n")
        print("\n".join(secondary(lineages)))
    if a.figure:
        print(f"\nfigure: {figure(lineages, a.figure)}")


if __name__ == "__main__":
    main()
