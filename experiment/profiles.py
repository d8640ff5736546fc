"""The run sizes of `python dagger.py --profile NAME`, and the config's valid values (check_config, where a
config enters: the command line, run_experiment).

Each profile is a set of overrides of dagger.Config's defaults (which are the paper's protocol), as
nanoGPT keeps its run configurations beside train.py; PROFILES holds the checked Configs.
"""
from __future__ import annotations

import numpy as np

import dagger
import diffusion
from experiment import controls, environments, lever

# Every method a run may name: Table I's rows and the research controls' (experiment/controls.py)
ALL_METHODS = dagger.TABLE_I_METHODS + tuple(controls.ROWS)
RECIPES = ("paper", *lever.RECIPES)  # how pi_0 and the arms train: the paper's (the authors' planar runs), a variant's

PROFILE_FIELDS = {
    # CI: every stage and every output file, tiny sizes (about 2 minutes). The calibration keeps the paper's
    # blend protocol (one rollout per ratio from every intervention segment long enough to keep, 9 in the
    # smoke round), so CI fits W by Eq. (12): with one segment (calib_blend_segments=1) each ratio had one
    # rollout, fewer than min_survivors = 3, and W always fell back to the open-loop error. Measured: 46 of
    # 117 rollouts kept, 6 ratios fitted; the calibration 2 s -> 4 s, the run 1 min 45 s -> 1 min 52 s on
    # the 2-core machine (tests/test_calibrate.py::test_the_smoke_profile_calibration_fits_W). Two lineages, so
    # that CI computes Table I's statistics (mean +- SE, the paired t-tests, TOST) from a run.
    "smoke": dict(name="smoke", n_demos=16, rounds=1, lineages=2, K=10,
                    down_dims=(16, 32), bc_steps=300, finetune_steps=150, batch_size=64, lr=1e-3,
                    methods=("bc", "hg_dagger", "fixed_4", "pooled", "per_step", "closed_loop"),
                    eval_scenarios=8, eval_repeats=1),
    # The default of `python dagger.py`: the whole loop on the planar env, the mid recipe at a student's scale
    # (one lineage, one round): 4 min 25 s - 4 min 57 s wall over three seeds on a 2-core AMD EPYC Zen 5, two
    # workers; 8 min 27 s - 9 min 17 s on an idle Zen 3, 9 min 26 s on a Zen 4 (benchmarks/README.md, "The default run").
    "quick": dict(name="quick", n_demos=300, rounds=1, lineages=1, oracle_attempts=1,
                    network="mlp", K=20, batch_size=256, lr=1e-3, bc_steps=6000, finetune_steps=6000,
                    methods=("bc", "hg_dagger", "fixed_4", "pooled"), eval_scenarios=100, eval_repeats=3),
    # Between quick and paper, for this 2-core machine (benchmarks/HISTORY.md, "Table I where DAgger has something
    # to fix"): the authors' 5 lineages for the paired statistics, 2 rounds, Table I's whole fixed sweep
    # (2 / 4 / 8 / 12 / 16: the paper's sweep, so that its best lies inside it; the sigma = 0 control, measured
    # before, is left out). The authors' evaluation starts (random, often folded: from their fixed
    # demonstration start DAgger had little to fix), their fine-tuning (every arm continues pi_0's optimizer along
    # one cosine of bc_steps + finetune_steps; their pi_0 sits at 43 % of it, ours at 50 %), and the residual-MLP
    # epsilon network, which trains ~8x more samples per CPU second than the (32, 64, 128) U-Net.
    # Lineages run side by side: --prepare, then --lineage i, then --report (README). Measured with sigma 2-16 and
    # pooled (2026-11-25): prepare 7 min, lineages 0-2 side by side 77 min, 3-4 side by side 55 min: 2 h 19 min
    # (benchmarks/HISTORY.md, "The mid run with Table I's whole sweep").
    "mid": dict(name="mid", n_demos=500, rounds=2, lineages=5,
                  network="mlp", K=20, batch_size=256, lr=1e-3, bc_steps=10_000, finetune_steps=10_000,
                  methods=("bc", "hg_dagger", "fixed_2", "fixed_4", "fixed_8", "fixed_12", "fixed_16", "pooled"),
                  eval_scenarios=100, eval_repeats=3),
    # All of Table I on the 2-core machine: the mid recipe with the paper's five rounds and every row (the fixed
    # sweep, pooled, per-step, and the closed-loop row's own chain of rounds), 5 lineages. One lineage is 45
    # fine-tuned cells; run it as --prepare, then --lineage i (side by side, or on other days and machines:
    # lineage folders join with --report), then --report. Measured (2026-11-25): prepare 7 min, one lineage 1 h 48 min
    # with --workers 2; five lineages 7.2 h projected on 2 cores (python benchmarks/table1_cost.py --run runs/table1;
    # benchmarks/HISTORY.md, "All of Table I: one whole table1 lineage").
    "table1": dict(name="table1", n_demos=500, rounds=5, lineages=5,
                     network="mlp", K=20, batch_size=256, lr=1e-3, bc_steps=10_000, finetune_steps=10_000,
                      methods=("bc", "hg_dagger", "fixed_2", "fixed_4", "fixed_8", "fixed_12", "fixed_16", "pooled",
                              "per_step", "closed_loop"),
                     eval_scenarios=100, eval_repeats=3),
    # The strength study (benchmarks/README.md, "A stronger policy: the probe and the study"): table1 with the strength probe's
    # kept knob, 3x the gradient steps (pi_0 at 30k of one 60k cosine, every row +30k; the kept 2x width left out
    # for its cost: 2.53x a step), K = 1, the study's seven rows. Measured: ~1.4 h of one core a lineage, ~7.4 CPU-h
    # in all (Zen 3). --prepare and --export-start, then --lineage i side by side, --export-lineages
    # benchmarks/results/table1_strong. Its result: HG-DAgger 72.8, no noised row above it (benchmarks/README.md).
    "table1_strong": dict(name="table1_strong", n_demos=500, rounds=1, lineages=5,
                            network="mlp", K=20, batch_size=256, lr=1e-3, bc_steps=30_000, finetune_steps=30_000,
                            methods=("bc", "hg_dagger", "authors_hg_dagger", "fixed_4", "fixed_8", "fixed_16",
                                     "pooled"),
                            eval_scenarios=100, eval_repeats=3),
    # The Table II analogue for this machine: the UR5 engine-lever env with Table II's rows (BC, HG-DAgger, pooled
    # Sigma-bar^alpha; the paper's 2 rounds and 3 lineages) and fixed sigma = 4 and 8 (8: the authors' calibrated
    # size in radians). The epsilon network chosen by measurement (python benchmarks/lever_networks.py;
    # benchmarks/HISTORY.md, "epsilon-networks the lever learns at CPU cost"): the U-Net at half the widths, batch 256,
    # BC 10k steps of one cosine of 20k that every arm continues (pi_0 45.0 % in 9.7 CPU-min; the earlier
    # U-Net (32, 64, 128), batch 64, 30k restarted: 49.0 % in ~48 CPU-min). --prepare, --lineage 0/1/2 side by
    # side, --report (README). Measured (2026-11-25): a cell 10.5 min of fine-tuning + 1 min of evaluations,
    # lineages 0 and 1 side by side 2 h (25 min of it lost to a side job); ~2 h 50 min end to end projected
    # (benchmarks/HISTORY.md, "The Table II analogue today").
    "table2": dict(name="table2", env="engine3d", n_demos=500, rounds=2, lineages=3,
                     K=20, down_dims=(16, 32, 64), batch_size=256, lr=1e-3, bc_steps=10_000,
                     finetune_steps=10_000,
                     methods=("bc", "hg_dagger", "fixed_4", "fixed_8", "pooled"),
                     eval_scenarios=100, eval_repeats=3),
    # Table I's protocol at the authors' sizes (benchmarks/SETUP.md §2): their U-Net widths, 100 diffusion
    # steps, batch 32, lr 1e-5, BC 75k steps, every cell fine-tuned +100k (for a GPU or a cluster).
    "paper": dict(name="paper", down_dims=(128, 256, 512), K=100, batch_size=32, lr=1e-5),
}


