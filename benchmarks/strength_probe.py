"""The probe of strength: does one knob of the policy's strength lift BC and HG-DAgger above the table1 recipe?

One lineage (lineage 0, master seed 0), one round (K = 1), rows BC and HG-DAgger only; every other field is the
table1 profile's. The knobs, each alone (the design, stated before any result: benchmarks/HISTORY.md, "Policy
strength"; its result: benchmarks/README.md):

    base     the table1 recipe itself: pi_0 and the BC row from the committed start, lineage 0's round 1 rerun here
    steps3x  3x the gradient steps: pi_0 at 30k of one 60k cosine, every row continued +30k
    wide     the residual MLP twice as wide (mlp_width 512: 2.93 M parameters against 0.78 M)
    k100     K = 100 diffusion steps, trained and sampled (a DDPM trained on 20 noise levels cannot be sampled at 100)
    unet     the authors' 1-D conv U-Net at (32, 64, 128) in place of the MLP, at the table1 budget (10k + 10k, batch 256)

    python benchmarks/strength_probe.py --run KNOB [--out runs/strength_probe]  # resumable: run it again after a stop
    python benchmarks/strength_probe.py --table                                # the probe's table from the committed files

A run writes its run folder (OUT/KNOB), then the lineage's results file and its stages' costs to
benchmarks/results/strength_probe/KNOB/ (lineage_0.json.gz, cost.json). --table reads only those committed files.
"""
from __future__ import annotations

import argparse
import glob
import gzip
import json
import math
import os
import resource
import sys
import time
from dataclasses import replace

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import dagger  # noqa: E402
from experiment import cli, profiles

RESULTS = os.path.join(ROOT, "benchmarks", "results", "strength_probe")
KNOBS = {
    "base": {},
    "steps3x": dict(bc_steps=30_000, finetune_steps=30_000),
    "wide": dict(mlp_width=512),
    "k100": dict(K=100),
    "unet": dict(network="unet", down_dims=(32, 64, 128)),
}
ROWS = ("bc", "hg_dagger")


def probe_config(knob):
    """table1's Config, one round, rows BC and HG-DAgger, with the knob's fields."""
    return replace(profiles.PROFILES["table1"], name=f"probe_{knob}", rounds=1, methods=ROWS, **KNOBS[knob])


def run(knob, out, workers):
    """The knob's lineage 0, round 1 (resuming its run folder), then its results file and costs."""
    folder = os.path.join(out, knob)
    if knob == "base":  # the committed start's pi_0 and BC row (the profile table1 copies them in)
        argv = ["--profile", "table1", "--rounds", "1", "--methods", ",".join(ROWS)]
    else:
        profiles.PROFILES[f"probe_{knob}"] = probe_config(knob)
        argv = ["--profile", f"probe_{knob}"]
    dest = os.path.join(RESULTS, knob)
    t0 = time.time()
    cli.main(argv + ["--lineage", "0", "--out", folder, "--workers", str(workers)])
    cpu = sum(getattr(resource.getrusage(who), f) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
              for f in ("ru_utime", "ru_stime"))
    cli.main(argv + ["--lineages", "1", "--report", "--out", folder, "--export-lineages", dest]
                if knob != "base" else argv + ["--report", "--out", folder, "--export-lineages", dest])
    cost_path = os.path.join(dest, "cost.json")
    cost = json.load(open(cost_path)) if os.path.exists(cost_path) else {"sittings": []}
    cost["stages_s"] = {os.path.basename(p)[:-5]: json.load(open(p))["seconds"]
                        for p in sorted(glob.glob(os.path.join(folder, "timings", "*.json")))}
    cost["sittings"].append({"wall_s": time.time() - t0, "cpu_s": cpu, "machine": machine()})
    with open(cost_path, "w") as fh:
        json.dump(cost, fh, indent=1)
    print(f"wrote {cost_path}")


def machine():
    """The CPU's family and model (the timings depend on the kind of machine)."""
    try:
        lines = open("/proc/cpuinfo").read().splitlines()
    except OSError:
        return "unknown"
    get = lambda key: next((l.split(":", 1)[1].strip() for l in lines if l.startswith(key)), "?")
    return f"{get('model name')} (family {get('cpu family')}, model {get('model')})"


def evaluation(files, key):
    """Per-scenario success rate (mean over repeats) and the scenario seeds."""
    e = files[key]
    return np.asarray(e["success"], float).mean(axis=1), list(e["seeds"])


def paired(a, b):
    """mean and SE over scenarios of a - b (two per-scenario rate arrays on the same scenarios), in points."""
    d = 100.0 * (np.asarray(a) - np.asarray(b))
    return float(d.mean()), float(d.std(ddof=1) / math.sqrt(d.size))


def load(knob):
    path = os.path.join(RESULTS, knob, "lineage_0.json.gz")
    if not os.path.exists(path):
        return None
    with gzip.open(path, "rt") as fh:
        return json.load(fh)["files"]


def table():
    """The probe's table from the committed files: BC, HG-DAgger, HG - BC (paired over the 100 scenarios),
    HG - the base's HG (paired over scenarios), and the knob's CPU-hours."""
    base = load("base")
    base_hg = evaluation(base, "lineage_0/round_1/eval/hg_dagger.json") if base else None
    print("| knob | BC | HG-DAgger | HG − BC (paired SE) | HG − base HG (paired SE) | kept (> 1 SE) | CPU-h |")
    print("|---|---|---|---|---|---|---|")
    for knob in KNOBS:
        files = load(knob)
        if files is None:
            print(f"| {knob} | not run | | | | | |")
            continue
        bc, seeds = evaluation(files, "eval/bc.json")
        hg, hg_seeds = evaluation(files, "lineage_0/round_1/eval/hg_dagger.json")
        assert seeds == hg_seeds, f"{knob}: BC and HG-DAgger on different scenarios"
        m, se = paired(hg, bc)
        lift = kept = ""
        if base_hg is not None and knob != "base":
            assert base_hg[1] == seeds, f"{knob}: not the base's scenarios"
            lm, lse = paired(hg, base_hg[0])
            lift, kept = f"{lm:+.1f} ± {lse:.1f}", "yes" if lm > lse else "no"
        cost = json.load(open(os.path.join(RESULTS, knob, "cost.json")))
        cpu_h = sum(s["cpu_s"] for s in cost["sittings"]) / 3600
        print(f"| {knob} | {100 * bc.mean():.1f} | {100 * hg.mean():.1f} | {m:+.1f} ± {se:.1f} | {lift} | {kept} | "
              f"{cpu_h:.2f} |")


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", choices=sorted(KNOBS), help="run this knob (resumes its folder)")
    p.add_argument("--out", default=os.path.join("runs", "strength_probe"), help="folder of the knobs' run folders")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--table", action="store_true", help="print the probe's table from the committed files")
    a = p.parse_args()
    if a.run:
        run(a.run, a.out, a.workers)
    if a.table or not a.run:
        table()
