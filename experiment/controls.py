"""Research controls: rows that are not the paper's, beside Table I's, to separate what a method's parts do.

    zero_noise         the noised arms' whole pipeline with sigma = 0: every intervention state relabelled by the
                       return labels, no noise. It separates the effect of the noise from that of relabelling (a noised
                       arm never sees the recorded intervention chunks, HG-DAgger sees nothing else). Measured on the
                       lever: benchmarks/HISTORY.md, "The σ = 0 control on the lever" (and the mid run's σ = 0 row).
    authors_hg_dagger  HG-DAgger as the authors' kit trained it (benchmarks/SETUP.md §2): each intervention its own
                       episode, every one of its steps a chunk start, a chunk that runs past the intervention's end
                       repeating its last action, and those padded "hold still at the hand-back point" steps in the
                       loss (PCD paper/tables_repro/planar_arms.sh: the hg arm passes only dart_relabel=false, so it
                       keeps the BC config's do_mask_loss_for_padding false; the lerobot fork's dataset clamps a
                       chunk's indices to its episode). Interventions shorter than 2 s are dropped, as in D_k: the
                       kit's collection passes teleop_pad_short_episodes=false with 60-frame episodes at least (2 s at
                       30 Hz = H at our 10 Hz). The paper's text, hg_dagger: only chunks that end inside their
                       intervention (t + H <= its end, Sec. IV-C) -- except where the intervention ends the episode:
                       the label rule (diffusion.label_mask) keeps those chunks, padded with the last action, so
                       hg_dagger already trains on the padded chunks of an intervention that ends its episode (35 %
                       of its intervention chunks in table1's lineage 0, round 1, re-collected for the strength probe).
                       The two rows differ only at the hand-backs before the episode's end: the last H - 1 steps of
                       such an intervention are chunk starts (padded, "hold still") here and not in hg_dagger.
    cotrain_fixed_8,   the paper's text's co-training (Sec. IV-A step 4, "co-train on the aggregate dataset and the
    cotrain_pooled     augmented intervention data"): a noised row's intervention rows half as recorded (hg_dagger's
                       chunks), half noised and relabelled (fixed sigma 8, pooled Sigma-bar^alpha). Table I's noised
                       rows noise every frame they draw, as the authors' code does.
Measured: benchmarks/HISTORY.md, "Why the noise's gain does not show here".
    zero_noise_servo,  zero_noise, fixed_8 and pooled with the authors' servo return label (experiment/servo.py, in
    fixed_8_servo,     the authors' units) instead of the paper's PD: each row its default twin with the one change
    pooled_servo       of label, so that a study can run both.

Each row is a Row of ROWS (its intervention sampler per round, and its words); the harness hands the loop a Rows
(dagger.policy_calibrated_dagger's sampler) where a config names one of them, or runs a recipe with its own samplers
(experiment/lever.py). It imports dagger.py, never the reverse.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np

import dagger
import diffusion
import relabel
from experiment import servo


# ---- the authors' padded cut (their teleop_pad_short_episodes; lever.py masks the padded steps) ----------------
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


class AuthorsChunkSampler:
    """The authors' HG-DAgger rows: (obs, chunk) at every intervention step of the episodes (every expert run their
    flags hold); past the intervention's end the chunk repeats its last action, and no mask: every step is in the
    loss (lever.PaddedChunkSampler is the same cut with those steps masked, as the authors' noised arms do)."""

    def __init__(self, episodes, H):
        self.obs, self.chunks, _ = padded_chunks(episodes, H)  # the padded steps' mask is not used

    def __call__(self, n, rng):
        pick = rng.integers(len(self.obs), size=n)
        return self.obs[pick], self.chunks[pick]


@dataclass(frozen=True)
class Row:
    """A row that builds a round's intervention sampler itself: sampler(D, H, recorded, noised) with recorded() the
    round's hg_dagger sampler and noised(noise, make=relabel.AugmentationSampler, cfg=relabel.RelabelConfig) a
    noised sampler, noise a Table I method's name or a (kind, sigma) of relabel.AugmentationSampler, make and cfg
    the sampler class and its config (the return label: the core's the paper's PD, servo.ServoSampler the
    authors' servo); what: its rows in words (the log's)."""
    sampler: Callable
    what: str


def co_trained(method):
    """Half of the intervention rows as recorded, half noised with `method`'s noise (Sec. IV-A step 4)."""
    return Row(lambda D, H, recorded, noised: relabel.MixtureSampler([recorded(), noised(method)], [0.5, 0.5]),
               f"half as recorded, half noised ({method}) and relabelled")


ROWS = {"zero_noise": Row(lambda D, H, recorded, noised: noised(("isotropic", 0.0)),
                          "every drawn frame relabelled, no noise (sigma = 0)"),
        "authors_hg_dagger": Row(lambda D, H, recorded, noised: AuthorsChunkSampler(D, H),
                                 "every intervention step a chunk start, the padded steps in the loss"),
        "cotrain_fixed_8": co_trained("fixed_8"),
        "cotrain_pooled": co_trained("pooled")}


def servo_labelled(noise):
    """A noised row with the authors' servo return label (experiment/servo.py) instead of the paper's PD."""
    return Row(lambda D, H, recorded, noised: noised(noise, servo.ServoSampler, servo.ServoConfig),
               "every drawn frame noised and relabelled by the authors' servo (experiment/servo.py)")


# The noised rows with the authors' servo label beside the default PD's (zero_noise, fixed_8, pooled): the label's
# difference, as a study compares them
ROWS.update({"zero_noise_servo": servo_labelled(("isotropic", 0.0)), "fixed_8_servo": servo_labelled("fixed_8"),
             "pooled_servo": servo_labelled("pooled")})


def equal_shares(frames):
    """The paper's shares of a batch's intervention rows: rounds 1..k equally."""
    return [1.0] * len(frames)


@dataclass(frozen=True)
class Rows:
    """The loop's sampler (dagger.intervention_sampler's arguments and result) for a run with the rows above or a
    recipe's own samplers: per round, HG-DAgger's rows (chunks), a Table I method's noised rows (states drawn at
    label_steps, None: the paper's rule), or a ROWS row's own; the rounds in the recipe's shares of their frames."""
    chunks: Callable = relabel.ChunkSampler
    label_steps: Callable = None
    shares: Callable = equal_shares

    def __call__(self, cfg, method, rounds_data, calibration, stats, make_env):
        per_round, first = [], np.cumsum([0] + [len(D) for D in rounds_data])  # each round's first episode index
        for D, offset in zip(rounds_data, first):
            def noised(noise, make=relabel.AugmentationSampler, config=relabel.RelabelConfig, D=D, offset=offset):
                kind, sigma = noise if isinstance(noise, tuple) else dagger.noise_model(
                    noise, calibration, range(offset, offset + len(D)), stats.median_step, stats.paper_median_step)
                return make(D, functools.partial(make_env, cfg.env), stats, kind, sigma,
                            config(horizon=cfg.horizon), self.label_steps)

            recorded = functools.partial(self.chunks, D, cfg.horizon)
            per_round.append(ROWS[method].sampler(D, cfg.horizon, recorded, noised) if method in ROWS else
                             recorded() if method == "hg_dagger" else noised(method))
        return relabel.MixtureSampler(per_round, self.shares([sum(int(ep["expert"].sum()) for ep in D)
                                                              for D in rounds_data]))
