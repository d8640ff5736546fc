"""The command's mode (run_experiment) and the report: Table I from the results on disk -- results.json,
results.csv, table.md, report.md, the table figures -- with the paper's figures.

write_report reads the finished evaluations (collect_results, scenario_paired) and assembles Table I (summarize:
mean ± SE over lineages, dagger.py's paired t-tests and TOST); here too the
run's own summaries (the differences paired over scenarios, the calibration in the paper's unit), the formatting
and the drawing.
"""
from __future__ import annotations

import csv
import math
import os
import re
import time

import numpy as np

import calibrate
import dagger
from experiment import controls, environments, figures, lever, profiles
from experiment.environments import paper_env, paper_median_step
from experiment.run_folder import (LABEL_WORDS, RETURN_LABEL, Run, copy_from, export_lineages, folder_labels,
                                   join_lineage, read_json, write_json)
from experiment.workers import worker_map

# Table I's row names (the paper's words); fixed_<s> is the isotropic sigma = s in the paper's median steps
METHOD_LABELS = {
    "bc": "BC (no aggregation)",
    "hg_dagger": "HG-DAgger",
    "pooled": "Pooled Sigma-bar^alpha (Ours)",
    "per_step": "Per-step Sigma^alpha (Ours)",
    "closed_loop": "Closed-loop pooled Sigma-bar^alpha (Ours)",
    "zero_noise": "Co-training control (sigma=0; not in the paper)",
    "authors_hg_dagger": "HG-DAgger as the authors' kit trained it (not in the paper)",
    "cotrain_fixed_8": "Half recorded, half fixed sigma=8 (the paper's co-training; not in its table)",
    "cotrain_pooled": "Half recorded, half pooled Sigma-bar^alpha (the paper's co-training; not in its table)",
    "zero_noise_servo": "Co-training control (sigma=0), the authors' servo label (not in the paper's table)",
    "fixed_8_servo": "Fixed iso. noise (sigma=8), the authors' servo label (not in the paper's table)",
    "pooled_servo": "Pooled Sigma-bar^alpha, the authors' servo label (not in the paper's table)",
}


# The paper's tables (mean ± SE over lineages, lineage count), to draw and print beside a run's own: Table I
# (planar reacher, 100 scenarios x 3) and Table II (UR5 engine lever). BC is one value for every K.
PAPER_TABLES = {
    "planar": {"bc": [(68.0, 0.2, 1)],
               "hg_dagger": [(79.9, 0.5, 5), (81.9, 0.7, 5), (83.3, 1.5, 5), (85.3, 0.7, 5), (87.3, 1.0, 5)],
               "fixed_2": [(81.9, 0.8, 5), (84.8, 0.7, 5), (85.1, 0.3, 5), (88.6, 0.4, 5), (89.1, 0.4, 5)],
               "fixed_4": [(82.7, 0.9, 5), (86.1, 0.7, 5), (86.3, 0.5, 5), (87.7, 0.6, 5), (89.2, 0.8, 5)],
               "fixed_8": [(83.9, 0.8, 5), (85.1, 0.8, 5), (85.1, 0.8, 5), (86.1, 0.8, 5), (87.1, 0.8, 5)],
               "fixed_12": [(83.3, 0.7, 5), (84.8, 0.6, 5), (85.1, 0.8, 5), (84.5, 1.0, 5), (85.0, 0.8, 5)],
               "fixed_16": [(83.2, 1.3, 5), (85.1, 0.6, 5), (83.8, 0.9, 5), (83.4, 0.9, 5), (84.8, 0.8, 5)],
               "pooled": [(82.0, 0.6, 5), (86.2, 0.8, 5), (86.5, 0.4, 5), (87.5, 0.9, 5), (89.3, 0.5, 5)],
               "per_step": [(81.6, 0.9, 5), (85.3, 0.9, 5), (85.5, 0.3, 5), (86.5, 0.5, 5), (88.5, 0.8, 5)],
               "closed_loop": [(81.6, 1.0, 1), (83.3, 0.2, 1), (85.9, 0.5, 1), (88.8, 0.2, 1), (89.3, 0.7, 1)]},
    "engine3d": {"bc": [(58.0, 1.2, 1)],
                 "hg_dagger": [(57.4, 5.6, 3), (58.1, 4.0, 3)],
                 "pooled": [(68.8, 4.2, 3), (63.4, 4.8, 3)]},
}


# ---- The command's mode: the loop on a run folder, with what this config's variant hands it --------------------
def run_experiment(cfg, root, lineage=None, prepare=False, report_only=False, workers=1, join=(),
                   export_to=None, copy_src=None):
    """The command's mode on run folder `root` (resuming whatever is already there): every lineage, or only
    `lineage`, or (prepare) only the shared stages, then the report; report_only: only the report. join: lineage
    results files unpacked into the folder first; export_to: a folder to write each lineage's results file to;
    copy_src: a finished run folder of the same config with fewer methods whose stages are copied in first."""
    cfg = profiles.check_config(cfg)  # a clear error for a bad value before the folder is made
    run = Run(root, cfg)
    if copy_src:
        copy_from(run, copy_src)
    for path in join:
        join_lineage(run, path)
    t0 = time.time()
    if not report_only:
        lineages = [] if prepare else [lineage] if lineage is not None else list(range(cfg.lineages))
        run.hold_lineages(lineages)  # a second run of one of them into this folder stops here, naming this PID
        try:
            run.log(f"Policy-Calibrated DAgger, env {cfg.env}, folder {run.root}, {workers} worker process(es); the "
                    f"noised rows' return label: {LABEL_WORDS[RETURN_LABEL]}")
            lever.check_lineages(run, lineages)  # a recipe that trains on lineage 0's data needs it there first
            memo = lever.data_of_lineage_0(cfg, run.memo)  # the seeds recipe's lineages read lineage 0's data
            dagger.policy_calibrated_dagger(cfg, lineages, memo=memo, map=worker_map(workers, run.log), log=run.log,
                                            **loop_arguments(cfg))
        finally:
            run.release_lineages()
    with run.stage_lock("report"):  # runs of other lineages into this folder write the report one at a time
        text = write_report(run)
    run.log(f"done in {time.time() - t0:.0f} s; report.md, table, results and figures in {run.root}\n\n{text}")
    for path in export_lineages(run, export_to) if export_to else []:
        run.log(f"wrote {path}")
    return run.root


