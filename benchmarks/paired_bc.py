"""HG-DAgger - BC (or any arm - BC) paired over the evaluation scenarios, the lineages averaged.

The BC row is one policy shared by every lineage, evaluated once (100 scenarios x 3 repeats). A paired t
over lineages of (arm's rate - BC's rate) treats that one evaluation as exact: its own sampling error is
common to every lineage's difference and never enters the lineages' spread. This script pairs over the
scenarios instead, so BC's error counts:

    per scenario s:  d_s = mean over lineages and repeats of the arm's success on s
                         - mean over repeats of BC's success on s
    paired t over the scenarios (df = number of scenarios - 1).

It reads only the committed results files (``--export-lineages``); no training, no evaluation:

    python benchmarks/paired_bc.py benchmarks/results/mid
    python benchmarks/paired_bc.py benchmarks/results/table2 --method pooled

Each line also gives the earlier design for comparison (paired over lineages, BC's rate taken as exact).
Standard library and numpy; the t distribution is the project's ``dagger.student_t_cdf``.
"""

from __future__ import annotations

import argparse
import glob
import gzip
import json
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from dagger import student_t_cdf  # noqa: E402


def load_lineages(folder):
    """{lineage index: its 'files' dict} for every lineage_*.json.gz in folder."""
    out = {}
    for path in sorted(glob.glob(os.path.join(folder, "lineage_*.json.gz"))):
        with gzip.open(path, "rt") as fh:
            d = json.load(fh)
        out[int(d["lineage"])] = d["files"]
    if not out:
        raise SystemExit(f"no lineage_*.json.gz in {folder}")
    return out


def matrix(evaluation):
    """(seeds, success as a scenarios x repeats float array)."""
    return list(evaluation["seeds"]), np.asarray(evaluation["success"], float)


def t_test(d):
    """Two-sided one-sample t of mean(d) = 0: (mean, SE, t, df, p)."""
    d = np.asarray(d, float)
    n = d.size
    mean, sd = float(d.mean()), float(d.std(ddof=1))
    se = sd / math.sqrt(n)
    if se == 0:
        return mean, 0.0, (0.0 if mean == 0 else math.copysign(math.inf, mean)), n - 1, (1.0 if mean == 0 else 0.0)
    t = mean / se
    return mean, se, t, n - 1, 2.0 * (1.0 - student_t_cdf(abs(t), n - 1))


def compare(lineages, method, rnd, unseen):
    suffix = "_unseen" if unseen else ""
    bc_seeds, bc = matrix(next(iter(lineages.values()))[f"eval/bc{suffix}.json"])
    arms, rates = [], []
    for lin, files in sorted(lineages.items()):
        key = f"lineage_{lin}/round_{rnd}/eval/{method}{suffix}.json"
        if key not in files:
            continue
        seeds, s = matrix(files[key])
        if seeds != bc_seeds:
            raise SystemExit(f"{key}: scenarios differ from BC's")
        arms.append(s.mean(axis=1))                     # per scenario, mean over repeats
        rates.append((lin, int(s.sum()), s.size))
    if not arms:
        return None
    per_scenario = 100.0 * (np.mean(arms, axis=0) - bc.mean(axis=1))
    mean, se, t, df, p = t_test(per_scenario)
    bc_count = int(bc.sum())
    above = sum(c > bc_count for _, c, _ in rates)
    ties = sum(c == bc_count for _, c, _ in rates)
    lineages_word = "lineages" if len(arms) > 1 else "lineage"
    line = (f"K={rnd} {'unseen' if unseen else 'eval  '} {method} - BC, {len(arms)} {lineages_word} averaged, "
            f"paired over {per_scenario.size} scenarios: {mean:+.1f} +- {se:.1f}, t({df}) = {t:.2f}, p = {p:.3g}")
    old = ""
    if len(arms) >= 2:
        lin_diff = [100.0 * (c / n - bc.mean()) for _, c, n in rates]
        m2, se2, t2, df2, p2 = t_test(lin_diff)
        old = (f"      [earlier design, over lineages with BC's {bc.size} episodes taken as exact: {m2:+.1f} +- "
               f"{se2:.1f}, t({df2}) = {t2:.2f}, p = {p2:.3g}; {above} of {len(arms)} lineages above BC"
               f"{f', {ties} tied' if ties else ''}]")
    return line, old


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folder", help="a folder of lineage_*.json.gz (e.g. benchmarks/results/mid)")
    ap.add_argument("--method", default="hg_dagger", help="the arm compared with BC (default hg_dagger)")
    args = ap.parse_args(argv)
    lineages = load_lineages(args.folder)
    rounds = sorted({int(k.split("/")[1].split("_")[1]) for f in lineages.values() for k in f
                     if k.startswith("lineage_") and "/round_" in k})
    print(f"{args.folder}: lineages {sorted(lineages)}, rounds {rounds}")
    for unseen in (False, True):
        for rnd in rounds:
            out = compare(lineages, args.method, rnd, unseen)
            if out is None:
                continue
            print(out[0])
            if out[1]:
                print(out[1])


if __name__ == "__main__":
    main()
