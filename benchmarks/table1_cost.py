"""What all of Table I costs on this machine: each stage measured in a run folder, counted for the table1
profile (or any profile), and the wall it projects for 5 lineages on 2 cores and on more cores.

A run folder's timings/ holds the wall seconds of every finished stage (experiment.run_folder.Run.record_time).
Run it on a folder made with the same recipe (mid: the same data, network, steps and evaluations; table1 is
mid with five rounds and every row), with the lineages that ran one process per core (the seconds are wall
seconds: lineages that shared the cores with more processes than cores are slower per stage):

  python benchmarks/table1_cost.py --run runs/mid --lineages 3 4 [--profile table1] [--cores 2 4 8 16]

Prints a markdown table of the stages (measured count and mean; how many a table1 lineage runs; its seconds),
then one lineage's wall with --workers 1 and 2, and the projected wall for the profile's lineages on each core
count: prepare, then the lineages side by side, floor(cores / workers) at a time, for the best --workers.
A stage the folder has not measured at a round is taken from the last round it has (collection), or
extrapolated linearly over rounds (calibration, whose input grows with every round's interventions); such
rows say "projected". Run it on a table1 folder itself to get the measured cost.

The model is the loop as dagger.py runs it: per round, collection, HG-DAgger's cell (fine-tuning and its two
evaluations), calibration, the noised arms in waves of --workers, then the closed-loop row's round (collection
and calibration from round 2, its cell), one stage after another.
"""
import argparse
import json
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import dagger  # noqa: E402
from experiment import profiles


def read_timings(root, lineages):
    """{(kind, round or 0, chain): [seconds]} from root/timings; lineages: keep only these (None: all)."""
    folder = os.path.join(root, "timings")
    if not os.path.isdir(folder):
        raise SystemExit(f"--run {root}: no timings/ folder (a run folder of dagger.py has one)")
    out = {}
    for name in sorted(os.listdir(folder)):
        with open(os.path.join(folder, name)) as f:
            t = json.load(f)
        parts = t["stage"].split("/")
        lineage = next((int(p.split("_")[1]) for p in parts if p.startswith("lineage_")), None)
        if lineages is not None and lineage is not None and lineage not in lineages:
            continue
        k = next((int(p.split("_")[1]) for p in parts if p.startswith("round_")), 0)
        kind = parts[0]
        if kind.startswith("train_") and kind not in ("train_bc", "train_hg_dagger"):
            kind = "train_noised"  # every noised arm trains the same steps on the same batch
        out.setdefault((kind, k, "closed_loop" in parts), []).append(t["seconds"])
    return out


def per_round(timings, kind, k, grow=False):
    """(seconds, measured?) of stage kind at round k: its mean there, else the last measured round's (or, with
    grow, a straight line through the first and last measured rounds)."""
    rounds = sorted({r for (kd, r, _) in timings if kd == kind and r > 0})
    if not rounds:
        raise SystemExit(f"the run folder has no measured {kind!r} stage in these lineages")
    mean = {r: float(np.mean([s for (kd, rr, _), v in timings.items() if kd == kind and rr == r for s in v]))
            for r in rounds}
    if k in mean:
        return mean[k], True
    if grow and len(rounds) >= 2:
        a, b = rounds[0], rounds[-1]
        return max(mean[a], mean[a] + (mean[b] - mean[a]) * (k - a) / (b - a)), False
    return mean[rounds[-1]], False


def flat(timings, kind):
    values = [s for (kd, _, _), v in timings.items() if kd == kind for s in v]
    if not values:
        raise SystemExit(f"the run folder has no measured {kind!r} stage")
    return float(np.mean(values))


