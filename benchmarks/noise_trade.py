"""Where the noise wins and loses: each row - HG-DAgger by pi_0's per-scenario class, paired over lineages.

pi_0's committed evaluation (eval/pi0.json, scenarios x repeats) puts every evaluation scenario in one class,
independent of every row: *never* (pi_0 solved it in none of its repeats), *sometimes*, *always*. The rounds collect
interventions only where pi_0 (then the lineage's policy) fails, so the classes separate the scenarios the
interventions were recorded on from the ones they were not. For each row and round, and each class, the row's success
on that class's scenarios minus HG-DAgger's, in points, one difference per lineage; mean +- SE over lineages, t(n-1).
The fixed-sigma rows also give the dose-response: per lineage the least-squares slope of that difference on sigma
(points per paper median step), t over lineages.

It reads only committed results files (--export-lineages), no training:

    python benchmarks/noise_trade.py benchmarks/results/table1 benchmarks/results/mid benchmarks/results/table2 \\
        --figure benchmarks/figures/noise_trade.png
    python benchmarks/noise_trade.py benchmarks/results/table1 --with benchmarks/results/table1_k1_controls \\
        --round 1 --compare authors_hg_dagger-hg_dagger fixed_8-authors_hg_dagger cotrain_fixed_8-fixed_8

--with joins another folder's rows (trained later on the same start) lineage by lineage, only where that folder's
hg_dagger evaluation equals this one's bit for bit (the same interventions and training); a lineage where it does
not keeps only the other folder's own rows and is named. --compare A-B: A - B paired over lineages and over the
scenarios (a scenario's success averaged over lineages and repeats, t(scenarios - 1)), on both scenario sets.
"""
from __future__ import annotations

import argparse
import os
import re
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from paired_bc import load_lineages, t_test  # noqa: E402

CLASSES = ("never", "sometimes", "always")


def pi0_classes(files):
    """(scenarios,) str: pi_0's class of each evaluation scenario from its committed evaluation."""
    solved = np.asarray(files["eval/pi0.json"]["success"], bool).sum(axis=1)  # (scenarios,) repeats solved
    repeats = len(files["eval/pi0.json"]["success"][0])
    return np.where(solved == 0, "never", np.where(solved == repeats, "always", "sometimes"))


def success(files, lineage, k, method, unseen=False):
    """(scenarios, repeats) float success of a row at round k, or None if the lineage has none."""
    key = f"lineage_{lineage}/round_{k}/eval/{method}{'_unseen' if unseen else ''}.json"
    return np.asarray(files[key]["success"], float) if key in files else None


def rows_of(lineages, k):
    """The rows evaluated at round k in any lineage, in a stable order."""
    found = {m.group(1) for files in lineages.values() for key in files
             for m in [re.fullmatch(rf"lineage_\d+/round_{k}/eval/(\w+?)\.json", key)] if m}
    return sorted(m for m in found if not m.endswith("_unseen"))


def merge(lineages, other, rounds, names=("first", "other")):
    """lineages with other's rows added where other's hg_dagger equals lineages' at every round in `rounds`;
    returns (merged, {lineage: True if joined bit for bit, False if only other's own rows are kept},
    origin: {lineage: {file key: the name in `names` of the folder it came from}})."""
    merged, matched = {l: dict(f) for l, f in lineages.items()}, {}
    origin = {l: {key: names[0] for key in f} for l, f in lineages.items()}
    for l, files in other.items():
        same = l in lineages and all(
            success(files, l, k, "hg_dagger") is not None
            and np.array_equal(success(files, l, k, "hg_dagger"), success(lineages[l], l, k, "hg_dagger"))
            for k in rounds)
        matched[l] = same
        if same:
            added = {key: v for key, v in files.items() if key not in merged[l]}
            merged[l].update(added)
            origin.setdefault(l, {}).update({key: names[1] for key in added})
        else:  # another round 1 here: its rows pair only with each other
            merged[l] = dict(files)
            origin[l] = {key: names[1] for key in files}
    return merged, matched, origin


def row_origin(origin, lineages, k, method):
    """'folder: lineages; folder: lineages' — where a row's evaluations at round k came from (a --with join)."""
    by_folder = {}
    for l in sorted(lineages):
        folder = origin.get(l, {}).get(f"lineage_{l}/round_{k}/eval/{method}.json")
        if folder is not None:
            by_folder.setdefault(folder, []).append(str(l))
    return "; ".join(f"{f}: {','.join(ls)}" for f, ls in by_folder.items()) or "-"


