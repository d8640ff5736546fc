"""Speed and difficulty of EngineReach3D (the UR5 engine-lever env, paper Sec. V / Table II).

Measures, over the evaluation scenes:
  * collision checks per second: vectorized numpy `in_collision` by batch size vs pybullet
    contacts (the simulator, one configuration at a time); fk; env.step (pybullet, 4 substeps);
    reset (scene generation with IK checks); a 64x64 TinyRenderer image;
  * difficulty: the fraction of scenes where the straight joint-space line from the start to
    EVERY collision-free goal configuration (env.goal_configurations, closed-form IK) collides;
  * the oracle (oracle.py): expert success, planning CPU time and demo length over the scenes.

Usage:  python benchmarks/bench_engine3d.py [--seconds 1.0] [--scenes 100] [--no-oracle] [--max-time S]
                                           [--no-speed]
Rates are given per wall-clock second and per CPU second of this process (what one core delivers
when other jobs share the machine).
"""
import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_envs import rate  # noqa: E402
from experiment.environments import make_env  # noqa: E402


def speed_rows(env, seconds, n_scenes, rng):
    lo, hi = env.joint_limits
    seeds = env.eval_seeds()[:n_scenes]
    rows = []
    for batch in (1, 100, 1000, 10_000):
        rates, frac = [], []
        for seed in seeds:
            env.reset(seed=seed)
            q = rng.uniform(lo, hi, size=(batch, env.dof))
            rates.append(rate(lambda: env.in_collision(q), batch, seconds / len(seeds)))
            frac.append(env.in_collision(q).mean())
        rows.append((f"numpy in_collision, batch {batch}", tuple(np.mean(rates, axis=0)), "checks/s",
                     f"{np.mean(frac):.0%} of random configs collide"))
    env.reset(seed=seeds[0])
    q = rng.uniform(lo, hi, size=(1000, env.dof))
    rows.append(("numpy in_collision, margin 0.01 m, batch 1000",
                 rate(lambda: env.in_collision(q, margin=0.01), 1000, seconds), "checks/s", ""))
    q_small = q[:200]
    rows.append(("pybullet contacts, one config at a time",
                 rate(lambda: env.pybullet_in_collision(q_small), 200, seconds), "checks/s", ""))
    rows.append(("fk, batch 1000", rate(lambda: env.fk(q), 1000, seconds), "configs/s", ""))
    rows.append(("goal_configurations (192 orientations x 8 IK branches)",
                 rate(lambda: env.goal_configurations(), 1, seconds), "calls/s", ""))
    seed_iter = iter(range(10**9))
    rows.append(("reset (scene generation)", rate(lambda: env.reset(seed=next(seed_iter)), 1, seconds),
                 "resets/s", ""))
    env.reset(seed=seeds[0])
    start = env.q

    def wiggle():
        if env.step_count >= env.max_steps - 1:
            env.set_state(start)
        env.step(env.q + 0.01 * np.sin(env.step_count + np.arange(env.dof)))
    rows.append(("env.step (pybullet, 4 substeps)", rate(wiggle, 1, seconds), "steps/s", ""))
    for size in (32, 64):
        rows.append((f"camera_image {size}x{size} (TinyRenderer)",
                     rate(lambda: env.camera_image(start, size, size), 1, seconds), "images/s",
                     "engine3d_image's observation (32: its image_size's default)" if size == 32 else ""))
    rows.append(("memory per env (its pybullet client)", [memory_per_env(20)], "MB",
                 "why dagger.evaluate runs UR5 episodes in groups of 100"))
    return rows


def memory_per_env(n, **config):
    """Resident memory added per EngineReach3D (reset to a scene), from /proc over n envs."""
    def rss_mb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    before = rss_mb()
    envs_ = [make_env("engine3d", **config) for _ in range(n)]
    for i, e in enumerate(envs_):
        e.reset(seed=10_000 + i)
    per_env = (rss_mb() - before) / n
    for e in envs_:
        e.close()
    return per_env


def straight_line_collides(env, resolution):
    """True if the straight joint-space line from env.q to every free goal configuration collides."""
    goals = env.goal_configurations()
    for goal in goals:
        n = int(np.ceil(np.max(np.abs(goal - env.q) / resolution))) + 1
        line = env.q + np.linspace(0.0, 1.0, n)[:, None] * (goal - env.q)
        if not env.in_collision(line).any():
            return False
    return True


def oracle_rows(env, n_scenes, max_time=None):
    import oracle

    orc = oracle.Oracle() if max_time is None else oracle.Oracle(oracle.OracleConfig(max_time=max_time))
    succ, cpu, length, straight, reasons, start_goal = [], [], [], [], [], []
    t_start = time.perf_counter()
    for k, seed in enumerate(env.eval_seeds()[:n_scenes]):
        env.reset(seed=seed)
        start_goal.append(float(np.linalg.norm(env.ee(env.q) - env.goal)))
        straight.append(straight_line_collides(env, resolution=0.005))
        c0 = time.process_time()
        try:
            episode = orc.demonstrate(env, seed)
            succ.append(episode["success"])
            length.append(len(episode["q"]))
        except oracle.PlanningFailed as e:
            succ.append(False)
            reasons.append(f"seed {seed}: {e.reason[:80]}")
        cpu.append(time.process_time() - c0)
        done = k + 1
        eta = (time.perf_counter() - t_start) / done * (n_scenes - done)
        print(f"scene {done}/{n_scenes} (seed {seed}): success {succ[-1]}, plan+demo cpu {cpu[-1]:.1f} s, "
              f"straight line collides {straight[-1]}; success so far {np.mean(succ):.0%}, "
              f"eta {eta / 60:.1f} min", flush=True)
    rows = [(f"oracle expert success over {n_scenes} eval scenes", (np.mean(succ),), "fraction", ""),
            ("straight start-goal line collides (every goal config)", (np.mean(straight),), "fraction", ""),
            ("oracle demonstrate CPU time, median / 90th pct / max",
             (np.median(cpu), np.percentile(cpu, 90), np.max(cpu)), "s", ""),
            ("demo length, median / 90th pct / max",
             tuple(np.percentile(length, [50, 90, 100])) if length else (np.nan,), "steps", ""),
            ("start TCP to goal, median / min / max",
             (np.median(start_goal), np.min(start_goal), np.max(start_goal)), "m", "")]
    return rows, reasons


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=1.0, help="time per speed measurement")
    parser.add_argument("--scenes", type=int, default=100, help="eval scenes for the oracle run")
    parser.add_argument("--no-oracle", action="store_true", help="speed measurements only")
    parser.add_argument("--max-time", type=float, default=None,
                        help="OracleConfig.max_time (s per RRT attempt); default: the oracle's own")
    parser.add_argument("--no-speed", action="store_true", help="skip the speed measurements")
    args = parser.parse_args()
    env = make_env("engine3d")
    rng = np.random.default_rng(0)
    rows = [] if args.no_speed else speed_rows(env, args.seconds, 3, rng)
    reasons = []
    if not args.no_oracle:
        more, reasons = oracle_rows(env, args.scenes, args.max_time)
        rows += more
    print("\n| measurement | value(s) | unit | note |\n|---|---|---|---|")
    for name, values, unit, note in rows:
        text = " / ".join(f"{v:,.3g}" if isinstance(v, float) else str(v) for v in values)
        if unit.endswith("/s"):
            text = f"{values[0]:,.0f} wall, {values[1]:,.0f} CPU"
        print(f"| {name} | {text} | {unit} | {note} |")
    for r in reasons:
        print("failed:", r)


if __name__ == "__main__":
    main()