def loop_arguments(cfg):
    """What the harness hands dagger.policy_calibrated_dagger for this config: the env factory of every env a run may
    name (experiment/environments.py), and a variant's own functions: the lever recipe's (experiment/lever.py), or
    the research rows' sampler (experiment/controls.py) where the config names one of them."""
    arguments = dict(make_env=environments.make_env)
    if cfg.recipe != "paper":
        arguments.update(lever.loop_arguments(cfg))
    elif any(method in controls.ROWS for method in cfg.methods):
        arguments["sampler"] = controls.Rows()
    return arguments


def write_report(run):
    """Table I from the evaluations on disk, on both scenario sets: results.json, results.csv, table.md, the
    table figures, the paper's figures (when their inputs changed) and report.md. Returns the table."""
    run.check_lineages()  # a lineage folder copied in from elsewhere joins only if made like this one
    tables = {}
    for scenarios in ("eval", "unseen"):
        success = collect_results(run, scenarios)
        table, stats = summarize(run.cfg, success)
        stats["scenario_paired"] = scenario_paired(run, scenarios)
        tables[scenarios] = (success, table, stats)
    text = write_tables(run, tables)
    if run.inputs_changed("figures/drawn_from.json", figures.FIGURE_INPUTS):
        figures.make_figures(run)
        run.record_inputs("figures/drawn_from.json", figures.FIGURE_INPUTS)
    else:
        run.log("figures 1-5: their inputs have not changed since they were drawn (figures/drawn_from.json)")
    write_markdown_report(run, text, tables["eval"][2], tables["unseen"][2])
    return text


def summarize(cfg, results):
    """Per method and round: (mean, SE over lineages, count); the paired tests over the lineages that finished
    every round (each averaged over rounds), per round, HG-DAgger vs BC, and the best fixed sigma per round.
    results: {method: {lineage: [success per round]}}, BC's {'all': [success]}; the tests: dagger.py's."""
    table = {}
    for method, per_lineage in results.items():
        if method == "bc":
            table[method] = [mean_se(per_lineage["all"])]
        else:
            rounds = [list(at_round(per_lineage, k).values()) for k in range(cfg.rounds)]
            table[method] = [mean_se(vals) if vals else None for vals in rounds]
    stats = paired_statistics(cfg, lambda m: {l: float(np.mean(r)) for l, r in results.get(m, {}).items()
                                              if len(r) == cfg.rounds})
    stats["per_round"] = {str(k + 1): paired_statistics(cfg, lambda m, k=k: at_round(results.get(m, {}), k))
                          for k in range(cfg.rounds)}
    stats["hg_dagger_vs_bc"], stats["best_fixed_per_round"] = {}, {}
    bc_all = results.get("bc", {}).get("all")
    for k in range(cfg.rounds):
        # HG-DAgger against BC: one pi_0 for all lineages, so the pairs are (HG_l,k, BC)
        hg_k = list(at_round(results.get("hg_dagger", {}), k).values())
        if bc_all and len(hg_k) >= 2:
            bc = [bc_all[0]] * len(hg_k)
            t, df, p = dagger.paired_ttest(hg_k, bc)
            stats["hg_dagger_vs_bc"][str(k + 1)] = {"diff": float(np.mean(hg_k) - bc_all[0]), "t": t, "df": df,
                                                    "p": p, "n_above": int(sum(v > bc_all[0] for v in hg_k)),
                                                    "n": len(hg_k), "degenerate": degenerate(hg_k, bc)}
        # the best fixed sigma of the round in hindsight (beside the calibrated sigma, Sec. V)
        cells = {m: table[m][k][0] for m in cfg.methods
                 if is_fixed(m) and m in table and table[m][k] is not None}
        if cells:
            stats["best_fixed_per_round"][str(k + 1)] = max(cells, key=cells.get)
    return table, stats


def at_round(rows, k):
    """{lineage: success of round k + 1} of the lineages that finished it; rows: {lineage: [success per round]}."""
    return {l: r[k] for l, r in rows.items() if len(r) > k}


def paired_statistics(cfg, values):
    """Each method against HG-DAgger (paired t over lineages) and the calibrated methods against the best fixed
    sigma (TOST at dagger.TOST_MARGIN); values(method) -> {lineage: success} (a round's, or averaged over rounds)."""
    hg = values("hg_dagger")
    fixed = [m for m in cfg.methods if is_fixed(m) and values(m)]
    best_fixed = max(fixed, key=lambda m: np.mean(list(values(m).values()))) if fixed else None
    stats = {"paired_vs_hg_dagger": {}, "tost_vs_best_fixed": {}, "best_fixed": best_fixed}
    for method in cfg.methods:
        if method in ("bc", "hg_dagger"):
            continue
        a, b = pairs(values(method), hg)
        if len(a) >= 2:
            t, df, p = dagger.paired_ttest(a, b)
            stats["paired_vs_hg_dagger"][method] = {"diff": mean_difference(a, b), "t": t, "df": df, "p": p,
                                                    "degenerate": degenerate(a, b)}
        a, b = pairs(values(method), values(best_fixed)) if best_fixed else ([], [])
        if method in ("pooled", "per_step", "closed_loop") and len(a) >= 2:
            p, _, _ = dagger.tost(a, b, dagger.TOST_MARGIN)
            stats["tost_vs_best_fixed"][method] = {"vs": best_fixed, "diff": mean_difference(a, b), "p": p,
                                                   "margin": dagger.TOST_MARGIN, "degenerate": degenerate(a, b)}
    return stats


def pairs(mine, ref):
    """The paired values of two {lineage: success}: two lists over the lineages both hold, in lineage order."""
    common = sorted(set(mine) & set(ref))
    return [mine[l] for l in common], [ref[l] for l in common]


def mean_difference(a, b):
    return float(np.mean([x - y for x, y in zip(a, b)]))


def mean_se(values):
    """(mean, standard error, count) of the values (SE 0 for one value)."""
    v = np.asarray(values, float)
    se = v.std(ddof=1) / math.sqrt(v.size) if v.size > 1 else 0.0
    return float(v.mean()), float(se), int(v.size)