def class_differences(lineages, k, method, base="hg_dagger"):
    """{class or 'all': [method - base in points on that class's scenarios, one per lineage holding both]}."""
    out = {c: [] for c in CLASSES + ("all",)}
    for l, files in sorted(lineages.items()):
        a, b = success(files, l, k, method), success(files, l, k, base)
        if a is None or b is None:
            continue
        cls = pi0_classes(files)
        for c in CLASSES:
            if (cls == c).any():
                out[c].append(100.0 * (a[cls == c].mean() - b[cls == c].mean()))
        out["all"].append(100.0 * (a.mean() - b.mean()))
    return out


def fmt(diffs):
    if len(diffs) < 2:
        return f"{diffs[0]:+.1f} (1)" if diffs else "-"
    mean, se, t, df, p = t_test(diffs)
    return f"{mean:+.1f} ± {se:.1f}, p {p:.2g}"


def class_table(name, lineages, k, base="hg_dagger", origin=None):
    """Markdown: every row - base by pi_0's class at round k; the class sizes in the header. origin (from merge):
    a last column naming the folder each row's lineages came from, and a line for the base row's."""
    cls = pi0_classes(next(iter(lineages.values())))
    sizes = {c: int((cls == c).sum()) for c in CLASSES}
    head = " | ".join(f"{c} ({sizes[c]})" for c in CLASSES)
    lines = [f"{name}, K = {k}: row − {base} in points, mean ± SE over lineages, paired t",
             f"| row | n | {head} | all |" + (" rows from (folder: lineages) |" if origin else ""),
             "|---|---|" + "---|" * (len(CLASSES) + 1 + bool(origin))]
    for m in rows_of(lineages, k):
        if m in (base, "bc"):
            continue
        d = class_differences(lineages, k, m, base)
        lines.append(f"| {m} | {len(d['all'])} | " + " | ".join(fmt(d[c]) for c in CLASSES + ("all",)) + " |"
                     + (f" {row_origin(origin, lineages, k, m)} |" if origin else ""))
    if origin:
        lines.append(f"{base} from {row_origin(origin, lineages, k, base)}")
    return "\n".join(lines)


def fixed_sigmas(lineages, k):
    return sorted(int(m.split("_")[1]) for m in rows_of(lineages, k) if re.fullmatch(r"fixed_\d+", m))


def dose_response(lineages, k, base="hg_dagger"):
    """({class or 'all': per-lineage slopes (points per paper median step) of fixed_s - base on s, over the lineages
    holding every fixed sigma}, the sigmas, {s: class_differences of fixed_s} over every lineage holding it)."""
    sigmas = fixed_sigmas(lineages, k)
    per_sigma = {s: class_differences(lineages, k, f"fixed_{s}", base) for s in sigmas}
    complete = {l: f for l, f in lineages.items()
                if all(success(f, l, k, m) is not None for m in [base] + [f"fixed_{s}" for s in sigmas])}
    diffs = {s: class_differences(complete, k, f"fixed_{s}", base) for s in sigmas}  # aligned: one per lineage
    slopes = {c: [float(np.polyfit(sigmas, [diffs[s][c][i] for s in sigmas], 1)[0])
                  for i in range(len(diffs[sigmas[0]][c]))] if len(sigmas) >= 2 else []
              for c in CLASSES + ("all",)}
    return slopes, sigmas, per_sigma


def dose_table(name, lineages, k):
    slopes, sigmas, _ = dose_response(lineages, k)
    if len(sigmas) < 2:
        return f"{name}, K = {k}: fewer than two fixed sigmas, no dose-response"
    return (f"{name}, K = {k}: slope of (fixed σ − hg_dagger) on σ ∈ {sigmas}, points per paper median step, "
            "mean ± SE over lineages\n" + "\n".join(f"  {c}: {fmt(slopes[c])}" for c in CLASSES + ("all",)))


def compare(lineages, k, a, b, unseen=False):
    """A - B at round k: (over lineages: mean, SE, t, df, p, n) and (over scenarios: mean, SE, t, df, p), points."""
    per_lineage, sa, sb = [], [], []
    for l, files in sorted(lineages.items()):
        x, y = success(files, l, k, a, unseen), success(files, l, k, b, unseen)
        if x is None or y is None:
            continue
        per_lineage.append(100.0 * (x.mean() - y.mean()))
        sa.append(x.mean(axis=1))
        sb.append(y.mean(axis=1))
    if len(per_lineage) < 2:
        return None
    over_scenarios = 100.0 * (np.mean(sa, axis=0) - np.mean(sb, axis=0))  # (scenarios,)
    return (*t_test(per_lineage), len(per_lineage)), t_test(over_scenarios)


