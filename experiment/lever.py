"""A research variant: the authors' lever recipe, their UR5 runs' training (benchmarks/SETUP.md §2; PCD lib_repro.sh
lever_train and lever_seeds.sh), measured here as benchmarks/results/table2_authors_finetune(_seeds)
(benchmarks/HISTORY.md, "The authors' lever fine-tuning" and "The authors' replicate design"). Run it with
`python dagger.py --profile table2 --recipe authors_lever` (or authors_lever_seeds).

Where it differs from the paper's recipe (dagger.py's defaults, the authors' planar runs, Table I):
  - fine-tuning: pi_0 ends its own cosine at bc_steps; every arm continues pi_0's AdamW state at a constant
    lr / 10 for finetune_steps more (their +20k at 1e-6 after BC's 1e-5 peak); the table's BC row is pi_0 itself;
  - interventions shorter than H are kept (their teleop_pad_short_episodes): a chunk repeats its run's last action
    past the run's end and those steps are out of the loss (do_mask_loss_for_padding); the noised arms draw states
    at their steps too. D0 and the calibration keep the paper's rule;
  - the intervention share of a batch is split over rounds in proportion to their intervention frames;
  - authors_lever_seeds: every lineage trains on lineage 0's interventions and calibrations with its own training
    seeds (three training seeds on one intervention set); lineage 0 runs first.

It brings its own functions, which the harness hands to dagger.policy_calibrated_dagger (loop_arguments): a
learning-rate function (AuthorsLeverLR), a BC row (pi0_is_the_bc_row), a label rule (every_run) and the
intervention samplers (controls.Rows with the padded chunks and label steps, rounds by frames); the seeds' data
through the harness's memo (data_of_lineage_0).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Callable

import dagger
import diffusion
import envs
from experiment.controls import Rows, padded_chunks, padded_label_steps
from experiment.run_folder import RunFolderError

RECIPES = ("authors_lever", "authors_lever_seeds")


# ---- the padded label rule (their teleop_pad_short_episodes, do_mask_loss_for_padding: controls.padded_chunks)
class PaddedChunkSampler:
    """HG-DAgger's intervention rows as recorded, at every intervention step, with the padded steps' loss mask."""

    def __init__(self, episodes, H):
        self.obs, self.chunks, self.mask = padded_chunks(episodes, H)

    def __call__(self, n, rng):
        pick = rng.integers(len(self.obs), size=n)
        return self.obs[pick], self.chunks[pick], self.mask[pick]


# ---- the recipe's functions, handed to the loop (loop_arguments) ---------------------------------------------------
def every_run(expert, H):
    """The label rule of their collection: every intervention is kept, however short (the paper's: >= H steps)."""
    return diffusion.expert_runs(expert, 1)


def frame_shares(frames):
    """A batch's intervention rows over rounds 1..k in proportion to their intervention frames."""
    return [f / sum(frames) for f in frames]


@dataclass(frozen=True)
class AuthorsLeverLR:
    """Their learning rate (train_cfg.lr the peak): pi_0 warms up and ends its own cosine at bc_steps; every arm
    continues pi_0's AdamW state at a constant lr / 10 (their +20k steps at 1e-6 after BC's 1e-5 peak)."""
    bc_steps: int

    def __call__(self, step, train_cfg):
        if step >= self.bc_steps:
            return train_cfg.lr / 10
        warmup = min(500, self.bc_steps // 10)
        if step < warmup:
            return train_cfg.lr * (step + 1) / warmup
        progress = (step - warmup) / max(1, self.bc_steps - warmup)
        return train_cfg.lr * 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


def pi0_is_the_bc_row(cfg, demos, pi0, memo=None, log=print, make_env=envs.make_env, lr_schedule=None):
    """Their table's BC row: pi_0 itself, evaluated (dagger.bc_row_arm's arguments and result)."""
    return pi0, dagger.evaluate_policy(memo or dagger.compute, cfg, "eval/bc.json", pi0, "bc", log, make_env=make_env)


def loop_arguments(cfg):
    """What the recipe hands dagger.policy_calibrated_dagger (besides the env factory)."""
    return dict(lr_schedule=AuthorsLeverLR(cfg.bc_steps), label_rule=every_run, bc_row=pi0_is_the_bc_row,
                sampler=Rows(chunks=PaddedChunkSampler, label_steps=padded_label_steps, shares=frame_shares))


def check_recipe(cfg):
    """ValueError for a config the recipe cannot run (experiment/profiles.check_config, before any folder)."""
    if cfg.recipe == "authors_lever_seeds" and "closed_loop" in cfg.methods:
        raise ValueError(f"recipe {cfg.recipe!r} trains every lineage on lineage 0's interventions, but the "
                         "closed_loop row collects its own chain of them: run it with recipe 'authors_lever'")


def data_of_lineage_0(cfg, memo):
    """The loop's memo for the run's recipe: with authors_lever_seeds, a lineage's interventions and calibrations
    (lineage_l/round_k/D.npz, calibration.json) are lineage 0's files (check_lineages: made before it)."""
    return LineageZerosData(memo) if cfg.recipe == "authors_lever_seeds" else memo


@dataclass(frozen=True)
class LineageZerosData:
    """memo(name, step, ...) with lineage_l/round_k/D.npz and calibration.json read as lineage 0's (a class, not a
    closure: worker processes receive the loop's memo)."""
    memo: Callable

    def __call__(self, name, step, *args, **kwargs):
        parts = name.split("/")
        if len(parts) == 3 and parts[0].startswith("lineage_") and parts[2] in ("D.npz", "calibration.json"):
            name = "/".join(["lineage_0", *parts[1:]])
        return self.memo(name, step, *args, **kwargs)


def check_lineages(run, lineages):
    """RunFolderError if the run's recipe trains lineages > 0 on lineage 0's interventions and a run of them alone
    would find lineage 0's last round missing in the folder (the harness's check before the loop)."""
    others = [lineage for lineage in lineages if lineage > 0]
    if run.cfg.recipe != "authors_lever_seeds" or 0 in lineages or not others:
        return  # lineage 0 runs first in this command, or no lineage needs another's data
    last = os.path.join(run.root, "lineage_0", f"round_{run.cfg.rounds}", "D.npz")
    if not os.path.exists(last):
        raise RunFolderError(f"recipe {run.cfg.recipe}: lineage {others[0]} trains on lineage 0's interventions, and "
                             f"{last} is not there yet; run lineage 0 first (--lineage 0, or all lineages in one "
                             "command)")