def degenerate(a, b):
    """Why a paired test of a vs b has no p-value (the differences have no spread), or None."""
    d = dagger.paired_differences(a, b)
    if d.size >= 2 and np.all(d == d[0]):
        return (f"every lineage differs by exactly {d[0]:+.1f} points: the paired differences have no spread, "
                "so t and p are undefined")
    return None


def table_number(cfg):
    """The paper's table of this run's env: 'I' (planar) or 'II' (the UR5 lever, a variant's env of it too)."""
    return "II" if paper_env(cfg.env) == "engine3d" else "I"


def paper_table(cfg):
    """The paper's cells for this run's env, methods and rounds in table_rows' layout ({} if the paper has none)."""
    paper = PAPER_TABLES.get(paper_env(cfg.env), {})  # a variant's env: the paper's env it derives from
    return {m: ([paper[m][0]] if m == "bc" else [paper[m][k] if k < len(paper[m]) else None
                                                   for k in range(cfg.rounds)])
            for m in cfg.methods if m in paper}


def is_fixed(method):
    """Whether `method` is a row of Table I's fixed sweep, fixed_<sigma> (fixed_8_servo, a variant's row, is not)."""
    return re.fullmatch(r"fixed_\d+", method) is not None


def method_label(method):
    """The table's name of a method: METHOD_LABELS, or 'Fixed iso. noise (sigma=s, ...)' for fixed_<s>."""
    if is_fixed(method):
        return f"Fixed iso. noise (sigma={method.split('_', 1)[1]}, paper's unit)"
    return METHOD_LABELS[method]


def collect_results(run, scenarios="eval"):
    """success[method][lineage][k-1] in percent, from every finished evaluation on disk; scenarios 'eval'
    (the evaluation scenarios) or 'unseen' (the unseen ones, files <method>_unseen.json). A file of another
    shape or other scenarios than the run's config says is refused, naming it (Run.load: RunFolderError)."""
    cfg = run.cfg
    results = {}
    suffix = "" if scenarios == "eval" else "_unseen"
    bc_name = f"eval/bc{suffix}.json"
    if os.path.exists(os.path.join(run.root, bc_name)):
        results["bc"] = {"all": [100.0 * float(np.mean(run.load(bc_name)["success"]))]}
    for method in cfg.methods:
        if method == "bc":
            continue
        for lineage in range(cfg.lineages):
            row = []
            for k in range(1, cfg.rounds + 1):
                name = f"lineage_{lineage}/round_{k}/eval/{method}{suffix}.json"
                if not os.path.exists(os.path.join(run.root, name)):
                    break
                row.append(100.0 * float(np.mean(run.load(name)["success"])))
            if row:
                results.setdefault(method, {})[str(lineage)] = row
    return results


def scenario_paired(run, scenarios="eval"):
    """Differences paired over scenarios, in points: per round and lineage, HG-DAgger - BC and every other
    method - HG-DAgger, each the mean over scenarios of the per-scenario success difference (its repeats
    averaged) with the SE over scenarios. What one lineage can say: its scenarios, not its lineages, are the
    repeats. {k: {lineage: {method: {"vs", "diff", "se", "n"}}}}."""
    cfg, suffix = run.cfg, "" if scenarios == "eval" else "_unseen"

    def per_scenario(name):  # an evaluation's success per scenario (its repeats averaged), checked by Run.load
        exists = os.path.exists(os.path.join(run.root, *name.split("/")))
        return np.asarray(run.load(name)["success"], float).mean(axis=1) if exists else None

    bc = per_scenario(f"eval/bc{suffix}.json")
    out = {}
    for k in range(1, cfg.rounds + 1):
        for lineage in range(cfg.lineages):
            folder = f"lineage_{lineage}/round_{k}/eval"
            hg = per_scenario(f"{folder}/hg_dagger{suffix}.json")
            if hg is None:
                continue
            pairs = {"hg_dagger": (hg, bc, "bc")} if bc is not None else {}
            for m in cfg.methods:
                if m not in ("bc", "hg_dagger"):
                    mine = per_scenario(f"{folder}/{m}{suffix}.json")
                    if mine is not None:
                        pairs[m] = (mine, hg, "hg_dagger")
            for m, (a, b, vs) in pairs.items():
                d = 100.0 * (a - b)
                out.setdefault(str(k), {}).setdefault(str(lineage), {})[m] = {
                    "vs": vs, "diff": float(d.mean()), "se": float(d.std(ddof=1) / math.sqrt(len(d))), "n": len(d)}
    return out


# The paper's calibrated numbers, in its median steps (an env's paper_median_step), set beside ours in that unit: the
# pooled Sigma_bar^alpha's per-joint sigma (paper Sec. VI: "3.9--5.1 median per-step joint displacement in 2D
# planar reacher", "1.3--4.2 median steps in 3D engine lever-reaching") and W (PCD paper/fig_noise_levels/plot.py:
# PLANAR_W = 8.0; LEVER_W 7.94-8.10 over rounds 1-4).
PAPER_CALIBRATION = {"planar": {"sigma": "3.9–5.1", "W": "8.0"}, "engine3d": {"sigma": "1.3–4.2", "W": "7.9–8.1"}}


def calibration_text(cal):
    """A calibrate.Calibration as the log says it, in one unit: the paper's median steps (our own median steps
    for an env the paper gives none for), radians beside; the last line says what each unit is."""
    p = cal.paper_median_step
    unit, name = (p, "paper median steps") if p is not None else (cal.median_step, "median steps")
    ci = ("" if cal.W_ci is None else
          f"95 % bootstrap interval {cal.W_ci[0] / unit:.2f}–{cal.W_ci[1] / unit:.2f}, ")
    fitted = calibrate.ratio_cells(cal.blend_beta, cal.blend_s, cal.blend_x, cal.blend_kept).fitted
    return "\n".join([
        f"W = {in_unit(cal.W, unit, name)} ({ci}||W||, {cal.fit_note}"
        + (f", r = K*/K_theta = {cal.r:.3g})" if cal.r is not None else ")"),
        f"kept blend rollouts: {int(cal.blend_kept.sum())}/{len(cal.blend_kept)} over "
        f"{len(np.unique(cal.blend_beta))} ratios, {int(fitted.sum())} "
        f"with >= {calibrate.CalibrationConfig.min_survivors} kept (fitted)",
        f"pooled Sigma_bar^alpha per-joint sigma = {in_unit(np.sqrt(np.diag(cal.pooled)), unit, name)}",
        (f"units: the paper's median step {p:.4f} rad (L2 over the joints, 30 Hz); ours {cal.median_step:.4f} rad "
         f"(per joint, base demos) = {cal.median_step / p:.2f}x theirs" if p is not None else
         f"units: our median step {cal.median_step:.4f} rad (per joint, base demos); the paper gives none for "
         "this env")])


