"""Where and when does a policy fail on the evaluation scenarios? (the failure table)

Rolls a saved policy out on the 100 evaluation scenarios (x repeats, the same lockstep rollout as
dagger.evaluate) and sorts every episode into: success, collision with an obstacle, self-collision,
or timeout (the step limit, env.max_steps). For collisions it names what touched first and the step
(planar: the arm part, link 1 .. 3, palm, a finger; engine3d: what was hit, the engine or lever, a
box, the wall, the table, the arm itself); for timeouts the end effector's final distance to the
target. Collisions are re-judged on the sub-steps of the last step with the env's own numpy check.
engine3d with position-only success also counts the successes whose tool is within 10 deg of the goal
posture's orientation (the authors' rule has this part: the env variant engine3d_oriented, experiment/oriented_goal.py).

With several checkpoints (e.g. BC, HG-DAgger and pooled of one round) it ends with the failure-time
histogram side by side: when the collisions happen (the first second, 1-3 s, 3-10 s, later), their share in
the first second, and the timeouts -- the paper's lever policies fail mostly in the first second.

Usage:  python benchmarks/bc_failures.py CHECKPOINT [CHECKPOINT ...] [--labels BC HG pooled]
                                         [--env planar|engine3d] [--repeats 3] [--seed 123]
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import dagger  # noqa: E402
import envs  # noqa: E402
from experiment import checkpoints, engine3d, environments, oriented_goal  # noqa: E402

PART_NAMES = ("link1", "link2", "link3", "palm", "finger_left", "finger_right")  # rows of PlanarReacher.parts

def ending(env, episode):
    """(outcome or None, step, final distance, the state reached (dof,), the last step's sub-states (S, dof),
    their collision flags): outcome 'success' or 'timeout', None when the episode ended early without
    success (its last step collided; the caller names what it hit). An episode records the state before
    each action, so the state reached is its last action applied by the env's motion rule."""
    T = len(episode["q"])
    q0 = episode["q"][-1]
    q1 = env.clip_action(q0, episode["action"][-1])
    dist = float(np.linalg.norm(env.ee(q1) - env.goal))
    if episode["success"] or T >= env.max_steps:
        return ("success" if episode["success"] else "timeout"), T, dist, q1, None, None
    sweep = q0 + np.linspace(0, 1, 4 * env.cfg.n_substeps + 1)[1:, None] * (q1 - q0)
    return None, T, dist, q1, sweep, env.in_collision(sweep)


def classify(env, episode):
    """(outcome, part, step, final distance) of one finished episode in env (reset to its seed)."""
    outcome, T, dist, _, sweep, hit = ending(env, episode)
    if outcome:
        return outcome, "", T, dist
    # the first colliding sub-state of the last step and the part (and the kind of contact) behind it
    q = sweep[np.argmax(hit)]
    boxes = [x[:, 0] for x in env.part_boxes(q[None])]  # (n_parts,) each
    margin = env.contact_margin
    for p, name in enumerate(PART_NAMES):
        part = tuple(x[p] for x in boxes)
        for obstacle in zip(*env._obstacle_boxes):
            if envs.box_distance(part, obstacle) < margin:
                return "collision: obstacle", name, T, dist
    for i, j in env.SELF_PAIRS:
        if envs.box_distance(tuple(x[i] for x in boxes), tuple(x[j] for x in boxes)) < margin:
            return "collision: self", f"{PART_NAMES[i]}-{PART_NAMES[j]}", T, dist
    return "collision: other", "", T, dist


def classify_engine3d(env, episode):
    """classify for the UR5 cell: the collision's partner from the clearance terms of engine3d.EngineReach3D."""
    outcome, T, dist, _, sweep, hit = ending(env, episode)
    if outcome:
        return outcome, "", T, dist
    if not hit.any():
        return "collision: other", "pybullet contact only", T, dist
    q = sweep[np.argmax(hit)][None]
    a0, a1 = env._arm_components(q)
    r, (i, j) = env.link_radii, engine3d.ENGINE_SELF_PAIRS.T
    terms = {"the arm itself": float((engine3d.segment_distance_3d(a0[:, :, i], a1[:, :, i], a0[:, :, j], a1[:, :, j])
                                      - r[i] - r[j]).min()),
             "the table": float(env._ground_clearance(a0, a1)[0]),
             "the wall": float(env._wall_clearance(a0, a1)[0])}
    if len(env.obstacles):
        g = env._geom
        d = (engine3d.segment_distance_3d(a0[..., None], a1[..., None], g["start"][:, None, None], g["end"][:, None, None])
             - g["contact"]).min(axis=(0, 1))  # (N,) per obstacle
        for k, kind in enumerate(env.obstacle_kinds):
            name = {"engine": "the engine", "lever": "the lever", "box": "a box"}.get(kind, kind)
            terms[name] = min(terms.get(name, np.inf), float(d[k]))
    partner = min(terms, key=terms.get)
    return ("collision: self" if partner == "the arm itself" else "collision: obstacle"), partner, T, dist


# the failure-time histogram's bins, in seconds of the episode
TIME_BINS = ((0, 1), (1, 3), (3, 10), (10, float("inf")))


def failure_times(rows, dt):
    """{'success', 'timeout', 'collisions', (lo, hi) per TIME_BINS: collisions whose step falls in [lo, hi) s,
    'first_second': the share of the collisions within the first second}, counts of episodes (rows of
    classify; a collision at step T happened during the T-th step, at (T - 1) * dt to T * dt s)."""
    t = np.array([(r[2] - 1) * dt for r in rows if r[0].startswith("collision")])
    out = {"episodes": len(rows), "success": sum(r[0] == "success" for r in rows),
           "timeout": sum(r[0] == "timeout" for r in rows), "collisions": len(t)}
    for lo, hi in TIME_BINS:
        out[(lo, hi)] = int(np.sum((t >= lo) & (t < hi)))
    out["first_second"] = out[TIME_BINS[0]] / len(t) if len(t) else float("nan")
    return out


