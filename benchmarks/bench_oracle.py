"""Benchmark of the RRT oracle expert on the planar env's 100 evaluation scenarios.

For every scenario: Oracle.demonstrate (plan + execute with env.step). Reports
  expert success (target >= 98 %), median planning time, median demo length (steps),
  demos per minute on this machine (wall clock of plan + execution, single process),
  time_parameterize duration / lower bound, where the lower bounds are
    path bound:  the slowest joint's bang-bang (trapezoid) time over its total travel along the
                 executed samples (min_time_lower_bound(plan.samples); Plan keeps no path since 6caf654);
    line bound:  the same over the straight joint-space line start -> chosen goal configuration
                 (no path from start to that configuration can be faster),
    traversal:   the full-speed time of the executed samples' polyline (each piece at its dominant
                 joint's v_max) plus v_max / a_max: the cost of the time parameterization itself,
  and checks the velocity / acceleration / jerk limits at every sample of every plan.
Failures are listed with their seed and reason.
Interventions (--n-interventions scenarios): the state 30 % into the demo is perturbed by a random
joint offset and a random velocity (a policy drifting off the expert's path); Oracle.intervention
plans from there. Reports its planning time, how often the handoff velocity was matched, the
number of steps driven, and whether executing them collided.

--compare REV: a before/after table instead. oracle.py as of git revision REV ("before", imported
from `git show`) and the working tree's ("after") demonstrate the same scenes, one after the other
per scene (so both see the same machine load): the first --n planar and --n-3d engine3d eval
scenes. Per oracle: successes, planning time (median / 90th percentile), configurations passed to
env.in_collision per plan (and calls), demo length, and two checks of every executed demo: the
visited states resampled so that no arm point moves more than 1 mm between samples, under
env.in_collision (margin 0), and the simulator's own contact check inside env.step.

Usage:  python benchmarks/bench_oracle.py [--n 100] [--seeds eval|train] [--n-interventions 20]
        python benchmarks/bench_oracle.py --compare 566a67c --n 30 --n-3d 8
"""
import argparse
import importlib.util
import os
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)
import oracle  # noqa: E402
from experiment.environments import make_env  # noqa: E402
from oracle import Oracle, PlanningFailed  # noqa: E402



def record_plans(expert):
    """Wrap expert.plan: returns a list that gets (Plan, planning seconds) of every plan it makes."""
    plans, plan = [], expert.plan

    def timed_plan(*args, **kwargs):
        t0 = time.perf_counter()
        result = plan(*args, **kwargs)
        plans.append((result, time.perf_counter() - t0))
        return result

    expert.plan = timed_plan
    return plans


def min_time_lower_bound(path, v_max, a_max):
    """Lower bound (s) on any rest-to-rest traversal of `path` (N, dof): the slowest joint's bang-bang time.

    Joint j travels at least its total variation D_j along the path with |v| <= v_max_j, |a| <= a_max_j: at
    least the trapezoid time D/v + v/a (or 2 sqrt(D/a) if it never reaches v_max). Jerk limits only add."""
    travel = np.sum(np.abs(np.diff(np.atleast_2d(path), axis=0)), axis=0)  # (dof,)
    cruise = travel >= v_max ** 2 / a_max
    return float(np.where(cruise, travel / v_max + v_max / a_max, 2 * np.sqrt(travel / a_max)).max())


def traversal_time(path, v_max, a_max):
    """Full-speed traversal of the polyline (each piece at its dominant joint's v_max) + v/a."""
    return float(np.sum(np.max(np.abs(np.diff(path, axis=0)) / v_max, axis=1))
                 + np.max(v_max / a_max))