def in_unit(rad, unit, name):
    """A length in rad (a number, or one per joint) in `unit` (rad) named `name`, radians beside:
    '9.03 paper median steps (0.159 rad)'."""
    values = np.atleast_1d(np.asarray(rad, dtype=np.float64))
    return (", ".join(f"{v / unit:.2f}" for v in values) + f" {name} ("
            + ", ".join(f"{v:.3f}" for v in values) + " rad)")


def calibration_summary(run, chain=None):
    """Per round: the pooled Sigma_bar^alpha's per-joint sigma and W per lineage, in our median steps
    ('sigma_per_joint', 'W', 'W_ci'), in radians ('..._rad') and in the paper's median steps ('..._paper';
    None where the env has no paper unit). chain='closed_loop': that row's own calibrations (rounds >= 2)."""
    cfg, out = run.cfg, {}
    paper = paper_median_step(cfg.env)
    in_paper = lambda rad: None if paper is None or rad is None else (np.asarray(rad) / paper).tolist()  # noqa: E731
    for k in range(1, cfg.rounds + 1):
        for lineage in range(cfg.lineages):
            p = os.path.join(run.root, f"lineage_{lineage}", f"round_{k}", *([chain] if chain else []),
                             "calibration.json")
            if os.path.exists(p):
                c = read_json(p)
                m = c["median_step"]
                ci = c.get("W_ci")
                sigma_rad = np.sqrt(np.diag(np.asarray(c["pooled"], float))).tolist()  # per joint, rad
                out.setdefault(str(k), {})[str(lineage)] = {
                    "sigma_per_joint": [float(v) for v in c["sigma_per_joint"]], "W": c["W"] / m,
                    "W_ci": None if ci is None else [ci[0] / m, ci[1] / m], "fit": c["fit_note"],
                    "kept": int(np.sum(c["blend_kept"])), "rollouts": len(c["blend_kept"]),
                    "median_step": m, "paper_median_step": paper,
                    "sigma_per_joint_rad": sigma_rad, "W_rad": c["W"], "W_ci_rad": ci,
                    "sigma_per_joint_paper": in_paper(sigma_rad), "W_paper": in_paper(c["W"]),
                    "W_ci_paper": in_paper(ci)}
    return out


def stage_times(run):
    """{stage kind: (count, total seconds, mean seconds)} from timings/ (demos, bc, collect, calibrate,
    train_<method>, evaluate)."""
    folder = os.path.join(run.root, "timings")
    kinds = {}
    for name in sorted(os.listdir(folder)) if os.path.isdir(folder) else []:
        t = read_json(os.path.join(folder, name))
        kinds.setdefault(t["stage"].split("/")[0], []).append(t["seconds"])
    return {k: (len(v), float(np.sum(v)), float(np.mean(v))) for k, v in kinds.items()}


def format_cell(cell):
    """'mean ± SE (n)'; a single lineage has no measured spread: 'mean (1)'."""
    if cell is None:
        return "–"
    m, se, n = cell
    return f"{m:.1f} ({n})" if n == 1 else f"{m:.1f} ± {se:.1f} ({n})"


def stat_words(s):
    """t(df) = .., p = .. -- or 'no spread' (NO_SPREAD, said once under the table, says why there is no p)."""
    return "no spread" if s.get("degenerate") else f"t({s['df']}) = {s['t']:.2f}, p = {s['p']:.3g}"


NO_SPREAD = ("\"No spread\": every lineage differs by the same number of points, so the paired differences have no "
             "spread and t and p are undefined.")


def has_no_spread(stats):
    """True where any paired statistic in stats (nested dicts, as summarize returns them) has no spread."""
    return isinstance(stats, dict) and (bool(stats.get("degenerate")) or any(map(has_no_spread, stats.values())))