def lineage_wall(cfg, timings, workers):
    """(seconds of one lineage with `workers` processes, rows of the stage table)."""
    noised = [m for m in cfg.methods if m not in ("bc", "hg_dagger", "closed_loop")]
    ev = 2 * flat(timings, "evaluate") if cfg.eval_unseen else flat(timings, "evaluate")  # a cell's evaluations
    rows, wall = {}, 0.0

    def add(name, count, seconds, measured, serial_count=None):
        n, s, m = rows.get(name, (0, 0.0, True))
        rows[name] = (n + count, s + count * seconds, m and measured)
        return (serial_count if serial_count is not None else count) * seconds

    for k in range(1, cfg.rounds + 1):
        wall += add("collect", 1, *per_round(timings, "collect", k))
        hg, m = per_round(timings, "train_hg_dagger", k)
        wall += add("cell: HG-DAgger (train + evaluations)", 1, hg + ev, m)
        if noised or "closed_loop" in cfg.methods:
            wall += add("calibrate", 1, *per_round(timings, "calibrate", k, grow=True))
        if noised:
            cell, m = per_round(timings, "train_noised", k)
            wall += add("cell: a noised arm (train + evaluations)", len(noised), cell + ev, m,
                        serial_count=math.ceil(len(noised) / workers))
        if "closed_loop" in cfg.methods:
            if k > 1:
                wall += add("closed-loop chain: collect", 1, *per_round(timings, "collect", k))
                wall += add("closed-loop chain: calibrate", 1, *per_round(timings, "calibrate", k, grow=True))
            cell, m = per_round(timings, "train_noised", k)
            wall += add("closed-loop chain: cell", 1, cell + ev, m)
    return wall, rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, help="a run folder with timings/ (e.g. runs/mid)")
    ap.add_argument("--lineages", type=int, nargs="*", default=None,
                    help="use only these lineages' stages (those that ran one process per core)")
    ap.add_argument("--profile", default="table1", choices=sorted(profiles.PROFILES))
    ap.add_argument("--cores", type=int, nargs="*", default=[2, 4, 8, 16])
    args = ap.parse_args(argv)
    cfg = profiles.PROFILES[args.profile]
    timings = read_timings(args.run, set(args.lineages) if args.lineages else None)
    # timings' names: 'bc' is pi_0's training, 'train_bc' the BC row's (pi_0 continued on D0 alone)
    prepare = sum(flat(timings, kind) for kind in ("demos", "bc")) + flat(timings, "evaluate")
    bc_row = flat(timings, "train_bc") + 2 * flat(timings, "evaluate")  # the BC row, in the background
    walls = {w: lineage_wall(cfg, timings, w)[0] for w in (1, 2, 3, 4, 7, 8)}
    _, rows = lineage_wall(cfg, timings, 1)
    print(f"Stages measured in {args.run}" + (f" (lineages {args.lineages})" if args.lineages else "")
          + f", counted for the {args.profile} profile ({cfg.rounds} rounds, {len(cfg.methods)} rows, "
            f"{cfg.lineages} lineages):\n")
    print("| stage | per lineage | s each | s per lineage | source |")
    print("|---|---|---|---|---|")
    for name, (n, s, measured) in rows.items():
        print(f"| {name} | {n} | {s / n:.0f} | {s:.0f} | {'measured' if measured else 'projected from the measured rounds'} |")
    core_s = sum(s for _, s, _ in rows.values())
    print(f"| one lineage, all stages | | | {core_s:.0f} ({core_s / 3600:.1f} core-h) | |")
    print(f"| prepare (D0, BC, pi_0's evaluation) | | | {prepare:.0f} | once |")
    print(f"| BC row (beside the lineages) | | | {bc_row:.0f} | once |")
    print()
    print(f"One lineage alone: {walls[1] / 3600:.2f} h with --workers 1, {walls[2] / 3600:.2f} h with --workers 2.")
    print()
    print(f"| cores | best plan | projected wall for {cfg.lineages} lineages |")
    print("|---|---|---|")
    for c in args.cores:
        best = None
        for w in sorted(walls):
            if w > c:
                continue
            side = max(1, c // w)  # lineage processes at once; the last, smaller batch gets more workers each
            full, rest = divmod(cfg.lineages, side)
            w_last = max(v for v in walls if v <= max(1, c // rest)) if rest else w
            total = prepare + full * walls[w] + (walls[w_last] if rest else 0.0)
            if full:
                plan = f"{full} x {side} lineages side by side with --workers {w}"
                plan += f", then {rest} with --workers {w_last}" if rest else ""
            else:
                plan = f"all {rest} side by side with --workers {w_last}"
            if best is None or total < best[0]:
                best = (total, plan)
        print(f"| {c} | {best[1]} | {best[0] / 3600:.1f} h |")


if __name__ == "__main__":
    main()
