"""The paper's figures (fig1-fig5) of a run folder, from D0 and lineage 0, round 1: which files, which episode and
which policy each draws. The drawing is each figure's concept module's: oracle.plot_demonstration (fig5),
calibrate.plot_blend_fit (fig4), calibrate.plot_method_overview (fig2), relabel.plot_recovery (fig1),
partial_denoise.plot_partial_denoising (fig3). experiment/report.py calls make_figures when an input changed.
"""
from __future__ import annotations

import os

import numpy as np
import torch

import calibrate
import dagger
import diffusion
import oracle as oracle_mod
import partial_denoise
import relabel
from dagger import stage_seed
from experiment import engine3d, environments

FIGURE_INPUTS = ("data/D0.npz", "lineage_0/round_1/D.npz", "lineage_0/round_1/calibration.json",
                 "lineage_0/round_1/checkpoints/hg_dagger.pt")  # what make_figures draws from


def make_figures(run):
    """fig1-fig5 (the paper's analogues) from D0 and lineage 0, round 1 (skipped figures are logged)."""
    cfg = run.cfg
    if not os.path.exists(os.path.join(run.root, "data", "D0.npz")):  # a folder of joined lineage results only
        run.log("no data/D0.npz here (lineages joined from results files): the paper's figures need --prepare")
        return
    demos = run.load("data/D0.npz")
    stats = dagger.demo_statistics(cfg, demos, environments.make_env)  # the unit of the noise drawn
    fig = lambda name: run.path("figures", name)  # noqa: E731
    env = environments.make_env(cfg.env)
    if env.dim == 2:  # fig5: the planar scene drawn with a demonstration; the UR5's scene rendered by pybullet
        oracle_mod.plot_demonstration(env, demos[0], fig("fig5_environment.png"))
    else:
        env.reset(seed=int(demos[0]["seed"]))
        engine3d.render_scene_image(env, fig("fig5_environment.png"))
    env.plot_policy_view(demos[0], fig("fig5_policy_view.png"))  # a variant's camera input; the paper's envs: none
    if not os.path.exists(os.path.join(run.root, "lineage_0", "round_1", "calibration.json")):
        run.log("figures 1-4 need lineage 0 round 1: not finished yet")
        return
    D1 = run.load("lineage_0/round_1/D.npz")
    cal = run.load("lineage_0/round_1/calibration.json")
    # the policy that was calibrated: the round's HG-DAgger policy (benchmarks/SETUP.md §5)
    calibrated = "lineage_0/round_1/checkpoints/hg_dagger.pt"
    policy = run.load(calibrated if os.path.exists(os.path.join(run.root, calibrated)) else "checkpoints/bc.pt")
    gen = lambda: torch.Generator(device=policy.device).manual_seed(stage_seed(cfg, "figures"))  # noqa: E731
    episode = max(D1, key=lambda ep: ep["expert"].sum())  # the longest intervention shows the method best
    calibrate.plot_blend_fit(cal, stats.median_step, fig("fig4_blend_fit.png"))
    # figs 1-3 draw end-effector paths: in the plane of the planar env, in the top view (x, y) of the UR5's
    calibrate.plot_method_overview(env, episode, cal, policy, fig("fig2_method_overview.png"), generator=gen())
    relabel.plot_recovery(env, episode, cal.pooled, fig("fig1_recovery.png"),
                          np.random.default_rng(stage_seed(cfg, "fig1")), stats,
                          relabel.RelabelConfig(horizon=cfg.horizon))
    t = int(np.flatnonzero(diffusion.label_mask(episode["expert"], cfg.horizon))[0])  # fig3: the first labelled state
    chunk = episode["action"][t:t + cfg.horizon]
    chunk = np.pad(chunk, ((0, cfg.horizon - len(chunk)), (0, 0)), mode="edge")  # past the end: the last action
    env.reset(seed=int(episode["seed"]))
    partial_denoise.plot_partial_denoising(env, policy, episode["obs"][t], chunk, (0.1, 0.3, 0.5, 0.7),
                                           fig("fig3_partial_denoising.png"), gen(), q=episode["q"][t])