def table_rows(cfg, table):
    """The markdown rows of Table I's layout: rows = methods, columns = rounds K, mean +- SE (lineages)."""
    cols = [f"K={k}" for k in range(1, cfg.rounds + 1)]
    lines = ["| Method | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for method in cfg.methods:
        if method not in table:
            continue
        if method == "bc":
            lines.append(f"| {method_label('bc')} | {format_cell(table['bc'][0])}, all K |" + " |" * (len(cols) - 1))
            continue
        cells = [format_cell(c) for c in table[method]]
        lines.append(f"| {method_label(method)} | " + " | ".join(cells) + " |")
    return lines


def scenario_words(cfg, scenarios="eval"):
    """What the table's scenarios are: the evaluation scenarios are the ones HG-DAgger collected on (the
    authors' protocol), not held out; the unseen ones never enter any training data."""
    if scenarios == "unseen":
        return f"{cfg.eval_scenarios} unseen scenarios (never trained on)"
    return f"the {cfg.eval_scenarios} evaluation scenarios, on which HG-DAgger collected (the authors' protocol)"


def format_table(cfg, table, stats, unseen=None):
    """Markdown in Table I's layout: rows = methods, columns = rounds K, mean +- SE (lineages), with the
    paired statistics; unseen: (table, stats) of the same policies on the unseen scenarios, a second table."""
    lines = table_rows(cfg, table)
    lines.append("")
    lines.append(f"Success rate in % on {scenario_words(cfg)} x {cfg.eval_repeats} "
                 f"evaluations; mean ± SE over lineages (count in parentheses; a single lineage has no ±: "
                 f"its spread is not measured). BC is one pi_0 shared by every lineage."
                 + (" A lineage here is a training seed: every lineage trains on lineage 0's interventions and "
                    "calibrations (recipe authors_lever_seeds, the authors' lever runs), so the spread is the "
                    "training seeds' alone." if cfg.recipe == "authors_lever_seeds" else ""))
    paper = paper_table(cfg)
    if paper:
        lines += ["", f"The paper's Table {table_number(cfg)} for the same rows and rounds (its "
                      f"own env, network and budget: compare orderings and gaps, not levels):", ""]
        lines += table_rows(cfg, paper)
    lines += paired_lines(cfg, stats)
    if unseen is not None and unseen[0]:
        lines += ["", f"**Unseen scenarios.** The same policies on {scenario_words(cfg, 'unseen')} x "
                      f"{cfg.eval_repeats} evaluations (not in the paper; one sampling seed for every method):", ""]
        lines += table_rows(cfg, unseen[0]) + paired_lines(cfg, unseen[1])
    if has_no_spread(stats) or (unseen is not None and has_no_spread(unseen[1])):
        lines += ["", NO_SPREAD]  # once, not beside every test it concerns
    lines += calibration_lines(cfg, stats)
    if stats.get("stage_times"):
        lines.append("")
        lines.append("Wall time of the stages (s; summed over lineages and rounds; processes ran in parallel):")
        for kind, (n, total, mean) in stats["stage_times"].items():
            lines.append(f"- {kind}: {n} x {mean:.0f} s = {total / 60:.1f} min")
    if not stats["paired_vs_hg_dagger"]:
        lines.append("")
        lines.append("(Paired tests need at least 2 finished lineages.)")
    return "\n".join(lines) + "\n"


def paired_lines(cfg, stats):
    """format_table's paired statistics: each method vs HG-DAgger, TOST vs the best fixed sigma, HG-DAgger vs BC."""
    lines = []
    if stats["paired_vs_hg_dagger"]:
        lines.append("")
        lines.append("Paired t-test vs HG-DAgger (lineages, averaged over rounds):")
        for m, s in stats["paired_vs_hg_dagger"].items():
            lines.append(f"- {method_label(m)}: {s['diff']:+.1f} points, {stat_words(s)}")
    if stats["tost_vs_best_fixed"]:
        lines.append("")
        margin = next(iter(stats["tost_vs_best_fixed"].values()))["margin"]  # dagger.TOST_MARGIN
        lines.append(f"TOST equivalence (±{margin:g} points) vs the best fixed noise in hindsight "
                     f"({stats['best_fixed']}):")
        for m, s in stats["tost_vs_best_fixed"].items():
            lines.append(f"- {method_label(m)}: {s['diff']:+.1f} points, "
                         + ("no spread" if s.get("degenerate") else f"p = {s['p']:.3g}"))
    per_round = {k: r for k, r in (stats.get("per_round") or {}).items() if r["paired_vs_hg_dagger"]}
    if per_round:
        lines.append("")
        margins = {s["margin"] for r in per_round.values() for s in r["tost_vs_best_fixed"].values()}
        lines.append("Per round (paired over the lineages that finished it): each method vs HG-DAgger; the "
                     "calibrated ones vs that round's best fixed noise"
                     + "".join(f", TOST ±{m:g}" for m in sorted(margins)) + ":")
        for k, r in per_round.items():
            parts = [f"{m} {s['diff']:+.1f} (" + ("no spread" if s.get("degenerate") else f"p = {s['p']:.2g}")
                     + ")" for m, s in r["paired_vs_hg_dagger"].items()]
            parts += [f"{m} vs {s['vs']} {s['diff']:+.1f} (TOST " + ("no spread" if s.get("degenerate") else
                                                                   f"p = {s['p']:.2g}") + ")"
                      for m, s in r["tost_vs_best_fixed"].items()]
            lines.append(f"- K={k}: " + "; ".join(parts))
    if stats.get("hg_dagger_vs_bc"):
        lines.append("")
        lines.append("HG-DAgger vs BC at each round (paired over lineages; one pi_0):")
        for k, s in stats["hg_dagger_vs_bc"].items():
            lines.append(f"- K={k}: {s['diff']:+.1f} points, above BC in {s['n_above']} of {s['n']} lineages, "
                         f"{stat_words(s)}")
    lines += scenario_paired_lines(cfg, stats.get("scenario_paired") or {})
    return lines


def scenario_paired_lines(cfg, paired):
    """format_table's differences paired over scenarios (scenario_paired), one line per round: HG-DAgger - BC
    and each arm - HG-DAgger per lineage (mean ± SE over the scenarios); for a single lineage, what it can show."""
    if not paired:
        return []
    lines = ["", f"Paired over the {cfg.eval_scenarios} scenarios (per-scenario success difference, mean ± SE over "
                 f"scenarios; per lineage):"]
    ses = []
    for k, per_lineage in paired.items():
        parts = []
        for m in ["hg_dagger"] + [m for m in cfg.methods if m not in ("bc", "hg_dagger")]:
            cells = [(l, d[m]) for l, d in per_lineage.items() if m in d]
            if not cells:
                continue
            name = "HG-DAgger − BC" if m == "hg_dagger" else f"{m} − HG-DAgger"
            parts.append(name + ": " + ", ".join(f"{s['diff']:+.1f} ± {s['se']:.1f}" for _, s in cells))
            ses += [s["se"] for _, s in cells]
        lines.append(f"- K={k}: " + "; ".join(parts))
    if cfg.lineages == 1 and ses:
        lines.append(f"One lineage shows differences paired over its scenarios only: one beyond about twice its SE "
                     f"(here ±{np.median(ses):.0f} points) is measured, a smaller one is not; the order of the "
                     f"noise arms, a few points apart in the paper, needs lineages (the mid profile).")
    return lines


def calibration_lines(cfg, stats):
    """format_table's calibration: per round the pooled Sigma_bar^alpha's per-joint sigma and W (mean over
    lineages) in one unit, the paper's median steps (our own for an env the paper gives none for), radians beside,
    with the paper's own numbers (PAPER_CALIBRATION: they compare in its unit only), and the best fixed sigma in
    hindsight."""
    if not stats.get("calibration"):
        return []
    paper = paper_median_step(cfg.env)
    quoted = PAPER_CALIBRATION.get(paper_env(cfg.env)) if paper is not None else None
    name = "paper median steps" if paper is not None else "median steps"
    lines = ["", f"Calibrated pooled Sigma_bar^alpha, per-joint sigma and W in {name} "
                 + (f"({paper:.4f} rad, L2 over the joints at 30 Hz), " if paper is not None else
                    "(the paper gives no median step for this env: ours, per joint), ")
                 + "mean over lineages, radians beside, and the best fixed sigma of the round in hindsight:"]
    for k, per in stats["calibration"].items():
        sig_rad = np.mean([v["sigma_per_joint_rad"] for v in per.values()], axis=0)  # each lineage's own unit
        W_rad = np.mean([v["W_rad"] for v in per.values()])
        unit = paper if paper is not None else np.mean([v["median_step"] for v in per.values()])
        best = stats.get("best_fixed_per_round", {}).get(k)
        lines.append(f"- K={k}: sigma = {in_unit(sig_rad, unit, name)}"
                     + (f" (the paper: {quoted['sigma']})" if quoted else "")
                     + f"; W = {in_unit(W_rad, unit, name)}" + (f" (the paper: {quoted['W']})" if quoted else "")
                     + f"; {len(per)} lineage{'s' if len(per) > 1 else ''}; best fixed: "
                     + (best.replace("fixed_", "sigma = ") if best else "–"))
        lines.append("  - per lineage" + (" (the paper's median steps)" if paper is not None else " (rad)") + ": "
                     + "; ".join(lineage_calibration(l, v, paper is not None) for l, v in per.items()))
    if stats.get("calibration_closed_loop"):
        lines.append("- the closed-loop row's own chain (measured on the previous round's closed_loop policy over "
                     "the chain's interventions; round 1 is the one above), per lineage"
                     + (" (the paper's median steps)" if paper is not None else " (rad)") + ":")
        for k, per in stats["calibration_closed_loop"].items():
            lines.append(f"  - K={k}: " + "; ".join(lineage_calibration(l, v, paper is not None)
                                                    for l, v in per.items()))
    return lines


def lineage_calibration(lineage, v, in_paper_unit):
    """One lineage's W with its bootstrap interval and per-joint sigma (the paper's unit, else rad); a
    calibration that fell back to the open-loop W says so in capitals."""
    key = "_paper" if in_paper_unit else "_rad"
    ci = v.get("W_ci" + key)
    text = (f"{lineage}: W {v['W' + key]:.2f}" + (f" [{ci[0]:.2f}–{ci[1]:.2f}]" if ci else "")
            + ", sigma " + "/".join(f"{x:.2f}" for x in v["sigma_per_joint" + key]))
    return text + (" FALLBACK (no fit: W from the open-loop error)" if v["fit"].startswith("FALLBACK") else "")


def write_tables(run, tables):
    """results.json, results.csv, table.md and the table figures. tables: {'eval': (success, table, stats),
    'unseen': (...)} -- success[method][lineage][k-1] in percent (collect_results), the table and stats of
    summarize. The evaluation scenarios' stats gain the calibration and the stage times. Returns
    table.md's text."""
    cfg = run.cfg
    results, table, stats = tables["eval"]
    results_unseen, table_unseen, stats_unseen = tables["unseen"]
    stats["calibration"] = calibration_summary(run)
    if "closed_loop" in cfg.methods:
        stats["calibration_closed_loop"] = calibration_summary(run, chain="closed_loop")
    stats["stage_times"] = stage_times(run)
    write_json(os.path.join(run.root, "results.json"), {"success": results, "stats": stats,
                                                        "success_unseen": results_unseen, "stats_unseen": stats_unseen})
    with open(os.path.join(run.root, "results.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "lineage", "round", "success_pct", "unseen_success_pct"])
        for method, rows in results.items():
            for lineage, row in rows.items():
                unseen = results_unseen.get(method, {}).get(lineage, [])
                for k, v in enumerate(row, start=1):
                    w.writerow([method, lineage, "all" if method == "bc" else k, f"{v:.2f}",
                                f"{unseen[k - 1]:.2f}" if len(unseen) >= k else ""])
    text = format_table(cfg, table, stats, (table_unseen, stats_unseen))
    with open(os.path.join(run.root, "table.md"), "w") as f:
        f.write(text)
    plot_success_vs_round(cfg, table, run.path("figures", "success_vs_round.png"))
    plot_table(cfg, table, run.path("figures", "table_i.png"))
    panels = sigma_panels(cfg, {"eval": results, "unseen": results_unseen}, stats["calibration"])
    if panels:
        plot_success_vs_sigma(panels, run.path("figures", "success_vs_sigma.png"))
    return text


def noise_levels(methods):
    """{sigma: row} of a run's noise-level rows: fixed_<s> at s (the paper's median steps), zero_noise at 0."""
    return dict(sorted({**({0.0: "zero_noise"} if "zero_noise" in methods else {}),
                        **{float(m[len("fixed_"):]): m for m in methods if is_fixed(m)}}.items()))


def sigma_panels(cfg, results, calibration):
    """success_vs_sigma's panels at the run's last round, or [] for a run of fewer than two noise levels (or an env
    without the paper's median step, the sigmas' unit): [(title, {row: [one value per lineage]}, {sigma: row},
    the pooled row's sigma or None)]. results: {'eval' | 'unseen': success[method][lineage][k-1]} in percent."""
    levels = noise_levels(cfg.methods)
    if len([s for s in levels if s > 0]) < 2 or paper_median_step(cfg.env) is None:
        return []
    k = cfg.rounds
    per = calibration.get(str(k), {})
    pooled_sigma = (float(np.mean([np.sqrt(np.mean(np.square(v["sigma_per_joint_paper"]))) for v in per.values()]))
                    if per and "pooled" in cfg.methods else None)
    panels = []
    for scenarios, success in results.items():
        rows = {m: [row[k - 1] if m != "bc" else row[0] for row in success.get(m, {}).values()
                    if len(row) >= (1 if m == "bc" else k)] for m in cfg.methods}
        rows = {m: v for m, v in rows.items() if v}
        if "hg_dagger" in rows and sum(m in rows for m in levels.values()) >= 2:
            panels.append((f"K = {k}, {scenario_words(cfg, scenarios)}", rows, levels, pooled_sigma))
    return panels


T_975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228)  # Student's t, df 1..10


def t_975(df):
    """Student's t quantile 0.975 for df >= 1: the table to 10, beyond it Cornish-Fisher's expansion around the
    normal's 1.96 (within 0.001 of the exact value from df 11 on)."""
    if df <= len(T_975):
        return T_975[df - 1]
    z = 1.959964
    return (z + (z ** 3 + z) / (4 * df) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * df ** 2)
            + (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / (384 * df ** 3))


def plot_success_vs_sigma(panels, path):
    """Success against the noise's sigma, one panel a scenario set: each point the mean over lineages with its
    95 % t interval (none for one lineage); HG-DAgger at sigma = 0, pooled Sigma-bar^alpha at its measured sigma
    (sqrt of the mean per-joint variance: the isotropic sigma of the same size), BC dashed."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def ci(values):
        v = np.asarray(values, float)
        if v.size < 2:
            return v.mean(), 0.0
        return v.mean(), t_975(v.size - 1) * v.std(ddof=1) / np.sqrt(v.size)

    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4), sharey=True, squeeze=False)
    for ax, (title, rows, levels, pooled_sigma) in zip(axes[0], panels):
        have = [(s, m) for s, m in levels.items() if m in rows]
        m, e = zip(*(ci(rows[row]) for _, row in have))
        ax.errorbar([s for s, _ in have], m, yerr=e, marker="o", capsize=3,
                    label="fixed σ" + (" (σ = 0: zero_noise)" if "zero_noise" in rows else ""))
        hm, he = ci(rows["hg_dagger"])
        ax.errorbar([-0.4], [hm], yerr=[he], marker="s", capsize=3, color="k", ls="none", label="HG-DAgger (σ = 0)")
        if "pooled" in rows and pooled_sigma is not None:
            pm, pe = ci(rows["pooled"])
            ax.errorbar([pooled_sigma], [pm], yerr=[pe], marker="*", markersize=11, capsize=3, color="C3", ls="none",
                        label=f"pooled Σ̄^α (σ ≈ {pooled_sigma:.1f})")
        if "bc" in rows:
            ax.axhline(np.mean(rows["bc"]), color="gray", ls="--", lw=1, label="BC")
        n = len(rows["hg_dagger"])
        ax.set_title(f"{title}\n" + (f"{n} lineages, mean, 95 % t interval" if n > 1 else "1 lineage: no interval"),
                     fontsize=9)
        ax.set_xticks(sorted({0.0, *levels}))  # HG-DAgger stands at 0 with or without a zero_noise row
        ax.set_xlabel("noise σ (the paper's median steps)")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("success (%)")
    axes[0, -1].legend(fontsize=8, loc="best")
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_success_vs_round(cfg, table, path):
    """The run's table as lines over rounds; where the paper has the env's table, its numbers in a panel beside
    (same colours, same y-span: the orderings and gaps compare, the levels do not)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paper = paper_table(cfg)
    fig, axes = plt.subplots(1, 2 if paper else 1, figsize=(13 if paper else 8.5, 4), squeeze=False)
    span = _draw_success_lines(axes[0, 0], cfg, table)
    axes[0, 0].set_title(f"Success vs round ({cfg.env}, this run)")
    if paper:
        paper_span = _draw_success_lines(axes[0, 1], cfg, paper)
        axes[0, 1].set_title(f"The paper's Table {table_number(cfg)}")
        half = max(span[1] - span[0], paper_span[1] - paper_span[0]) / 2 + 2  # one y-span for both panels
        for ax, (lo, hi) in ((axes[0, 0], span), (axes[0, 1], paper_span)):
            ax.set_ylim((lo + hi) / 2 - half, (lo + hi) / 2 + half)
    axes[0, -1].legend(fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5), frameon=False)  # outside
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)


