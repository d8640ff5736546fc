"""Speed of the corrective-label augmentation (relabel.py) on the PlanarReacher.

The target set when the sampler was written: the AugmentationSampler runs inside every training step
(batch 256, about half augmented), so a call for 128 pairs should cost under ~1-2 ms amortized, next to a
training step of a few ms. Measured here: the fresh-pair generation rate of each stage and of the whole pipeline,
and the amortized / median / worst time of sampler calls of 128 pairs (pool refreshes included).

The intervention episodes are stand-ins that need no oracle: straight joint-space paths from a
scenario's start toward its nearest goal configuration, stopped before the first collision, timed
with a smoothstep, with the "intervention" covering all but the first 5 steps.

A second table measures label quality on RRT-oracle demonstrations (which move at the speed limit):
how close the chunks come back to the expert path, for both labels (the paper's PD, every profile's, and the
authors' servo of experiment/servo.py).

Usage:  python benchmarks/bench_relabel.py [--calls 400] [--episodes 24] [--oracle-demos 8]
Prints a markdown table. Numbers depend on machine load (the team shares 2 cores); the CPU-time
row (time.process_time) is the least sensitive to other processes.
"""
import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
import relabel  # noqa: E402
from envs import PAPER_FRAME_DT, make_env, median_step  # noqa: E402
from experiment import servo  # noqa: E402
from helpers import straight_line_episode  # noqa: E402 (tests/helpers.py)

H = 16  # steps: the label chunk's length measured here


def straight_episode(env, seed, min_len=40):
    """tests/helpers.py straight_line_episode, or None when shorter than min_len steps."""
    ep = straight_line_episode(env, seed)
    return ep if len(ep["q"]) >= min_len else None


def per_second(fn, items, seconds=1.0):
    fn()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        fn()
        n += items
    return n / (time.perf_counter() - t0)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--calls", type=int, default=400, help="sampler calls timed per noise model")
    parser.add_argument("--episodes", type=int, default=24, help="intervention episodes")
    parser.add_argument("--oracle-demos", type=int, default=8,
                        help="oracle demonstrations for the label-quality table (0 = skip; ~4 s each)")
    args = parser.parse_args()
    env = make_env("planar")
    episodes, seed = [], 0
    while len(episodes) < args.episodes:
        ep = straight_episode(env, seed)
        seed += 1
        if ep is not None:
            episodes.append(ep)
    stats = relabel.demo_stats(episodes, median_step(episodes), env.max_step)
    cfg = relabel.RelabelConfig(horizon=H)
    unit = stats.median_step
    pooled = np.diag([4.0, 5.0, 4.5]) ** 2 * unit ** 2
    per_step = {e: (np.arange(0, len(ep["q"]), 2), np.broadcast_to(pooled, (len(range(0, len(ep["q"]), 2)), 3, 3)))
                for e, ep in enumerate(episodes)}
    n_steps = sum(len(relabel.paper_label_steps(ep["expert"], cfg.horizon)[0]) for ep in episodes)
    print(f"{len(episodes)} intervention episodes, {n_steps} labelable steps, median step {unit:.4f} rad, "
          f"accel clamp {np.round(stats.accel_max, 4)} rad/step²\n")

    rows = []
    # stages, for 512 states of one scenario (the unit of work of a refresh draw is ~32 states)
    rng = np.random.default_rng(0)
    ep = episodes[0]
    env.reset(seed=ep["seed"])
    t_valid, seg_end = relabel.paper_label_steps(ep["expert"], cfg.horizon)
    pick = rng.integers(len(t_valid), size=512)
    t, t_end = t_valid[pick], seg_end[pick]
    factors = relabel.noise_factors(pooled, t, 3)
    q_tilde = ep["q"][t] + np.einsum("mij,mj->mi", factors, rng.standard_normal((512, 3)))
    v = ep["q"][t] - ep["q"][t - 1]
    rows.append(("in_collision, 32 states (one draw)", per_second(lambda: env.in_collision(q_tilde[:32]), 32), "states/s"))
    rows.append(("in_collision, 512 states", per_second(lambda: env.in_collision(q_tilde), 512), "states/s"))
    rows.append(("make_obs, 512 states", per_second(lambda: env.make_obs(q_tilde, q_tilde - v), 512), "states/s"))
    rows.append(("monotone_projection, 512", per_second(
        lambda: relabel.monotone_projection(q_tilde, ep["q"], t, window=cfg.projection_window, t_end=t_end), 512), "states/s"))
    proj = relabel.monotone_projection(q_tilde, ep["q"], t, window=cfg.projection_window, t_end=t_end)
    rows.append((f"pd_return_chunk, 512 x H={H}", per_second(
        lambda: relabel.pd_return_chunk(q_tilde, v, ep["q"], proj, H, 0, stats.accel_max, stats.max_step, t_end=t_end), 512),
        "chunks/s"))
    step, acc = servo.segment_geometry(ep["q"])
    knobs = servo.servo_knobs(np.full(512, step), env.dt / PAPER_FRAME_DT)
    rows.append((f"servo.servo_return_chunk, 512 x H={H}", per_second(
        lambda: servo.servo_return_chunk(q_tilde, v, ep["q"], ep["q"], proj, acc, knobs, H, stats.max_step,
                                         t_end=t_end), 512), "chunks/s"))

    for noise, sigma in (("isotropic", 4.0), ("pooled", pooled), ("per_step", per_step)):
        sampler = relabel.AugmentationSampler(episodes, lambda: make_env("planar"), stats, noise, sigma, cfg)
        rng = np.random.default_rng(1)
        t0 = time.perf_counter()
        sampler(128, rng)  # first call: creates one env per scenario and fills the pool
        first = time.perf_counter() - t0
        rows.append((f"[{noise}] first call (envs + pool of {cfg.pool_size})", first * 1e3, "ms"))
        rows.append((f"[{noise}] generate {cfg.refresh_size} fresh pairs",
                     per_second(lambda: sampler.generate(cfg.refresh_size, rng), cfg.refresh_size), "pairs/s"))
        times = np.empty(args.calls)
        cpu0 = time.process_time()
        for i in range(args.calls):
            t0 = time.perf_counter()
            sampler(128, rng)
            times[i] = time.perf_counter() - t0
        cpu = (time.process_time() - cpu0) / args.calls
        rows.append((f"[{noise}] sampler(128): amortized over {args.calls} calls, wall", times.mean() * 1e3, "ms/call"))
        rows.append((f"[{noise}] sampler(128): amortized, CPU time of this process", cpu * 1e3, "ms/call"))
        rows.append((f"[{noise}] sampler(128): median call / refresh call (max)",
                     f"{np.median(times) * 1e3:.3f} / {times.max() * 1e3:.2f}", "ms"))
        rows.append((f"[{noise}] acceptance (collision-free within limits, 1st try or after redraws)",
                     sampler.n_kept / sampler.n_drawn, "kept/drawn"))
        rows.append((f"[{noise}] fresh pairs per call of 128 (reuse {cfg.reuse:g})", 128 / cfg.reuse, "pairs/call"))

    print("| measurement | value | unit |\n|---|---:|---|")
    for name, value, unit_name in rows:
        text = value if isinstance(value, str) else (f"{value:,.0f}" if value >= 100 else f"{value:.3f}")
        print(f"| {name} | {text} | {unit_name} |")
    if args.oracle_demos > 0:
        label_quality(env, args.oracle_demos)


