"""Speed of one policy calibration (calibrate.py) on the PlanarReacher, stage by stage.

dagger.py calls calibrate() once per round on the round's intervention data. This script times its
stages on RRT-oracle demonstrations (cut into "interventions": each demo keeps expert labels on one
window of --segment steps, the rest marked policy-driven), with a diffusion policy trained briefly
on the demos (or loaded with --policy):

  open-loop Sigma_hat (Eq. 1)      every other label step, n_samples chunks each, batched sampling
  blend rollouts (13 betas)        closed loop with partial denoising, one call per decision
  closed-loop rollouts             unguided closed loop from the longest segments
  calibrate()                      all of the above + the fit and Eqs. (13)-(16)

Usage:  python benchmarks/bench_calibrate.py [--demos 12] [--train-steps 1000] [--policy PATH]
                                             [--threads N] [--segment 48]
Prints a markdown table (wall and CPU seconds). Numbers depend on machine load (the team shares 2
cores); --threads sets torch.set_num_threads for this process only (default: torch's default).
Small-batch torch calls are much slower with 2 threads than with 1 when other processes load the
cores; compare both.
"""
import argparse
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import calibrate as cal  # noqa: E402
import oracle  # noqa: E402
from diffusion import DiffusionPolicy, PolicyConfig, TrainConfig, chunk_dataset, train  # noqa: E402
from envs import make_env, median_step, paper_median_step  # noqa: E402


def timed(fn):
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w0, time.process_time() - c0


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--demos", type=int, default=12, help="oracle demonstrations (training seeds)")
    parser.add_argument("--train-steps", type=int, default=1000, help="policy training steps (no --policy)")
    parser.add_argument("--policy", default="", help="a DiffusionPolicy checkpoint instead of training")
    parser.add_argument("--threads", type=int, default=0, help="torch.set_num_threads (0: leave default)")
    parser.add_argument("--segment", type=int, default=48, help="expert window kept per demo (steps)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    env = make_env("planar")
    expert, seed = oracle.Oracle(), 0
    demos = []
    t0 = time.perf_counter()
    while len(demos) < args.demos:
        try:
            ep = expert.demonstrate(env, seed)
            if ep["success"]:
                demos.append(ep)
        except oracle.PlanningFailed:
            pass
        seed += 1
    print(f"{len(demos)} oracle demos in {time.perf_counter() - t0:.0f} s")
    unit = median_step(demos)
    if args.policy:
        policy = DiffusionPolicy.load(args.policy)
    else:
        policy = DiffusionPolicy(PolicyConfig(obs_dim=env.obs_dim, dof=env.dof, down_dims=(32, 64, 128)))
        train(policy, *chunk_dataset(demos, policy.cfg.horizon),
              TrainConfig(steps=args.train_steps, warmup_steps=100, log_every=0))

    # interventions: one expert window of --segment steps per demo, starting a few steps in
    interventions = []
    for ep in demos:
        expert_mask = np.zeros(len(ep["q"]), dtype=bool)
        expert_mask[5:5 + args.segment] = True
        interventions.append(dict(ep, expert=expert_mask))
    n_steps = sum(int(e["expert"].sum()) for e in interventions)

    cfg = cal.CalibrationConfig()
    threshold = cal.diverge_radius(cfg.diverge_threshold, unit, paper_median_step(env))  # as calibrate does
    gen = torch.Generator().manual_seed(0)
    H = policy.cfg.horizon
    segs = cal._segments_longest_first(interventions, H)
    chosen = [segs[i % min(len(segs), cfg.blend_segments)] for i in range(len(cfg.betas))]
    rows = []
    steps, w, c = timed(lambda: cal.open_loop_sigma(policy, interventions, cfg.stride, cfg.n_samples, gen))
    rows.append(("open-loop Sigma_hat (Eq. 1)", f"{len(steps.timestep)} steps x {cfg.n_samples} samples", w, c))
    blend, w, c = timed(lambda: cal._blend(env, policy, [(interventions[e], s) for e, s in chosen],
                                           np.asarray(cfg.betas), cfg.n_act, gen, threshold))
    rows.append(("blend rollouts", f"13 betas, {int(blend.rollouts.n_recorded.sum())} env steps, "
                 f"{int(blend.kept.sum())} kept", w, c))
    _, w, c = timed(lambda: cal.closed_loop_sigma(env, policy, interventions, cfg.n_act, gen, threshold,
                                                   cfg.closed_loop_segments))
    rows.append(("closed-loop rollouts", f"{min(len(segs), cfg.closed_loop_segments)} segments", w, c))
    calib, w, c = timed(lambda: cal.calibrate(env, policy, interventions, unit, cfg, gen))
    rows.append(("calibrate() total", f"{len(interventions)} interventions, {n_steps} expert steps", w, c))

    print(f"\ntorch threads: {torch.get_num_threads()}, policy K = {policy.cfg.K}, U-Net down_dims {policy.cfg.down_dims}\n")
    print("| stage | work | wall s | CPU s |")
    print("|---|---|---|---|")
    for name, work, wall, cpu in rows:
        print(f"| {name} | {work} | {wall:.2f} | {cpu:.2f} |")
    print("\n" + calib.report())


if __name__ == "__main__":
    main()