def _draw_success_lines(ax, cfg, table):
    """plot_success_vs_round's lines on one axis, a colour per method in cfg.methods' order. Returns the
    (lowest, highest) value drawn (mean -+ SE)."""
    ks = np.arange(1, cfg.rounds + 1)
    values = []
    for method in cfg.methods:
        if method not in table:
            continue
        if method == "bc":
            ax.axhline(table["bc"][0][0], color="k", ls=":", label=method_label("bc"))
            values.append(table["bc"][0][0])
            continue
        cells = table[method]
        xs = [k for k, c in zip(ks, cells) if c]
        if not xs:
            continue
        m = np.array([c[0] for c in cells if c])
        se = np.array([c[1] for c in cells if c])
        i = list(cfg.methods).index(method)
        xs = np.array(xs, float) + 0.04 * (i - len(cfg.methods) / 2)  # side by side, not on top of each other
        style = "-o" if method in ("pooled", "per_step", "closed_loop") else ("-s" if method == "hg_dagger" else "--.")
        ax.errorbar(xs, m, yerr=se, fmt=style, capsize=3, label=method_label(method), color=f"C{i % 10}")
        values += [*(m - se), *(m + se)]
    ax.set_xlabel("DAgger round K")
    ax.set_ylabel("success rate [%]")
    ax.set_xticks(ks)
    ax.set_xlim(0.6, cfg.rounds + 0.4)
    return (min(values), max(values)) if values else (0.0, 100.0)


