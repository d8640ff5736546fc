"""The probe of a cheaper quick profile: does `python dagger.py`'s story (HG-DAgger over BC) hold at a
training step that costs less, and does the run then take five minutes?

The design (benchmarks/HISTORY.md, "A cheaper quick profile"), stated before any of its results:

    now      the quick profile as it is (residual MLP width 256, batch 256)
    narrow   the same run with the MLP half as wide and half the batch (mlp_width 128, batch_size 128): every
             stage, step count, seed and row as quick's; only the network's width and the rows per step change
    short    the same run with fewer steps at the full width (bc_steps 2,500 + finetune_steps 2,500 of 6,000 +
             6,000): added after narrow's result, stated before its own runs, the design's next lead

each at master seeds 0, 1, 2 on one machine kind. The rule, fixed now: `narrow` replaces the quick profile when the
mean over the three seeds of HG-DAgger - BC (paired over the 100 scenarios x 3) is no smaller than `now`'s; `short`
by the same rule.

    python benchmarks/quick_probe.py --run CANDIDATE --seed S [--out runs/quick_probe] [--workers 2]
    python benchmarks/quick_probe.py --table       # the probe's table from the committed files

A run writes its run folder (OUT/CANDIDATE_seedS; it resumes), then its results file and its stages' seconds to
benchmarks/results/quick_probe/CANDIDATE_seedS/ (lineage_0.json.gz, cost.json with the run's wall, the worker
count and the machine). Its wall counts only on a quiet machine with two workers; its table on any machine of the
same kind (the same seed gives the same numbers for any worker count). --table reads only the committed files.
"""
from __future__ import annotations

import argparse
import gzip
import json
import os
import sys
import time
from dataclasses import replace

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import dagger  # noqa: E402
from strength_probe import evaluation, machine, paired  # noqa: E402
from experiment import cli, profiles

RESULTS = os.path.join(ROOT, "benchmarks", "results", "quick_probe")
CANDIDATES = {
    "now": {},
    "narrow": dict(mlp_width=128, batch_size=128),
    "short": dict(bc_steps=2500, finetune_steps=2500),
}
SEEDS = (0, 1, 2)
ROWS = {"bc": "eval/bc.json", "hg_dagger": "lineage_0/round_1/eval/hg_dagger.json",
        "fixed_4": "lineage_0/round_1/eval/fixed_4.json", "pooled": "lineage_0/round_1/eval/pooled.json"}


def run(candidate, seed, out, workers):
    """The candidate's whole quick run at this master seed (resuming its folder), then its results file and cost."""
    name = f"{candidate}_seed{seed}"
    profiles.PROFILES[f"quick_{candidate}"] = replace(profiles.PROFILES["quick"], name=f"quick_{candidate}",
                                                    **CANDIDATES[candidate])
    folder, dest = os.path.join(out, name), os.path.join(RESULTS, name)
    t0 = time.time()
    cli.main(["--profile", f"quick_{candidate}", "--seed", str(seed), "--out", folder,
                 "--workers", str(workers), "--export-lineages", dest])
    timings = os.path.join(folder, "timings")
    cost = {"wall_s": round(time.time() - t0, 1), "workers": workers, "machine": machine(),
            "stages_s": {f[:-5]: json.load(open(os.path.join(timings, f)))["seconds"]
                         for f in sorted(os.listdir(timings))}}
    with open(os.path.join(dest, "cost.json"), "w") as fh:
        json.dump(cost, fh, indent=1)
    print(f"wrote {dest}")


def load(name):
    path = os.path.join(RESULTS, name, "lineage_0.json.gz")
    if not os.path.exists(path):
        return None, None
    with gzip.open(path, "rt") as fh:
        files = json.load(fh)["files"]
    return files, json.load(open(os.path.join(RESULTS, name, "cost.json")))


def table():
    """Per candidate and seed: the four rows, HG - BC paired over scenarios, the wall; then the rule's means."""
    print("| candidate | seed | BC | HG-DAgger | fixed σ = 4 | pooled | HG − BC (paired SE) | wall (workers) |")
    print("|---|---|---|---|---|---|---|---|")
    gaps = {}
    for candidate in CANDIDATES:
        for seed in SEEDS:
            files, cost = load(f"{candidate}_seed{seed}")
            if files is None:
                print(f"| {candidate} | {seed} | not run | | | | | |")
                continue
            bc, seeds = evaluation(files, ROWS["bc"])
            hg, hg_seeds = evaluation(files, ROWS["hg_dagger"])
            assert seeds == hg_seeds, f"{candidate} seed {seed}: BC and HG-DAgger on other scenarios"
            gap, se = paired(hg, bc)
            gaps.setdefault(candidate, []).append(gap)
            cells = [f"{100 * evaluation(files, ROWS[m])[0].mean():.1f}" if ROWS[m] in files else "—" for m in ROWS]
            print(f"| {candidate} | {seed} | {' | '.join(cells)} | {gap:+.1f} ± {se:.1f} | "
                  f"{cost['wall_s']:.0f} s ({cost['workers']}) |")
    for candidate, g in gaps.items():
        print(f"{candidate}: mean HG − BC over {len(g)} seed(s) {np.mean(g):+.1f}")
    for candidate in CANDIDATES:
        if candidate != "now" and all(len(gaps.get(c, ())) == len(SEEDS) for c in ("now", candidate)):
            keep = np.mean(gaps[candidate]) >= np.mean(gaps["now"])
            print(f"rule ({candidate}'s mean HG − BC >= now's): "
                  f"{f'{candidate} may replace quick' if keep else 'quick stays'}")


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", choices=sorted(CANDIDATES), help="run this candidate (resumes its folder)")
    p.add_argument("--seed", type=int, choices=SEEDS, default=0, help="master seed")
    p.add_argument("--out", default=os.path.join("runs", "quick_probe"), help="folder of the candidates' run folders")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--table", action="store_true", help="print the probe's table from the committed files")
    a = p.parse_args()
    if a.run:
        run(a.run, a.seed, a.out, a.workers)
    if a.table or not a.run:
        table()