def label_quality(env, n_demos):
    """How close the labels come back to the expert path, on RRT-oracle demonstrations (they move at
    the speed limit, unlike the stand-ins above), for both labels (the PD and the authors' servo)."""
    import oracle

    expert, seed = oracle.Oracle(), 0
    demos = []
    t0 = time.perf_counter()
    while len(demos) < n_demos and seed < 10 * n_demos:
        try:
            demos.append(expert.demonstrate(env, seed))
        except oracle.PlanningFailed:
            pass
        seed += 1
    unit = median_step(demos)
    stats = relabel.demo_stats(demos, unit, env.max_step, paper_median_step=env.paper_median_step,
                               frames_per_step=env.dt / PAPER_FRAME_DT)
    print(f"\nLabel quality on {len(demos)} oracle demos ({time.perf_counter() - t0:.0f} s to plan): distance of "
          f"chunk[7] / chunk[15] to the expert segment, in median steps ({unit:.4f} rad), median (90th pct)\n")
    print("| σ (median steps) | start | label | chunk[7] | chunk[15] | mean |a| / clamp |\n|---:|---:|---|---:|---:|---:|")
    table = servo.ServoSampler(demos, lambda: make_env("planar"), stats, "isotropic", 0.0, servo.ServoConfig(H))
    traj = table.trajectory
    rng = np.random.default_rng(0)
    for sigma in (2, 4, 8, 16):
        rows = rng.integers(len(table.center), size=1000)
        q0 = table.center[rows] + rng.normal(size=(1000, env.dof)) * sigma * unit
        v, t, t_end = table.velocity[rows], table.t_glob[rows], table.end_glob[rows]

        def dist(x):  # distance to the nearest point of the expert segment from t on
            return np.array([np.linalg.norm(traj[a:b] - p, axis=1).min() for p, a, b in zip(x, t, t_end)]) / unit

        start = dist(q0)
        for label in ("servo", "pd"):  # the same table's labels: its own servo, or the core's PD
            proj = relabel.monotone_projection(q0, traj, t, window=table.cfg.projection_window, t_end=t_end)
            chunks = (table.return_chunks(rows, q0, v, proj, env.joint_limits)[0] if label == "servo" else
                      relabel.corrective_labels(q0, v, traj, t, t_end, stats, table.cfg, t_proj=proj))
            path = np.concatenate([q0[:, None], chunks], axis=1)
            acc = np.diff(np.concatenate([v[:, None], np.diff(path, axis=1)], axis=1), axis=1)
            mid, end = dist(chunks[:, 7]), dist(chunks[:, -1])
            fmt = lambda d: f"{np.median(d):.2f} ({np.percentile(d, 90):.2f})"
            print(f"| {sigma} | {fmt(start)} | {label} | {fmt(mid)} | {fmt(end)} | {np.mean(np.abs(acc) / stats.accel_max):.2f} |")


if __name__ == "__main__":
    main()