def plot_table(cfg, table, path):
    """Table I (II for engine3d) as the paper draws it: rows = methods, columns = rounds, each cell shaded
    by its mean success ("darker colors denote higher success") and labelled mean ± SE (n); the best
    cell of each round is boxed and bold."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    rows = [m for m in cfg.methods if m in table]
    R, C = len(rows), cfg.rounds
    means = np.full((R, C), np.nan)
    for i, m in enumerate(rows):
        for k in range(C):
            cell = table[m][0] if m == "bc" else table[m][k]
            if cell is not None:
                means[i, k] = cell[0]
    width, height = 3.7 + 1.9 * C, 1.0 + 0.42 * R  # inches: method labels, one column per round
    fig, ax = plt.subplots(figsize=(width, height))
    lo, hi = np.nanmin(means) if np.isfinite(means).any() else 0, np.nanmax(means) if np.isfinite(means).any() else 1
    shade = lambda v: plt.cm.Blues(0.15 + 0.7 * (v - lo) / max(hi - lo, 1e-9))  # noqa: E731
    best = [int(np.nanargmax(means[:, k])) if np.isfinite(means[:, k]).any() else -1 for k in range(C)]
    for i, m in enumerate(rows):
        for k in range(C):
            v = means[i, k]
            if m == "bc" and k > 0:
                continue  # one pi_0 for every round: one cell across the row
            span = C if m == "bc" else 1
            color = shade(v) if np.isfinite(v) else (1, 1, 1, 1)
            ax.add_patch(Rectangle((k, R - 1 - i), span, 1, facecolor=color, edgecolor="white", lw=2))
            cell = table[m][0] if m == "bc" else table[m][k]
            text = format_cell(cell) + (", all K" if m == "bc" else "")
            dark = np.isfinite(v) and (v - lo) / max(hi - lo, 1e-9) > 0.6
            is_best = m != "bc" and best[k] == i
            ax.text(k + span / 2, R - 0.5 - i, text, ha="center", va="center", fontsize=9,
                    color="white" if dark else "black", fontweight="bold" if is_best else "normal")
            if is_best:
                ax.add_patch(Rectangle((k + 0.03, R - 1 - i + 0.06), 0.94, 0.88, fill=False, edgecolor="#d55e00", lw=2))
    ax.set_xlim(0, C)
    ax.set_ylim(0, max(R, 1))  # a run with no finished row yet: an empty table
    ax.set_xticks(np.arange(C) + 0.5, [f"K = {k}" for k in range(1, C + 1)])
    ax.xaxis.tick_top()
    ax.set_yticks(R - 0.5 - np.arange(R), [method_label(m) for m in rows])
    ax.tick_params(length=0)
    for side in ax.spines.values():
        side.set_visible(False)
    name = f"Table {table_number(cfg)}"
    fig.text(0.5, 1 - 0.1 / height, f"{name} analogue: success rate [%], mean ± SE (n lineages)\n"
             f"darker = higher; boxed = the best of its round", ha="center", va="top", fontsize=9)
    fig.subplots_adjust(left=3.5 / width, right=1 - 0.1 / width, top=1 - 0.85 / height, bottom=0.05 / height)
    fig.savefig(path, dpi=150)
    plt.close(fig)


FIGURE_CAPTIONS = {
    "table_i.png": "Table I as the paper draws it: rows are methods, columns DAgger rounds, cells shaded by "
                   "mean success; the boxed cell is the best of its round.",
    "success_vs_sigma.png": "Success against the noise's size at the last round, on the evaluation scenarios (where "
                            "the interventions were collected) and on the unseen ones: HG-DAgger at sigma = 0, "
                            "pooled Sigma-bar^alpha at its measured sigma, BC dashed; does more noise cost on the "
                            "one set and pay on the other?",
    "success_vs_round.png": "The same numbers as lines: does each method improve with more rounds of "
                            "interventions, and where does it sit against BC (dotted)?",
    "fig1_recovery.png": "Fig. 1: the expert path (blue), the calibrated noise Sigma^alpha at a few states "
                         "(ellipses), and recovery chunks from noised states back to the path (orange).",
    "fig2_method_overview.png": "Fig. 2: (a) open-loop Sigma_hat along expert data, (b) blended rollouts, "
                                "(c) per-step Sigma^alpha, (d) pooled Sigma_bar^alpha.",
    "fig3_partial_denoising.png": "Fig. 3: partial denoising at one state: the larger the blend ratio beta, "
                                  "the more the sampled chunks follow the policy instead of the expert.",
    "fig4_blend_fit.png": "Fig. 4: settling error of the blended rollouts against sigma^2_k_sw with the "
                          "fitted equilibrium curve; its value at 1 is W, with a bootstrap interval (left axis: our "
                          "median steps; right axis: the paper's, where its W = 8.0 planar reads).",
    "fig5_environment.png": "Fig. 5: a scenario of the environment with an oracle demonstration.",
    "fig5_policy_view.png": "What the image policy sees: its camera input at a few steps of a demonstration.",
}


def figure_caption(name, cfg):
    """FIGURE_CAPTIONS[name], said for the run's env (Table II and the top view for the UR5)."""
    caption = FIGURE_CAPTIONS[name]
    if paper_env(cfg.env) == "engine3d":
        caption = caption.replace("Table I as", "Table II as")
        if name[:4] in ("fig1", "fig2", "fig3"):
            caption += " The UR5's end effector is drawn in the top view (x, y in m)."
    return caption