def check_config(cfg):
    """cfg (a dagger.Config) with BC and HG-DAgger first in methods and tuples where JSON gives lists, or a clear
    ValueError for a field outside its valid values: where a config enters (the command line, run_experiment, a
    profile), before any folder is made."""
    cfg.methods = tuple(cfg.methods)
    bad = [m for m in cfg.methods if m not in ALL_METHODS]
    if bad:
        raise ValueError(f"unknown method(s) {bad}; valid: {', '.join(ALL_METHODS)}")
    # BC and HG-DAgger anchor every comparison (paired design): always present, listed first.
    cfg.methods = ("bc", "hg_dagger") + tuple(m for m in cfg.methods if m not in ("bc", "hg_dagger"))
    if cfg.env not in environments.ENVIRONMENTS:
        raise ValueError(f"unknown env {cfg.env!r}; valid: {', '.join(sorted(environments.ENVIRONMENTS))}")
    cfg.down_dims = tuple(int(d) for d in cfg.down_dims)
    for key in ("n_demos", "rounds", "lineages", "horizon", "n_act", "K",
                "bc_steps", "finetune_steps", "batch_size", "eval_scenarios", "eval_repeats"):
        if getattr(cfg, key) < 1:
            raise ValueError(f"{key} must be >= 1, got {getattr(cfg, key)}")
    if cfg.recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {', '.join(RECIPES)} (paper: the authors' planar runs), "
                         f"got {cfg.recipe!r}")
    lever.check_recipe(cfg)
    if cfg.network not in diffusion.NETWORKS:
        raise ValueError(f"network must be one of {', '.join(diffusion.NETWORKS)}, got {cfg.network!r}")
    if not 0.0 < cfg.intervention_fraction < 1.0:
        raise ValueError(f"intervention_fraction must be in (0, 1), got {cfg.intervention_fraction}")
    if cfg.eval_scenarios > 100:
        raise ValueError(f"eval_scenarios must be <= 100 (the fixed set), got {cfg.eval_scenarios}")
    # every stage's seed is numpy's SeedSequence([seed, ...]) (dagger.stage_seed): it takes no negative
    # numbers, so a bad seed is refused here, before the run folder is made, not in the first stage
    if isinstance(cfg.seed, bool) or not isinstance(cfg.seed, (int, np.integer)) or cfg.seed < 0:
        raise ValueError(f"seed must be an integer >= 0 (the master seed every stage's seed is derived from), "
                         f"got {cfg.seed!r}")
    return cfg


PROFILES = {name: check_config(dagger.Config(**fields)) for name, fields in PROFILE_FIELDS.items()}