def limit_ratios(samples, v_max, a_max, j_max, dt):
    """Largest |v| / v_max, |a| / a_max, |jerk| / j_max over all samples (start and end at rest)."""
    vel = np.diff(samples, axis=0, prepend=samples[:1], append=samples[-1:]) / dt
    vel = np.concatenate([np.zeros((1, samples.shape[1])), vel])
    acc = np.diff(vel, axis=0) / dt
    jerk = np.diff(acc, axis=0) / dt
    return (np.abs(vel) / v_max).max(), (np.abs(acc) / a_max).max(), (np.abs(jerk) / j_max).max()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=100, help="number of scenarios")
    parser.add_argument("--seeds", choices=["eval", "train"], default="eval")
    parser.add_argument("--n-interventions", type=int, default=20)
    parser.add_argument("--compare", metavar="REV", default=None,
                        help="before/after table: oracle.py at git revision REV vs working tree")
    parser.add_argument("--n-3d", type=int, default=8, help="engine3d eval scenes for --compare")
    args = parser.parse_args()
    if args.compare:
        compare(args.compare, args.n, args.n_3d)
        return
    env = make_env("planar")
    oracle = Oracle()
    plans = record_plans(oracle)
    v_max, a_max, j_max = oracle.limits(env)
    seeds = env.eval_seeds()[: args.n] if args.seeds == "eval" else env.train_seeds(args.n)
    rows, failures = [], []
    t_start = time.perf_counter()
    for i, seed in enumerate(seeds):
        t0 = time.perf_counter()
        try:
            episode = oracle.demonstrate(env, seed)
        except PlanningFailed as e:
            failures.append((seed, f"planning failed: {e.reason}"))
            print(f"[{i + 1}/{len(seeds)}] seed {seed}: PLANNING FAILED ({e.reason})", flush=True)
            continue
        wall = time.perf_counter() - t0
        plan, plan_time = plans[-1]
        duration = (len(plan.samples) - 1) * env.dt
        rows.append(dict(
            seed=seed, success=episode["success"], steps=len(episode["q"]), wall=wall,
            plan_time=plan_time, duration=duration,
            path_ratio=duration / min_time_lower_bound(plan.samples, v_max, a_max),
            line_ratio=duration / min_time_lower_bound(plan.samples[[0, -1]], v_max, a_max),
            traversal_ratio=duration / traversal_time(plan.samples, v_max, a_max),
            limits=max(limit_ratios(plan.samples, v_max, a_max, j_max, env.dt))))
        if not episode["success"]:
            failures.append((seed, f"execution failed after {len(episode['q'])} steps "
                                   f"(collision or truncation at max_steps={env.max_steps})"))
        elapsed = time.perf_counter() - t_start
        print(f"[{i + 1}/{len(seeds)}] seed {seed}: success {episode['success']}, "
              f"{len(episode['q'])} steps, plan {plan_time:.2f} s, "
              f"T/bound {rows[-1]['path_ratio']:.2f}, {elapsed:.0f} s elapsed, "
              f"~{elapsed / (i + 1) * (len(seeds) - i - 1):.0f} s left", flush=True)
    total = time.perf_counter() - t_start
    col = lambda k: np.array([r[k] for r in rows])  # noqa: E731
    n_success = int(col("success").sum()) if rows else 0
    print(f"\nscenarios: {len(seeds)} ({args.seeds} seeds), {total:.0f} s total")
    print("| measure | value |\n|---|---|")
    print(f"| expert success | {n_success}/{len(seeds)} = {100 * n_success / len(seeds):.1f} % |")
    if rows:
        print(f"| planning time, s (median / 90th pct / max) | {np.median(col('plan_time')):.2f} / "
              f"{np.percentile(col('plan_time'), 90):.2f} / {col('plan_time').max():.2f} |")
        print(f"| demo length, steps (median / 90th pct / max) | {np.median(col('steps')):.0f} / "
              f"{np.percentile(col('steps'), 90):.0f} / {col('steps').max()} |")
        print(f"| demos per minute (plan + execute, 1 process) | {60 * n_success / total:.1f} |")
        print(f"| duration / path bound (median / max) | {np.median(col('path_ratio')):.2f} / "
              f"{col('path_ratio').max():.2f} |")
        print(f"| duration / straight-line bound (median / max) | {np.median(col('line_ratio')):.2f}"
              f" / {col('line_ratio').max():.2f} |")
        print(f"| duration / full-speed traversal of the path (median / max) | "
              f"{np.median(col('traversal_ratio')):.2f} / {col('traversal_ratio').max():.2f} |")
        print(f"| max limit use over all samples (|v|/v_max, |a|/a_max, |j|/j_max) | "
              f"{col('limits').max():.6f} |")
    for seed, reason in failures:
        print(f"failure: seed {seed}: {reason}")
    if args.n_interventions:
        bench_interventions(env, oracle, plans, [r["seed"] for r in rows][: args.n_interventions])


def bench_interventions(env, oracle, plans, seeds):
    rng = np.random.default_rng(0)
    times, matched, lengths, collided, failed = [], [], [], 0, []
    for seed in seeds:
        demo = oracle.demonstrate(env, seed)
        t = int(0.3 * len(demo["q"]))
        lo, hi = env.joint_limits
        q = np.clip(demo["q"][t] + rng.normal(0, 4 * env.max_step, env.dof), lo, hi)
        q_prev = q - rng.uniform(-env.max_step, env.max_step, env.dof)
        if env.in_collision(np.stack([q, q_prev])).any():
            continue
        env.set_state(q, q_prev)
        t0 = time.perf_counter()
        try:
            actions = oracle.intervention(env)
        except PlanningFailed as e:
            failed.append((seed, e.reason))
            continue
        times.append(time.perf_counter() - t0)
        matched.append(plans[-1][0].velocity_matched)
        lengths.append(len(actions))
        for a in actions:
            _, _, terminated, _, info = env.step(a)
            collided += info["collision"]
            if terminated:
                break
    print(f"\ninterventions: {len(times)} from perturbed mid-demo states")
    print("| measure | value |\n|---|---|")
    if times:
        print(f"| planning time, s (median / max) | {np.median(times):.2f} / {max(times):.2f} |")
        print(f"| handoff velocity matched | {np.mean(matched):.2f} |")
        print(f"| steps driven (median / min / max) | {np.median(lengths):.0f} / {min(lengths)} / "
              f"{max(lengths)} |")
    print(f"| executions that collided | {collided} |")
    print(f"| planning failures | {len(failed)} {failed} |")