def write_markdown_report(run, text, stats, stats_unseen):
    """report.md: the run folder readable on its own -- the table, the statistics in words, every figure
    with a one-line caption of what to see."""
    cfg = run.cfg
    lines = [f"# {cfg.name}: Policy-Calibrated DAgger on the {cfg.env} env", "",
             f"Profile settings: {cfg.n_demos} demonstrations, BC {cfg.bc_steps} steps, {cfg.rounds} round(s), "
             f"{cfg.lineages} lineage(s), fine-tuning {cfg.finetune_steps} steps per cell, interventions "
             f"collected on the evaluation scenarios (the paper's protocol: the evaluation scenarios enter the "
             f"training data)"
             + (f"; every policy is also evaluated on {scenario_words(cfg, 'unseen')}" if cfg.eval_unseen else "")
             + ". The noised rows' return label: " + (", ".join(sorted(LABEL_WORDS.get(label, label)
                                                               for label in folder_labels(run.root)))
                                                    or "no lineage yet") + ".", "", "## Table", "", text.rstrip(), ""]
    words = paired_words(stats)
    if words:
        lines += ["## The paired statistics in words", ""] + words + [""]
    words = paired_words(stats_unseen or {})
    if words:
        lines += [f"On {scenario_words(cfg, 'unseen')}:", ""] + words + [""]
    drawn = [f for f in FIGURE_CAPTIONS if os.path.exists(os.path.join(run.root, "figures", f))]
    if drawn:
        lines += ["## Figures", ""]
        for f in drawn:
            lines += [f"**{f}** — {figure_caption(f, cfg)}", "", f"![{f}](figures/{f})", ""]
    with open(os.path.join(run.root, "report.md"), "w") as fh:
        fh.write("\n".join(lines))


def paired_words(stats):
    """report.md's sentences for the paired statistics: each method vs HG-DAgger, TOST vs the best fixed sigma."""
    words = []
    for m, s in stats.get("paired_vs_hg_dagger", {}).items():
        words.append(f"- {method_label(m)} − HG-DAgger = {s['diff']:+.1f} points averaged over rounds, "
                     + stat_words(s) + ".")
    for m, s in stats.get("tost_vs_best_fixed", {}).items():
        words.append(f"- {method_label(m)} against the best fixed noise in hindsight ({s['vs']}): "
                     f"{s['diff']:+.1f} points; " + ("no spread" if s.get("degenerate") else
                     f"TOST at ±{s['margin']:g} points, p = {s['p']:.3g} "
                     + ("(equivalent at 5 %)" if s["p"] < 0.05 else "(equivalence not shown)")) + ".")
    return words