def compare_line(lineages, k, a, b, unseen=False):
    out = compare(lineages, k, a, b, unseen)
    if out is None:
        return f"{a} − {b}: fewer than two lineages hold both"
    (m, se, t, df, p, n), (m2, se2, t2, df2, p2) = out
    return (f"{a} − {b} ({'unseen' if unseen else 'evaluation'}): {m:+.1f} ± {se:.1f} over {n} lineages, "
            f"t({df}) = {t:.2f}, p = {p:.2g}; over scenarios {m2:+.1f} ± {se2:.1f}, t({df2}) = {t2:.2f}, p = {p2:.2g}")


def plot(panels, path, k):
    """One panel per folder: fixed sigma - hg_dagger against sigma, one line per class, SE bars over lineages; the
    class sizes in each panel's title, the legend outside the data."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels) + 1.8, 3.6), squeeze=False, sharey=True)
    for ax, (name, lineages) in zip(axes[0], panels):
        _, sigmas, per_sigma = dose_response(lineages, k)
        cls = pi0_classes(next(iter(lineages.values())))
        for c, color in zip(CLASSES + ("all",), ("tab:red", "tab:orange", "tab:green", "black")):
            means = [np.mean(per_sigma[s][c]) for s in sigmas]
            ses = [np.std(per_sigma[s][c], ddof=1) / np.sqrt(len(per_sigma[s][c])) for s in sigmas]
            ax.errorbar(sigmas, means, yerr=ses, marker="o", capsize=3, color=color, label=c,
                        linestyle="--" if c == "all" else "-")
        ax.axhline(0, color="gray", lw=0.8)
        n = len(per_sigma[sigmas[0]]["all"]) if sigmas else 0
        sizes = " / ".join(str(int((cls == c).sum())) for c in CLASSES)
        ax.set_title(f"{name}, K = {k}, {n} lineages\nscenarios never / sometimes / always: {sizes}", fontsize=9)
        ax.set_xlabel("fixed σ (paper median steps)")
        ax.set_xticks(sigmas)
    axes[0][0].set_ylabel("fixed σ − HG-DAgger (success points)")
    axes[0][-1].legend(title="π0 solved the scenario", fontsize=8, title_fontsize=8, loc="center left",
                       bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+", help="folders of lineage_*.json.gz (e.g. benchmarks/results/table1)")
    ap.add_argument("--with", dest="other", default=None, help="a folder whose rows join the first folder's")
    ap.add_argument("--round", type=int, default=None, help="one round (default: every round)")
    ap.add_argument("--base", default="hg_dagger", help="the row every class difference is taken against")
    ap.add_argument("--compare", nargs="*", default=(), metavar="A-B", help="rows A - B, paired (first folder)")
    ap.add_argument("--figure", default=None, help="PNG: fixed sigma - HG-DAgger by class, one panel per folder")
    args = ap.parse_args(argv)
    panels = []
    for i, folder in enumerate(args.folders):
        lineages, origin = load_lineages(folder), None
        name = os.path.basename(os.path.normpath(folder))
        rounds = sorted({int(m.group(1)) for f in lineages.values() for key in f
                         for m in [re.match(r"lineage_\d+/round_(\d+)/", key)] if m})
        if i == 0 and args.other:
            other = load_lineages(args.other)
            other_rounds = sorted({int(m.group(1)) for f in other.values() for key in f
                                   for m in [re.match(r"lineage_\d+/round_(\d+)/", key)] if m})
            other_name = os.path.basename(os.path.normpath(args.other))
            lineages, matched, origin = merge(lineages, other, other_rounds, (name, other_name))
            name = f"{name} with {other_name}"
            print(f"{args.other} joined: " + ", ".join(f"lineage {l} {'bit for bit' if ok else 'NOT the same round'}"
                                                      for l, ok in sorted(matched.items())))
        for k in [args.round] if args.round else rounds:
            print(class_table(name, lineages, k, args.base, origin) + "\n")
            print(dose_table(name, lineages, k) + "\n")
        if i == 0:
            for pair in args.compare:
                a, b = pair.split("-", 1) if "-" in pair else (pair, args.base)
                for k in [args.round] if args.round else rounds:
                    for unseen in (False, True):
                        print(f"K = {k}: " + compare_line(lineages, k, a, b, unseen))
        panels.append((name, lineages))
    if args.figure:
        print("wrote", plot(panels, args.figure, args.round or 1))


if __name__ == "__main__":
    main()
