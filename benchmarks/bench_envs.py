"""Speed of the PlanarReacher: collision checks per second and env steps per second.

The target set when the check was written: >= 1e6 configuration checks/s (obstacles + self-collision)
for batches of ~1000+ on a 2-core machine. pymunk's check of the same predicate is shown for contrast.

Usage:  python benchmarks/bench_envs.py [--seconds 1.0]
Prints a markdown table with rates per wall-clock second and per CPU second of this process (the
latter is what one core delivers when other jobs share the machine; numpy here is single-threaded).
"""
import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from envs import make_env  # noqa: E402


def rate(fn, items_per_call, seconds):
    """Calls fn repeatedly for ~seconds of CPU time; returns (items per wall second, per CPU second).

    The CPU-time rate is what one core delivers even when other jobs share the machine.
    """
    fn()  # warm up
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while time.process_time() - c0 < seconds:
        fn()
        n += items_per_call
    return n / (time.perf_counter() - t0), n / (time.process_time() - c0)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=1.0, help="time per measurement")
    parser.add_argument("--scenes", type=int, default=5, help="evaluation scenes averaged over")
    args = parser.parse_args()
    env = make_env("planar")
    lo, hi = env.joint_limits
    rng = np.random.default_rng(0)
    rows = []
    seeds = env.eval_seeds()[: args.scenes]
    for batch in (1, 100, 1000, 4096, 100_000):
        rates, frac = [], []
        for seed in seeds:
            env.reset(seed=seed)
            q = rng.uniform(lo, hi, size=(batch, env.dof))
            rates.append(rate(lambda: env.in_collision(q), batch, args.seconds / len(seeds)))
            frac.append(env.in_collision(q).mean())
        rows.append((f"numpy in_collision, batch {batch}", tuple(np.mean(rates, axis=0)), "checks/s",
                     f"{np.mean(frac):.0%} of random configs collide"))
    env.reset(seed=seeds[0])
    q = rng.uniform(lo, hi, size=(500, env.dof))
    rows.append(("pymunk shape_query, one config at a time", rate(lambda: env.pymunk_in_collision(q),
                                                              500, args.seconds), "checks/s", ""))
    q = rng.uniform(lo, hi, size=(4096, env.dof))
    rows.append(("fk, batch 4096", rate(lambda: env.fk(q), 4096, args.seconds), "configs/s", ""))

    # env.step: a free scene so episodes do not end at once; the action wiggles joint 0
    env.set_scene(np.zeros((0, 5)), goal=[5.0, 5.0])  # unreachable goal: never terminates
    env.set_state(np.zeros(env.dof))
    targets = np.stack([np.array([0.3, 0.0, 0.0]), np.array([-0.3, 0.0, 0.0])])
    counter = [0]

    def one_step():
        counter[0] += 1
        _, _, terminated, truncated, _ = env.step(targets[(counter[0] // 10) % 2])
        if terminated or truncated:
            env.set_state(np.zeros(env.dof))

    rows.append(("env.step (pymunk contacts at 4 sub-steps, empty scene)",
                 rate(one_step, 1, args.seconds), "steps/s", ""))
    env.reset(seed=seeds[0])
    q0 = env.q
    env.set_state(q0)

    def one_step_scene():
        _, _, terminated, truncated, _ = env.step(env.q)  # hold position: contacts every step
        if terminated or truncated:
            env.set_state(q0)

    rows.append((f"env.step (hold still, scene {seeds[0]})", rate(one_step_scene, 1, args.seconds),
                 "steps/s", ""))
    rows.append(("env.reset (scene generation with rejection)",
                 rate(lambda: env.reset(seed=int(rng.integers(0, 10_000))), 1, args.seconds),
                 "resets/s", ""))

    print("| measurement | per wall second | per CPU second | unit | note |\n|---|---:|---:|---|---|")
    for name, (wall, cpu), unit, note in rows:
        print(f"| {name} | {wall:,.0f} | {cpu:,.0f} | {unit} | {note} |")


if __name__ == "__main__":
    main()