def roll_out(checkpoint, args):
    """(rows, angles, scene): the policy at `checkpoint` on the evaluation scenarios x repeats, each episode
    classified; `angles` the tool's angle to the goal posture's orientation of every success (engine3d with
    position-only success, else empty); `scene` what print_failures needs of the env (dt, goal tolerance).

    The episodes run as in dagger.evaluate (dagger.rollouts_in_groups: lockstep, in groups of at most
    the env's max_parallel, engine3d 100 pybullet clients, each group closed before the next), and every
    episode is classified while its env is open: memory stays that of one group, however many policies."""
    policy = checkpoints.load_policy(checkpoint)
    jobs = [int(s) for _ in range(args.repeats) for s in envs.eval_seeds()]
    gen = torch.Generator().manual_seed(args.seed)
    rows, angles, scene = [], [], None
    for e, ep in dagger.rollouts_in_groups(policy, args.env, jobs, policy.cfg.n_act, gen,
                                           make_env=environments.make_env):
        e.reset(seed=ep["seed"])
        rows.append(classify(e, ep) if args.env == "planar" else classify_engine3d(e, ep))
        if scene is None:
            scene = {"dt": e.cfg.dt, "goal_tolerance": e.goal_tolerance,
                     "angle_rule": args.env == "engine3d" and not e.goal_is_pose}
        if scene["angle_rule"] and rows[-1][0] == "success":
            angles.append(oriented_goal.tool_angle(ending(e, ep)[3], e.cfg.goal_q))
    return rows, np.array(angles), scene


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("checkpoints", nargs="+", metavar="CHECKPOINT")
    parser.add_argument("--labels", nargs="+", default=None, help="a name per checkpoint for the histogram")
    parser.add_argument("--env", default="planar", choices=sorted(environments.ENVIRONMENTS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=123)
    args = parser.parse_args()
    labels = args.labels or [os.path.splitext(os.path.basename(c))[0] for c in args.checkpoints]
    if len(labels) != len(args.checkpoints):
        parser.error(f"--labels: {len(labels)} names for {len(args.checkpoints)} checkpoints; give one per checkpoint")
    torch.set_num_threads(1)
    histograms = []
    for checkpoint in args.checkpoints:
        rows, angles, scene = roll_out(checkpoint, args)
        print_failures(args, checkpoint, rows, angles, scene)
        histograms.append(failure_times(rows, scene["dt"]))
    if len(histograms) > 1:
        print("\n## When the policies fail (episodes; a collision's time is the start of its step)\n")
        bins = [f"collision {lo:g}-{hi:g} s" if hi != float("inf") else f"collision after {lo:g} s"
                for lo, hi in TIME_BINS]
        print("| policy | success | " + " | ".join(bins) + " | timeout | collisions in the first second |")
        print("|---|---|" + "---|" * len(bins) + "---|---|")
        for label, h in zip(labels, histograms):
            print(f"| {label} | {h['success']} | " + " | ".join(str(h[b]) for b in TIME_BINS)
                  + f" | {h['timeout']} | {h['first_second']:.0%} of {h['collisions']} |")


def print_failures(args, checkpoint, rows, angles, scene):
    """The outcome table, the colliding parts, the collision times and the timeouts' distances of one policy."""
    n = len(rows)
    print(f"{checkpoint}: {n} episodes ({n // args.repeats} scenarios x {args.repeats})\n")
    print("| outcome | episodes | share | median step | steps (10th-90th pct) |")
    print("|---|---|---|---|---|")
    for outcome in ("success", "collision: obstacle", "collision: self", "collision: other", "timeout"):
        steps = np.array([r[2] for r in rows if r[0] == outcome])
        if len(steps):
            print(f"| {outcome} | {len(steps)} | {len(steps) / n:.1%} | {np.median(steps):.0f} | "
                  f"{np.percentile(steps, 10):.0f}-{np.percentile(steps, 90):.0f} |")
    print("\n| " + ("colliding part" if args.env == "planar" else "hit") + " | episodes |\n|---|---|")
    parts = [r[1] for r in rows if r[0].startswith("collision")]
    for part in sorted(set(parts), key=parts.count, reverse=True):
        print(f"| {part} | {parts.count(part)} |")
    collided = np.array([r[2] for r in rows if r[0].startswith("collision")])
    if len(collided):
        print(f"\ncollisions within the first 10 s (100 steps at 10 Hz): {np.mean(collided <= 100):.0%}; "
              f"within the first 3 s (30 steps): {np.mean(collided <= 30):.0%}")
    timeouts = np.array([r[3] for r in rows if r[0] == "timeout"])
    if len(timeouts):
        print(f"timeouts: final end-effector distance to the target median {np.median(timeouts):.3f} m "
              f"(success radius {scene['goal_tolerance']} m)")
    if scene["angle_rule"]:  # the authors' 10 deg, not checked
        if len(angles):
            print(f"successes with the tool within 10 deg of the goal posture's orientation (the authors' rule, "
                  f"not checked by the env: --env engine3d_oriented checks it): {np.sum(angles <= 10)} of {len(angles)}; angle median "
                  f"{np.median(angles):.0f} deg (10th-90th pct {np.percentile(angles, 10):.0f}-"
                  f"{np.percentile(angles, 90):.0f})")


if __name__ == "__main__":
    main()
