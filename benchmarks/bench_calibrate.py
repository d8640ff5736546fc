"""Speed of one policy calibration (calibrate.py) on the PlanarReacher, stage by stage.

dagger.py calls calibrate() once per round on the round's intervention data. This script times its
stages on RRT-oracle demonstrations (cut into "interventions": each demo keeps expert labels on one
window of --segment steps, the rest marked policy-driven), with a diffusion policy trained briefly
on the demos (or loaded with --policy):

  open-loop Sigma_hat (Eq. 1)      every other label step, n_samples chunks each, batched sampling
  blend rollouts (13 betas)        closed loop with partial denoising, one call per decision
  calibrate()                      all of the above + the fit and Eqs. (13)-(16)

Usage:  python benchmarks/bench_calibrate.py [--demos 12] [--train-steps 1000] [--policy PATH]
                                             [--threads N] [--segment 48]
Prints a markdown table (wall and CPU seconds).

How steady W is:  python benchmarks/bench_calibrate.py --run runs/quick --seeds 5 [--lineage 0] [--round 1]
                                                       [--betas 0.1,0.2,0.3,0.5,0.75,0.9]
calibrates the round's HG-DAgger policy on the interventions of rounds 1..k of a finished run folder, with
the run's own calibration settings (dagger.calibration_config), once per calibration seed (seed 0 is the
run's own), and ends with one line: W spread: mean M, SD S, SD/mean P %, T s per calibration (M and S in
the paper's median steps). Numbers depend on machine load (the team shares 2
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
from envs import make_env, median_step  # noqa: E402
from experiment import checkpoints, environments, profiles  # noqa: E402


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
    parser.add_argument("--run", default="", help="a finished run folder: measure how steady its W is")
    parser.add_argument("--seeds", type=int, default=5, help="--run: calibration seeds (the first is the run's)")
    parser.add_argument("--lineage", type=int, default=0, help="--run: the lineage")
    parser.add_argument("--round", type=int, default=1, help="--run: the round k (its HG-DAgger policy, D_1..D_k)")
    parser.add_argument("--betas", default=None, metavar="B1,B2,...",
                        help="--run: the blend ratios instead of calibrate's 13 (e.g. the authors' lever set "
                             "0.1,0.2,0.3,0.5,0.75,0.9)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.run:
        return w_spread(args.run, args.seeds, args.lineage, args.round, parse_betas(args.betas))

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
        policy = checkpoints.load_policy(args.policy)
    else:
        policy = DiffusionPolicy(PolicyConfig(obs_dim=env.obs_dim, dof=env.dof, horizon=16, n_act=8, K=100,
                                                  down_dims=(32, 64, 128)))
        train(policy, *chunk_dataset(demos, policy.cfg.horizon),
              TrainConfig(steps=args.train_steps, warmup_steps=100, log_every=0))

    # interventions: one expert window of --segment steps per demo, starting a few steps in
    interventions = []
    for ep in demos:
        expert_mask = np.zeros(len(ep["q"]), dtype=bool)
        expert_mask[5:5 + args.segment] = True
        interventions.append(dict(ep, expert=expert_mask))
    n_steps = sum(int(e["expert"].sum()) for e in interventions)

    cfg = cal.CalibrationConfig(n_act=10)  # dagger.Config.n_act
    threshold = cal.diverge_radius(cfg.diverge_threshold, unit, env.paper_median_step)  # as calibrate does
    gen = torch.Generator().manual_seed(0)
    H = policy.cfg.horizon
    blend_beta, chosen = cal.blend_schedule(interventions, H, cfg)  # as calibrate starts them
    rows = []
    steps, w, c = timed(lambda: cal.open_loop_sigma(policy, interventions, cfg.stride, cfg.n_samples, gen,
                                                    n_act=cfg.n_act))
    rows.append(("open-loop Sigma_hat (Eq. 1)", f"{len(steps.timestep)} steps x {cfg.n_samples} samples", w, c))
    blend, w, c = timed(lambda: cal.blend_rollouts(env, policy, [(interventions[e], s) for e, s in chosen],
                                                   blend_beta, cfg, gen, threshold))
    rows.append(("blend rollouts", f"13 betas x {len(chosen) // 13} segments, "
                 f"{int(blend.rollouts.n_recorded.sum())} env steps, "
                 f"{int(blend.kept.sum())} kept", w, c))
    calib, w, c = timed(lambda: cal.calibrate(env, policy, interventions, unit, cfg, gen))
    rows.append(("calibrate() total", f"{len(interventions)} interventions, {n_steps} expert steps", w, c))

    print(f"\ntorch threads: {torch.get_num_threads()}, policy K = {policy.cfg.K}, U-Net down_dims {policy.cfg.down_dims}\n")
    print("| stage | work | wall s | CPU s |")
    print("|---|---|---|---|")
    for name, work, wall, cpu in rows:
        print(f"| {name} | {work} | {wall:.2f} | {cpu:.2f} |")
    print("\n" + calib.report())


def parse_betas(text):
    """--betas '0.1,0.2,...' as a tuple of ratios in (0, 1), at least 3 distinct (the fit has 2 parameters);
    None stays None (calibrate's own 13)."""
    if text is None:
        return None
    try:
        betas = tuple(float(b) for b in text.split(","))
    except ValueError:
        raise SystemExit(f"--betas {text!r}: give comma-separated numbers, e.g. 0.1,0.2,0.3,0.5,0.75,0.9") from None
    if len(set(betas)) < 3 or not all(0 < b < 1 for b in betas):
        raise SystemExit(f"--betas {text!r}: give at least 3 distinct blend ratios, each in (0, 1)")
    return betas


def w_spread(root, n_seeds, lineage, k, betas=None):
    """W of one round recalibrated with n_seeds calibration seeds: a table per seed and the spread line.
    betas: other blend ratios than calibrate's (the authors' six on the lever), or None."""
    import dataclasses
    import dagger
    from dagger import stage_seed
    from experiment.run_folder import Run, read_json, without_retired_fields
    if n_seeds < 2:
        raise SystemExit(f"--seeds {n_seeds}: a spread needs at least 2 seeds")
    saved = read_json(os.path.join(root, "config.json"))
    known = {f.name for f in dataclasses.fields(dagger.Config)}
    # fields deleted since the folder was made: checked to hold the value that remains, dropped
    saved = without_retired_fields(os.path.join(root, "config.json"), saved)
    cfg = dagger.Config(**{key: value for key, value in saved.items() if key in known})
    run = Run(root, cfg)  # reads the folder's stages; the settings below change only this measurement
    profile = profiles.PROFILES.get(cfg.name)
    if profile is not None:  # today's calibration settings of the run's profile (the folder may predate them)
        cfg = dataclasses.replace(cfg, **{f: getattr(profile, f) for f in known if f.startswith("calib_")})
    where = f"lineage_{lineage}/round_{k}"
    if not os.path.exists(os.path.join(root, where, "checkpoints", "hg_dagger.pt")):
        raise SystemExit(f"{root}: {where}/checkpoints/hg_dagger.pt is not there; finish that round first")
    policy = run.load(f"{where}/checkpoints/hg_dagger.pt")
    episodes = [ep for j in range(1, k + 1) for ep in run.load(f"lineage_{lineage}/round_{j}/D.npz")]
    demos = run.load("data/D0.npz")
    stats = dagger.demo_statistics(cfg, demos, environments.make_env)
    ccfg = dagger.calibration_config(cfg)
    if betas is not None:
        ccfg = dataclasses.replace(ccfg, betas=betas)
    paper = environments.paper_median_step(cfg.env) or stats.median_step
    seeds = [stage_seed(cfg, "calibrate", lineage, k)] + list(range(1, n_seeds))
    print(f"{root}, {where}: {len(episodes)} intervention episodes, unit {paper:.4f} rad (paper median step); "
          f"calibration settings of {'the ' + cfg.name + ' profile' if profile else 'the run folder'}: {ccfg}")
    print("| calibration seed | W (paper steps) | 95 % interval | rollouts kept | ratios fitted | fit | wall s |")
    print("|---|---|---|---|---|---|---|")
    Ws, walls = [], []
    for seed in seeds:
        gen = torch.Generator(device=policy.device).manual_seed(seed)
        c, wall, _ = timed(lambda: cal.calibrate(environments.make_env(cfg.env), policy, episodes, stats.median_step,
                                                 ccfg, gen))
        Ws.append(c.W / paper)
        walls.append(wall)
        ci = "–" if c.W_ci is None else f"{c.W_ci[0] / paper:.2f}–{c.W_ci[1] / paper:.2f}"
        cells = cal.ratio_cells(c.blend_beta, c.blend_s, c.blend_x, c.blend_kept, ccfg.min_survivors)
        print(f"| {seed} | {c.W / paper:.2f} | {ci} | {int(c.blend_kept.sum())}/{len(c.blend_kept)} | "
              f"{int(cells.fitted.sum())}/{len(cells.s)} | {c.fit_note} | {wall:.1f} |")
    m, sd = float(np.mean(Ws)), float(np.std(Ws, ddof=1))
    print(f"\nW spread: mean {m:.2f}, SD {sd:.2f}, SD/mean {100 * sd / m:.0f} %, {np.mean(walls):.1f} s per calibration")


if __name__ == "__main__":
    main()
