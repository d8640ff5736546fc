"""A research variant: the authors' lever recipe, their UR5 runs' training (benchmarks/SETUP.md §2; PCD lib_repro.sh
lever_train and lever_seeds.sh), measured here as benchmarks/results/table2_authors_finetune(_seeds)
(benchmarks/HISTORY.md, "The authors' lever fine-tuning" and "The authors' replicate design"). Run it with
`python dagger.py --profile table2 --recipe authors_lever` (or authors_lever_seeds).

Where it differs from the paper's recipe (dagger.PaperRecipe, the authors' planar runs, Table I):
  - fine-tuning: pi_0 ends its own cosine at bc_steps; every arm continues pi_0's AdamW state at a constant
    lr / 10 for finetune_steps more (their +20k at 1e-6 after BC's 1e-5 peak); the table's BC row is pi_0 itself;
  - interventions shorter than H are kept (their teleop_pad_short_episodes): a chunk repeats its run's last action
    past the run's end and those steps are out of the loss (do_mask_loss_for_padding); the noised arms draw states
    at their steps too. D0 and the calibration keep the paper's rule;
  - the intervention share of a batch is split over rounds in proportion to their intervention frames;
  - authors_lever_seeds: every lineage trains on lineage 0's interventions and calibrations with its own training
    seeds (three training seeds on one intervention set); lineage 0 runs first.

It plugs in through what the core names: dagger.RECIPES (a recipe is the set of hooks below), diffusion.LR_SCHEDULES
('constant'), and relabel.AugmentationSampler's label rule (a subclass); the seeds' data through the harness's memo
(data_of_lineage_0). It never imports dagger.py.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable

import numpy as np

import diffusion
import relabel
from experiment.run_folder import RunFolderError


# ---- the padded label rule (their teleop_pad_short_episodes, do_mask_loss_for_padding) ---------------------------
def padded_chunks(episodes, H):
    """(obs (N, obs_dim), chunks (N, H, dof), mask (N, H) bool) at every expert-driven step of every episode: the
    chunk repeats its run's last action past the run's end, and the mask is False on those padded steps."""
    obs_list, chunk_list, mask_list = [], [], []
    for ep in episodes:
        obs, action, expert = np.asarray(ep["obs"]), np.asarray(ep["action"]), np.asarray(ep["expert"], bool)
        starts, ends = padded_label_steps(expert, H)
        steps = starts[:, None] + np.arange(H)[None, :]                 # (n, H)
        last = ends[:, None] - 1                                         # the last step of each start's own run
        obs_list.append(obs[starts].astype(np.float32))
        chunk_list.append(action[np.minimum(steps, last)].astype(np.float32))
        mask_list.append(steps <= last)
    return np.concatenate(obs_list), np.concatenate(chunk_list), np.concatenate(mask_list)


def padded_label_steps(expert, H):
    """(t, seg_end): every step t of every expert run, however short, and the end (exclusive) of its run."""
    expert = np.asarray(expert, bool)
    seg_end = np.zeros(len(expert), np.int64)
    for start, end in diffusion.expert_runs(expert, 1):  # with H = 1 every run counts, however short
        seg_end[start:end] = end
    t = np.flatnonzero(expert)
    return t, seg_end[t]


class PaddedChunkSampler:
    """HG-DAgger's intervention rows as recorded, at every intervention step, with the padded steps' loss mask."""

    def __init__(self, episodes, H):
        self.obs, self.chunks, self.mask = padded_chunks(episodes, H)

    def __call__(self, n, rng):
        pick = rng.integers(len(self.obs), size=n)
        return self.obs[pick], self.chunks[pick], self.mask[pick]


class PaddedAugmentationSampler(relabel.AugmentationSampler):
    """The noised arms' sampler with states drawn at every intervention step (the labels end with the run)."""
    label_steps = staticmethod(padded_label_steps)


def constant_lr(step, cfg):
    """diffusion.LR_SCHEDULES['constant']: cfg.lr at every step, no warm-up or cosine."""
    return cfg.lr


diffusion.LR_SCHEDULES["constant"] = constant_lr


# ---- the recipes (dagger.RECIPES) ----------------------------------------------------------------------------------
class AuthorsLever:
    """The authors' lever recipe; dagger.PaperRecipe names what each hook does in the paper's."""

    def pi0_schedule_steps(cfg):
        return 0  # pi_0 ends its own cosine at bc_steps

    def arm_training(cfg):
        return dict(lr=cfg.lr / 10, lr_schedule="constant")  # their 1e-6 after BC's 1e-5 peak

    def bc_row(pi0, continued_on_d0):
        return pi0  # the table's BC row is pi_0 itself

    def round_shares(frames):
        return [f / sum(frames) for f in frames]  # by intervention frames

    def expert_runs(expert, H):
        return diffusion.expert_runs(expert, 1)  # every intervention, however short

    ChunkSampler = PaddedChunkSampler
    AugmentationSampler = PaddedAugmentationSampler


class AuthorsLeverSeeds(AuthorsLever):
    """The lever recipe with seed replicates: lineage l > 0 trains on lineage 0's interventions and calibrations
    (the harness's memo reads them there: data_of_lineage_0)."""


RECIPES = {"authors_lever": AuthorsLever, "authors_lever_seeds": AuthorsLeverSeeds}


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
