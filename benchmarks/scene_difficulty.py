"""How hard are the PlanarReacher scenes? (the task must need planning).

For each of the 100 evaluation scenarios:
  straight line  -- from the start to the collision-free goal configuration closest to it in joint
                    space (max-norm, i.e. fewest steps at the per-joint speed limit; goal
                    configurations from env.goal_configurations, the closed-form IK), checked at the
                    env's sub-step resolution. "blocked" = that line collides somewhere. Also
                    reported: the fraction where the lines to all goal configurations collide.
  grid path      -- a breadth-first flood fill over a joint-space grid (spacing = max_step, moves to
                    any of the 26 neighbouring cells, i.e. one env step with every joint moving at
                    most max_step) from the start to any goal cell. Gives "solvable" (a path exists at
                    this resolution; narrow passages thinner than a cell are missed, so this is a
                    conservative estimate) and the shortest path length in steps (an estimate of the
                    expert episode length before smoothing).

Usage:  python benchmarks/scene_difficulty.py [--n 100] [--grid 0.05] [--seeds eval|train]
Prints one line per scene and a summary table. Takes a few seconds per scene (grid collision checks).
"""
import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from envs import make_env  # noqa: E402


def straight_line(env, q0, q1):
    """Joint-space line q0 -> q1 at the env's sub-step resolution; (n, dof) including q1."""
    n_steps = max(1, int(np.ceil(np.max(np.abs(q1 - q0)) / env.max_step)))
    n = n_steps * env.cfg.n_substeps
    return q0 + np.linspace(0.0, 1.0, n + 1)[1:, None] * (q1 - q0), n_steps


def grid_search(env, start, goal_qs, spacing):
    """Flood fill over a joint grid; returns (solvable, path length in env steps or None)."""
    lo, hi = env.joint_limits
    axes = [np.arange(l, h + 1e-9, spacing) for l, h in zip(lo, hi)]
    shape = tuple(len(a) for a in axes)
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, env.dof)
    free = ~env.in_collision(grid)
    goal_cells = free & env.goal_reached(grid)
    cell = lambda q: np.ravel_multi_index(  # noqa: E731
        tuple(np.clip(np.rint((q - lo) / spacing).astype(int), 0, np.array(shape) - 1).T), shape)
    goal_cells[cell(goal_qs)] |= free[cell(goal_qs)]
    free, goal_cells = free.reshape(shape), goal_cells.reshape(shape)
    # seed: the start's cell and its free neighbours (the start itself is off-grid)
    reached = np.zeros(shape, bool)
    idx = np.unravel_index(cell(start[None])[0], shape)
    sl = tuple(slice(max(i - 1, 0), i + 2) for i in idx)
    reached[sl] = free[sl]
    steps_per_move = spacing / env.max_step
    for level in range(1, 10 * sum(shape)):
        if np.any(reached & goal_cells):
            return True, level * steps_per_move
        grown = reached.copy()
        for ax in range(3):  # 3x3x3 dilation, separably: 26-neighbour moves
            g = grown.copy()
            sl_a = [slice(None)] * 3
            sl_b = [slice(None)] * 3
            sl_a[ax], sl_b[ax] = slice(1, None), slice(None, -1)
            g[tuple(sl_a)] |= grown[tuple(sl_b)]
            g[tuple(sl_b)] |= grown[tuple(sl_a)]
            grown = g
        grown &= free
        if np.array_equal(grown, reached):
            return False, None
        reached = grown
    return False, None


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=100, help="number of scenarios")
    parser.add_argument("--grid", type=float, default=0.05, help="joint grid spacing (rad)")
    parser.add_argument("--seeds", choices=["eval", "train"], default="eval")
    parser.add_argument("--no-grid", action="store_true", help="skip the flood fill (fast)")
    args = parser.parse_args()
    env = make_env("planar")
    seeds = env.eval_seeds()[: args.n] if args.seeds == "eval" else env.train_seeds(args.n)
    blocked, all_blocked, straight_steps, solvable, grid_steps = [], [], [], [], []
    t0 = time.time()
    for seed in seeds:
        _, info = env.reset(seed=seed)
        start = info["q"]
        goal_qs = env.goal_configurations(n_angles=720)
        nearest = goal_qs[np.argmin(np.max(np.abs(goal_qs - start), axis=1))]
        line, n_steps = straight_line(env, start, nearest)
        blocked.append(bool(env.in_collision(line).any()))
        # does ANY goal configuration have a free straight line? (every one blocked = must plan)
        any_free = False
        for q_goal in goal_qs[np.argsort(np.max(np.abs(goal_qs - start), axis=1))][::4]:
            if not env.in_collision(straight_line(env, start, q_goal)[0]).any():
                any_free = True
                break
        all_blocked.append(not any_free)
        straight_steps.append(n_steps)
        msg = f"seed {seed}: straight line {'BLOCKED' if blocked[-1] else 'free   '} {n_steps:4d} steps"
        if not args.no_grid:
            ok, length = grid_search(env, start, goal_qs, args.grid)
            solvable.append(ok)
            if ok:
                grid_steps.append(length)
            msg += f" | grid: {'solvable' if ok else 'NO PATH'}" + (f" {length:5.0f} steps" if ok else "")
        print(msg, flush=True)
    s = np.array(straight_steps)
    print(f"\nscenes: {len(seeds)} ({args.seeds} seeds), {time.time() - t0:.0f} s")
    print("| measure | value |\n|---|---|")
    print(f"| straight joint-space line to nearest goal configuration collides | {np.mean(blocked):.2f} |")
    print(f"| straight lines to every goal configuration (1 in 4 tried) collide | "
          f"{np.mean(all_blocked):.2f} |")
    print(f"| straight-line length, steps (median / 90th pct / max) | "
          f"{np.median(s):.0f} / {np.percentile(s, 90):.0f} / {s.max()} |")
    if solvable:
        g = np.array(grid_steps)
        print(f"| solvable on the {args.grid} rad grid | {np.mean(solvable):.2f} |")
        print(f"| grid shortest path, steps (median / 90th pct / max) | "
              f"{np.median(g):.0f} / {np.percentile(g, 90):.0f} / {g.max():.0f} |")
        print(f"| env max_steps | {env.max_steps} |")


if __name__ == "__main__":
    main()