# ----------------------------------------------------------------------------------------------
# --compare: before/after table
# ----------------------------------------------------------------------------------------------
def load_oracle_at(rev):
    """oracle.py as of git revision `rev`, imported as a module of its own (the "before")."""
    source = subprocess.run(["git", "-C", ROOT, "show", f"{rev}:oracle.py"], check=True,
                            capture_output=True, text=True).stdout
    name = f"oracle_at_{rev}"
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(name, loader=None))
    sys.modules[name] = module  # dataclasses look their module up here
    exec(compile(source, f"{rev}:oracle.py", "exec"), module.__dict__)
    return module


def count_planning_checks(env, oracle_):
    """Counts {'configs', 'calls'} of env.in_collision while oracle_.plan runs (instance wrappers
    around both, so scene generation in env.reset is not counted)."""
    counts, planning = {"configs": 0, "calls": 0}, [False]
    env_check, plan = env.in_collision, oracle_.plan

    def in_collision(q, margin=0.0):
        if planning[0]:
            counts["configs"] += len(np.atleast_2d(q))
            counts["calls"] += 1
        return env_check(q, margin=margin)

    def counted_plan(*args, **kwargs):
        planning[0] = True
        try:
            return plan(*args, **kwargs)
        finally:
            planning[0] = False

    env.in_collision, oracle_.plan = in_collision, counted_plan
    return counts


def record_step_collisions(env):
    """Wrap env.step: returns a list that gets info['collision'] of every step."""
    collisions, step = [], env.step

    def recorded_step(action):
        out = step(action)
        collisions.append(out[-1]["collision"])
        return out

    env.step = recorded_step
    return collisions


def dense_collides(env, states, spacing=0.001):
    """env.in_collision (margin 0) on the polyline `states` resampled so that no arm point moves
    more than `spacing` m between samples (lever-arm bound, oracle.lever_arms)."""
    step = np.abs(np.diff(states, axis=0)) @ oracle.lever_arms(env)  # (T - 1,) m
    n = np.maximum(1, np.ceil(step / spacing)).astype(int)
    dense = np.concatenate([states[:1]] + [states[t] + np.arange(1, k + 1)[:, None] / k
                                           * (states[t + 1] - states[t]) for t, k in enumerate(n)])
    return bool(env.in_collision(dense).any())


def compare(rev, n_planar, n_3d):
    before = load_oracle_at(rev)
    oracles = {f"before ({rev})": before, "after (working tree)": oracle}
    print(f"{'scene':>14} | " + " | ".join(f"{k}: ok, plan s, checks" for k in oracles), flush=True)
    table = []
    for env_name, n in (("planar", n_planar), ("engine3d", n_3d)):
        if n == 0:
            continue
        env = make_env(env_name)
        step_collisions = record_step_collisions(env)
        rows = {k: [] for k in oracles}
        for seed in env.eval_seeds()[:n]:
            cells = []
            for label, module in oracles.items():
                # the compared commit's own oracle, at its defaults
                expert = module.Oracle(module.OracleConfig())
                plans = record_plans(expert)
                counts = count_planning_checks(env, expert)
                del step_collisions[:]
                try:
                    episode = expert.demonstrate(env, seed)
                except module.PlanningFailed:
                    rows[label].append(dict(success=False, planned=False))
                    cells.append("PLANNING FAILED")
                    continue
                visited = np.concatenate([episode["q"], episode["action"][-1:]])
                rows[label].append(dict(
                    success=episode["success"], planned=True,
                    time=plans[-1][1], steps=len(episode["q"]),
                    configs=counts["configs"], calls=counts["calls"],
                    dense=dense_collides(env, visited), simulator=any(step_collisions)))
                r = rows[label][-1]
                cells.append(f"{r['success']!s:5} {r['time']:6.2f} {r['configs']:8d}")
            print(f"{env_name:>8} {seed:5d} | " + " | ".join(cells), flush=True)
        for label in oracles:
            table.append((env_name, n, label, rows[label]))
    print(f"\n| env (scenes) | oracle | success | planning s, median / p90 | in_collision configs "
          f"per plan, median (calls) | demo steps, median | executed demos colliding: dense "
          f"re-check / simulator |\n|---|---|---|---|---|---|---|")
    for env_name, n, label, rows in table:
        ok = [r for r in rows if r["planned"]]
        col = lambda k: np.array([r[k] for r in ok])  # noqa: E731
        if not ok:
            print(f"| {env_name} ({n}) | {label} | 0/{n} | - | - | - | - |")
            continue
        print(f"| {env_name} ({n}) | {label} | {int(col('success').sum())}/{n} | "
              f"{np.median(col('time')):.2f} / {np.percentile(col('time'), 90):.2f} | "
              f"{np.median(col('configs')):,.0f} ({np.median(col('calls')):.0f}) | "
              f"{np.median(col('steps')):.0f} | {int(col('dense').sum())} / "
              f"{int(col('simulator').sum())} |")


if __name__ == "__main__":
    main()
