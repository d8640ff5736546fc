"""The RRT oracle expert (paper Sec. V; the expert gating of Sec. IV-A).

The paper replaces the human of HG-DAgger by a deterministic planner that uses privileged simulator
information (Sec. IV-A: the oracle decides "based on heuristics like whether the policy's predicted
action chunk will drive the robot into collision or if the policy has not yet reached the goal").
Sec. V: it "plans a path from the current state to the goal, but we execute only a fraction of the
plan", picks "the optimal path under a deterministic criterion (for example, minimum end effector
arc length)", smooths it with "random shortcutting, trajectory optimization, corner smoothing, and
speed, acceleration, and jerk limits enforced by TOPP-RA", and matches "the policy's induced pose
and velocity at the handoff". This file builds it from scratch, for any serial arm behind the env
interface of envs.py (env.dof, env.joint_limits, env.in_collision, env.fk / env.ee, env.ee_jacobian,
env.max_step, env.dt), in the paper's order:

  solve_ik            goal configurations: damped least squares from many seeds
  rrt_connect         bidirectional RRT-Connect in joint space, batched edge checks, several goals
  shortcut            random shortcutting (after one greedy batched pass)
  smooth_corners      quadratic-Bezier corner rounding, sharp corner kept where rounding collides
                      (no separate trajectory-optimization step)
  time_parameterize   speed / acceleration / jerk limits at every sample, WITHOUT TOPP-RA (here: a
                      double moving-average (FIR) filter of a full-speed traversal, verified and
                      locally slowed down where needed)
  Gate, Oracle        demonstrate (full expert episodes for D0); the HG-DAgger gate (predicted
                      collision, stall, and the authors' time triggers) and intervention, which
                      matches the policy's pose and velocity at the handoff and drives only a
                      fraction of the plan before handing back
  plot_demonstration  Fig. 5: a scene with an expert demonstration

Beyond the paper (after the banner): the edge checks every step above relies on (lever arms, edge
interpolation, batched checks with a clearance margin; why they cannot miss an obstacle is
explained there) and min_time_lower_bound, a yardstick for the time parameterization.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np


class PlanningFailed(RuntimeError):
    """The planner found no plan within its budget (or the problem has none)."""

    def __init__(self, reason, iters=0):
        super().__init__(reason)
        self.reason = reason  # human-readable cause
        self.iters = iters  # RRT iterations spent (0 if it failed before the search)


@dataclass
class OracleConfig:
    # --- the authors' planner and gate (PAPER_SETUP.md §3). Their counts are frames at 30 Hz; our
    #     envs run at 10 Hz, so each becomes a third as many steps (the same seconds) ---
    # Distinct goal configurations handed to the planner (nearest first). The authors rank 32 IK
    # candidates; measured on the 100 planar evaluation scenes, 8 left the planner without a
    # reachable goal in 3 of 40 scenes, 32 solved 99 of 100.
    max_goals: int = 32  # configurations
    # Limits of the expert's motion, the authors' 0.5 rad/s, 1 rad/s^2, 10 rad/s^3 per joint (the
    # speed limit is the env's: v_max = speed_fraction * env.max_step / env.dt, see Oracle.limits).
    speed_fraction: float = 1.0  # fraction of the env's speed limit
    a_max: float = 1.0  # rad/s^2 per joint
    j_max: float = 10.0  # rad/s^3 per joint
    gate_lookahead: int | None = 3  # steps at 10 Hz of the pending chunk the gate checks, before every
    #   policy step (theirs: the next 8 frames); None = the whole pending chunk
    gate_clearance: float = 0.010  # m, a pending state this close to a collision triggers the expert.
    #   Theirs is 0.019 m, just inside their planner's 0.02 m clearance; our planner keeps
    #   margin * sweep = 0.011 m (planar), so the gate sits just inside that instead: a policy
    #   that flies the expert's own route does not trigger it.
    handback_steps: tuple = (20, 67)  # steps at 10 Hz the expert drives, drawn in this range (both
    #   included; theirs: 60-200 frames), or its whole plan if shorter, then hands back
    max_interventions: int = 5  # interventions per episode (theirs: 5 per scenario)
    time_trigger_first: int = 200  # policy steps at 10 Hz before the first time trigger (theirs: 600 frames)
    time_trigger_every: tuple = (67, 100)  # policy steps at 10 Hz between time triggers (theirs: 200-300)
    rewind_steps: tuple = (17, 33)  # steps at 10 Hz that stall and time triggers first rewind (theirs:
    #   50-100 frames), so that the expert takes over before the policy went astray

    # --- not in the paper ---
    seed: int = 0  # base seed of the planner's randomness (mixed with scenario seed / state)
    # Inverse kinematics
    n_ik_seeds: int = 512  # DLS starting points (start + uniform random); free goal configs can
    #   be rare in clutter (~2% of converged seeds in some planar scenes), and seeds are batched
    ik_iters: int = 40  # DLS iterations (most seeds converge in 10-20)
    ik_damping: float = 0.05  # m/rad, lambda of DLS: keeps steps bounded near singularities
    ik_tolerance: float = 1e-3  # m, an IK solution's end effector must be this close to the goal
    goal_dedup: float = 0.2  # rad, solutions closer than this (max-norm) count as one
    # RRT-Connect
    step_size: float = 0.3  # rad, joint-space length of one EXTEND step
    # Samples per iteration, checked in one batched call. One in_collision call costs as much as
    # a few hundred more configurations in it (planar: ~150 us + 0.5 us per configuration), so
    # fewer, larger calls plan faster: 8 -> 32 halved the planar planning time (bench_oracle.py).
    rrt_batch: int = 32  # samples
    max_iters: int = 500  # RRT iterations per attempt, i.e. 16k samples at rrt_batch = 32; on
    #   failure the plan falls back to thinner margins (min_sweep_fraction), so a larger budget
    #   would only make the failing levels slower
    max_time: float = 10.0  # s per attempt: a guard against hanging, not the normal budget
    n_attempts: int = 3  # independent RRT runs; the plan with the smallest ee arc length wins
    shortcut_iters: int = 64  # random shortcut proposals (after the greedy pass)
    corner_fraction: float = 0.4  # fraction of the shorter edge where a corner's blend starts
    corner_points: int = 8  # points sampled on each corner's Bezier blend
    # Collision checking (see the edge checks behind the banner). The margins are in sweeps: a
    # sweep is sweep_tolerance m, the arm-point motion between two checks of the executed
    # trajectory (and of the gate's checks); None: half the env's link_radius (planar 0.0075 m).
    sweep_tolerance: float | None = None  # m
    # Planning margin (RRT, shortcut, corners). Planning checks are spaced 2 (margin -
    # verify_margin) sweeps apart, so every state between two of them keeps verify_margin of
    # clearance: 1.5 spaces them 2 sweeps apart (planar: 0.011 m margin, 0.015 m spacing), half
    # the checks of margin 1.0 (1 sweep apart); the authors' planner keeps 0.02 m (PAPER_SETUP.md
    # §3). Narrow passages the margin closes are left to the fallback below.
    margin: float = 1.5  # sweeps
    verify_margin: float = 0.5  # sweeps, margin the executed trajectory is verified with;
    #   >= 0.5 rules out grazes between checks (with_margin); < margin leaves room for corner cuts
    relax_sweeps: float = 4.0  # sweeps: no margin within this much arm motion of start / goals
    # If no path is found, halve the sweep (so all margins and spacings) down to this fraction.
    # 1/8: the tightest planar eval scene (seed 10097) needs a margin below 0.006 m.
    min_sweep_fraction: float = 0.125  # fraction of the sweep
    horizon: int = 16  # steps: H, the policy's action chunk (dagger drops interventions shorter than H)
    # The authors' "in collision and stuck" trigger cannot fire here (a contact ends our episodes),
    # so a stall of the end effector stands in for it.
    stall_window: int = 40  # steps at 10 Hz: stalled if the ee got no closer to the goal in this window
    stall_progress: float = 0.02  # m, the improvement that counts as progress in the window


# ----------------------------------------------------------------------------------------------
# Inverse kinematics (goal configurations)
# ----------------------------------------------------------------------------------------------
def solve_ik(env, goal, rng, q_start=None, n_seeds=512, iters=40, damping=0.05, tolerance=1e-3,
             max_goals=8, dedup=0.2, in_collision=None):
    """Collision-free goal configurations (M, dof), M <= max_goals, nearest to q_start first.

    Damped least squares, batched over seeds: dq = J^T (J J^T + lambda^2 I)^-1 (goal - ee(q)),
    projected onto the joint limits. Seeds: q_start (if given) and uniform random configurations.
    An env whose goal includes an orientation (env.goal_is_pose: engine3d's goal_angle_tolerance) gives
    its goal configurations in closed form instead (env.goal_configurations).
    Kept: solutions within `tolerance` of the goal, accepted by env.goal_reached, collision-free
    (in_collision, default env.in_collision), and more than `dedup` rad (max-norm) from every
    solution kept before them.
    """
    in_collision = in_collision or env.in_collision
    goal = np.asarray(goal, dtype=np.float64)
    if env.goal_is_pose:
        # the goal includes an orientation (engine3d with the authors' rule), which position-only DLS
        # would miss: its configurations come in closed form from the env
        q = env.goal_configurations()
    else:
        lo, hi = env.joint_limits
        q = rng.uniform(lo, hi, size=(n_seeds, env.dof))  # (S, dof)
        if q_start is not None:
            q[0] = q_start
        for _ in range(iters):
            err = goal - env.ee(q)  # (S, dim)
            J = env.ee_jacobian(q)  # (S, dim, dof), central differences
            JJt = J @ J.transpose(0, 2, 1) + damping ** 2 * np.eye(J.shape[1])  # (S, dim, dim)
            dq = (J.transpose(0, 2, 1) @ np.linalg.solve(JJt, err[..., None]))[..., 0]  # (S, dof)
            q = np.clip(q + dq, lo, hi)
        close = np.linalg.norm(env.ee(q) - goal, axis=1) <= tolerance
        q = q[close & env.goal_reached(q)]
    q = q[~in_collision(q)] if len(q) else q
    if q_start is not None and len(q):
        q = q[np.argsort(np.linalg.norm(q - q_start, axis=1), kind="stable")]
    kept = []
    for cand in q:
        if all(np.max(np.abs(cand - k)) > dedup for k in kept):
            kept.append(cand)
        if len(kept) == max_goals:
            break
    return np.array(kept).reshape(-1, env.dof)


# ----------------------------------------------------------------------------------------------
# RRT-Connect (Kuffner & LaValle 2000), joint space, several goal roots
# ----------------------------------------------------------------------------------------------
class _Tree:
    """Nodes (n, dof) with parent indices; roots have parent -1 (the goal tree has several)."""

    def __init__(self, roots):
        self.nodes = np.array(roots, dtype=np.float64)  # grows by doubling
        self.parent = np.full(len(self.nodes), -1)
        self.sq_norm = np.sum(self.nodes ** 2, axis=1)  # |node|^2, for `nearest`
        self.n = len(self.nodes)

    def add(self, q, parent):
        """Append nodes q (N, dof) with parent indices (N,)."""
        while self.n + len(q) > len(self.nodes):
            self.nodes = np.concatenate([self.nodes, np.empty_like(self.nodes)])
            self.parent = np.concatenate([self.parent, np.full(len(self.parent), -1)])
            self.sq_norm = np.concatenate([self.sq_norm, np.empty_like(self.sq_norm)])
        new = slice(self.n, self.n + len(q))
        self.nodes[new], self.parent[new], self.sq_norm[new] = q, parent, np.sum(q ** 2, axis=1)
        self.n += len(q)

    def nearest(self, q):
        """Indices (B,) of the nodes nearest (Euclidean, joint space) to q (B, dof)."""
        # |q - x|^2 = |x|^2 - 2 q.x + |q|^2, and |q|^2 is the same for every node x: one matrix
        # product instead of a (B, n, dof) difference array (the search's cost in large trees)
        return np.argmin(self.sq_norm[:self.n] - 2 * q @ self.nodes[:self.n].T, axis=1)

    def branch(self, i):
        """Nodes from node i back to its root, (k, dof)."""
        out = []
        while i >= 0:
            out.append(self.nodes[i])
            i = self.parent[i]
        return np.array(out)


def _grow(tree, near, targets, free, step_size):
    """Add to `tree` the free part of the edges near[i] -> targets[i] (free: fraction (E,)),
    one node every step_size along it. Returns the index of each edge's last node (E,)."""
    q_near = tree.nodes[near]  # (E, dof)
    dq = targets - q_near
    n_new = np.ceil(free * np.linalg.norm(dq, axis=1) / step_size - 1e-9).astype(int)  # (E,)
    edge, k = substeps(n_new)  # (N,) each: new node k of edge `edge`
    index = tree.n + np.arange(len(edge))  # (N,) the indices the new nodes get
    parent = np.where(k == 1, near[edge], index - 1)  # a chain from near[e] along each edge
    tree.add(q_near[edge] + ((k / n_new[edge]) * free[edge])[:, None] * dq[edge], parent)
    last = np.array(near)
    last[n_new > 0] = tree.n - len(edge) + np.cumsum(n_new)[n_new > 0] - 1
    return last


def rrt_connect(q_start, q_goals, in_collision, joint_limits, rng, step_size=0.3, resolution=0.05,
                max_iters=500, max_time=10.0, batch=32):
    """A collision-free path (N, dof) from q_start to one of q_goals, or raise PlanningFailed.

    q_goals (M, dof) are all roots of the goal tree. `resolution` (scalar or (dof,), rad) is the
    edge-check spacing (see `edge_resolution`). Each iteration is one batched RRT-Connect step:
    tree A EXTENDs toward `batch` uniform samples (one step_size each, keeping the free part of a
    blocked step, which still makes progress into narrow passages), then tree B CONNECTs
    greedily toward every new node (straight, as far as free); the trees swap roles. Two batched
    edge checks per iteration (each a few in_collision calls: `edge_free_fraction`). Budget:
    max_iters iterations (deterministic) and max_time seconds (a hang guard; hitting it is the
    only non-deterministic outcome).
    """
    q_start = np.asarray(q_start, dtype=np.float64)
    q_goals = np.atleast_2d(np.asarray(q_goals, dtype=np.float64))
    lo, hi = (np.asarray(x, dtype=np.float64) for x in joint_limits)
    if q_start.ndim != 1 or q_goals.shape[1:] != q_start.shape:
        raise ValueError(f"q_start (dof,) and q_goals (M, dof) must agree, got {q_start.shape} "
                         f"and {q_goals.shape}")
    if step_size <= 0 or max_iters < 0 or batch < 1:
        raise ValueError(f"need step_size > 0, max_iters >= 0, batch >= 1; got {step_size}, "
                         f"{max_iters}, {batch}")
    if in_collision(q_start[None])[0]:
        raise PlanningFailed("start configuration is in collision")
    q_goals = q_goals[~in_collision(q_goals)]
    if len(q_goals) == 0:
        raise PlanningFailed("every goal configuration is in collision")
    # Straight lines first (one batched check): the common easy case costs a single call.
    free = edges_free(np.repeat(q_start[None], len(q_goals), 0), q_goals, in_collision,
                      resolution)
    if np.any(free):
        direct = np.flatnonzero(free)
        best = direct[np.argmin(np.linalg.norm(q_goals[direct] - q_start, axis=1))]
        return np.stack([q_start, q_goals[best]])
    trees = [_Tree([q_start]), _Tree(q_goals)]  # [start tree, goal tree]
    t0 = time.perf_counter()
    for it in range(max_iters):
        if time.perf_counter() - t0 > max_time:
            raise PlanningFailed(f"time budget of {max_time} s exhausted", iters=it)
        # >>> exercise 10: RRT-Connect's EXTEND and CONNECT (Sec. V, the RRT oracle)
        a, b = trees[it % 2], trees[1 - it % 2]
        # EXTEND tree A toward `batch` uniform samples (one batched check)
        q_rand = rng.uniform(lo, hi, size=(batch, len(lo)))  # (batch, dof)
        near = a.nearest(q_rand)
        d = q_rand - a.nodes[near]
        dist = np.linalg.norm(d, axis=1)
        q_new = a.nodes[near] + d * np.minimum(1.0, step_size / np.maximum(dist, 1e-12))[:, None]
        free = edge_free_fraction(a.nodes[near], q_new, in_collision, resolution)
        useful = free * np.minimum(dist, step_size) >= 0.1 * step_size  # else not worth a node
        if not useful.any():
            continue
        new = _grow(a, near[useful], q_new[useful], free[useful], step_size)  # one node each
        # CONNECT tree B toward every new node (one batched check)
        targets = a.nodes[new]
        near_b = b.nearest(targets)
        free_b = edge_free_fraction(b.nodes[near_b], targets, in_collision, resolution)
        last_b = _grow(b, near_b, targets, free_b, step_size)
        reached = np.flatnonzero(free_b == 1.0)
        if len(reached):
            e = reached[0]  # first in sample order: deterministic
            branch_a, branch_b = a.branch(new[e]), b.branch(last_b[e])
            start_side, goal_side = (branch_a, branch_b) if it % 2 == 0 else (branch_b, branch_a)
            return _drop_duplicates(np.concatenate([start_side[::-1], goal_side]))
        # <<< exercise 10
    raise PlanningFailed(f"no path within max_iters={max_iters}", iters=max_iters)


def _drop_duplicates(path, tol=1e-12):
    """Remove consecutive repeated states from a polyline (N, dof)."""
    keep = np.concatenate([[True], np.linalg.norm(np.diff(path, axis=0), axis=1) > tol])
    return path[keep]


# ----------------------------------------------------------------------------------------------
# Path post-processing: shortcutting and corner smoothing
# ----------------------------------------------------------------------------------------------
def shortcut(path, in_collision, rng, iters=64, resolution=0.05, batch=8):
    """Shorter collision-free polyline with the same end points.

    1) Greedy pass: from each kept vertex jump to the farthest later vertex reachable by a free
       straight edge (all candidate edges of a vertex in one batched check).
    2) Random shortcutting: `iters` proposals of two random points along the path, in batches of
       `batch` checked together; the free proposal that saves the most length is applied.
    """
    path = _drop_duplicates(np.asarray(path, dtype=np.float64))
    out, i = [path[0]], 0
    while i < len(path) - 1:
        later = np.arange(i + 1, len(path))
        free = edges_free(np.repeat(path[i][None], len(later), 0), path[later], in_collision,
                          resolution)
        free[0] = True  # i -> i + 1 is an edge of the given path: valid by assumption
        i = later[np.flatnonzero(free).max()]
        out.append(path[i])
    path = np.array(out)
    for _ in range(iters // batch):
        if len(path) < 3:
            break
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
        s = np.sort(rng.uniform(0, cum[-1], size=(batch, 2)), axis=1)  # (batch, 2) arc positions
        seg = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(path) - 2)  # (batch, 2)
        t = (s - cum[seg]) / (cum[seg + 1] - cum[seg])
        p = path[seg] + t[..., None] * (path[seg + 1] - path[seg])  # (batch, 2, dof)
        saving = (s[:, 1] - s[:, 0]) - np.linalg.norm(p[:, 1] - p[:, 0], axis=1)
        useful = (seg[:, 0] < seg[:, 1]) & (saving > 1e-9)
        if not useful.any():
            continue
        free = edges_free(p[useful, 0], p[useful, 1], in_collision, resolution)
        if not free.any():
            continue
        cand = np.flatnonzero(useful)[free]
        k = cand[np.argmax(saving[cand])]
        path = _drop_duplicates(np.concatenate([path[:seg[k, 0] + 1], p[k], path[seg[k, 1] + 1:]]))
    return path


def smooth_corners(path, in_collision, resolution=0.05, fraction=0.4, n_points=8, n_halvings=3):
    """Replace each interior vertex by a quadratic Bezier blend, where that stays collision-free.

    The blend of vertex v between neighbours a, b runs from p_in = v + d (a - v)/|a - v| to
    p_out = v + d (b - v)/|b - v| with control point v: B(u) = (1-u)^2 p_in + 2u(1-u) v + u^2 p_out,
    tangent to both edges (so the direction changes gradually). d = fraction * min(|a-v|, |b-v|)
    (fraction <= 0.5: neighbouring blends never overlap). A blend that collides is retried with d
    halved, n_halvings times; after that the sharp corner stays (always valid: it was checked).
    All corners of one halving level are checked in one batched call.
    """
    path = _drop_duplicates(np.asarray(path, dtype=np.float64))
    if not 0 < fraction <= 0.5:
        raise ValueError(f"fraction must be in (0, 0.5], got {fraction}")
    n_corner = len(path) - 2
    if n_corner < 1:
        return path
    v, a, b = path[1:-1], path[:-2], path[2:]  # (C, dof) each
    len_a = np.linalg.norm(a - v, axis=1)[:, None]
    len_b = np.linalg.norm(b - v, axis=1)[:, None]
    d = fraction * np.minimum(len_a, len_b)  # (C, 1)
    u = np.linspace(0.0, 1.0, n_points)[None, :, None]  # (1, n_points, 1)
    blends = [None] * n_corner
    todo = np.arange(n_corner)
    for _ in range(n_halvings + 1):
        p_in = v[todo] + d[todo] * (a[todo] - v[todo]) / len_a[todo]
        p_out = v[todo] + d[todo] * (b[todo] - v[todo]) / len_b[todo]
        curve = ((1 - u) ** 2 * p_in[:, None] + 2 * u * (1 - u) * v[todo][:, None]
                 + u ** 2 * p_out[:, None])  # (C', n_points, dof)
        q_from = curve[:, :-1].reshape(-1, path.shape[1])
        q_to = curve[:, 1:].reshape(-1, path.shape[1])
        ok = edges_free(q_from, q_to, in_collision, resolution).reshape(len(todo), -1)
        ok = np.all(ok, axis=1)  # p_in itself lies on a checked edge of the path
        for row, c in enumerate(todo):
            if ok[row]:
                blends[c] = curve[row]
        todo = todo[~ok]
        d[todo] *= 0.5
        if len(todo) == 0:
            break
    pieces = [path[:1]]
    for c in range(n_corner):
        pieces.append(blends[c] if blends[c] is not None else path[c + 1:c + 2])
    pieces.append(path[-1:])
    return _drop_duplicates(np.concatenate(pieces))


# ----------------------------------------------------------------------------------------------
# Time parameterization with velocity / acceleration / jerk limits (TOPP-free)
# ----------------------------------------------------------------------------------------------
def _per_joint(x, dof, name):
    x = np.broadcast_to(np.asarray(x, dtype=np.float64), (dof,)).copy()
    if not np.all(x > 0):
        raise ValueError(f"{name} must be > 0 for every joint, got {x}")
    return x


def filter_kernel(v_max, a_max, j_max, dt):
    """Impulse response of two moving averages, (n_acc + n_jerk - 1,), summing to 1.

    Averaging a velocity sequence over n_acc steps turns any jump of at most v_max into a ramp of
    slope <= v_max / (n_acc dt) <= a_max; averaging again over n_jerk steps turns each acceleration
    step into a ramp of slope <= a_max / (n_jerk dt) <= j_max (the FIR form of an S-curve).
    """
    # >>> exercise 11: time parameterization under speed, acceleration and jerk limits (Sec. V)
    n_acc = int(math.ceil(np.max(v_max / (a_max * dt)) - 1e-9))
    n_jerk = int(math.ceil(np.max(a_max / (j_max * dt)) - 1e-9))
    return np.convolve(np.ones(n_acc) / n_acc, np.ones(n_jerk) / n_jerk)
    # <<< exercise 11


def handoff_point(q0, v0, kernel, dt):
    """Where the filter input must start so that the output starts at q0 with velocity v0.

    The filter input is taken to have moved at v0 forever before t = 0, so the output begins at
    velocity v0 with zero acceleration. That history adds v0 * dt * (mean delay of the kernel) to
    the total displacement, so the input path starts that far ahead of q0, along v0 (a "coast").
    """
    delay = np.sum(np.arange(len(kernel)) * kernel)  # mean delay in steps
    return np.asarray(q0, dtype=np.float64) + np.asarray(v0, dtype=np.float64) * dt * delay


def time_parameterize(path, v_max, a_max, j_max, dt, v0=None, in_collision=None, resolution=None,
                      max_repairs=60, repair_factor=0.7, min_speed_factor=1e-2):
    """Samples (T, dof) of a trajectory along `path` at the step dt, within per-joint limits.

    Finite differences at dt of the samples, with sample -1 = q0 - v0 dt (and constant velocity
    before that), satisfy |v| <= v_max, |a| <= a_max, |jerk| <= j_max at EVERY sample; the first
    sample is path[0] moving at v0, the last is path[-1] at rest.

    Method (no TOPP-RA): (1) traverse the polyline at full speed (the most constrained joint at its
    v_max; per-joint speed is then <= v_max on every piece), sampled at dt -> input velocities w;
    (2) prepend the handoff history (w = v0 before t = 0) and filter w with `filter_kernel`, whose
    two moving averages bound acceleration and jerk; integrate to positions. The input starts at
    `handoff_point` and then follows path[1:] (the caller plans path[1:] from that point).
    (3) Verify every sample (limits and, if in_collision is given, every output edge at
    `resolution`); where a sample fails, slow the input down by repair_factor over the time window
    that sample depends on (and, near a moving handoff, wait at the handoff point a step longer),
    and repeat. The filter cuts corners by at most the path length traversed within one kernel
    window, so slowing down also shrinks any colliding corner cut. Raises PlanningFailed if a
    piece had to go below min_speed_factor of full speed or after max_repairs rounds.
    A straight rest-to-rest move takes L / v_max + (n_acc + n_jerk - 2) dt: an S-curve's time.
    """
    path = np.atleast_2d(np.asarray(path, dtype=np.float64))
    dof = path.shape[1]
    v_max, a_max, j_max = (_per_joint(x, dof, n) for x, n in
                           ((v_max, "v_max"), (a_max, "a_max"), (j_max, "j_max")))
    if dt <= 0:
        raise ValueError(f"dt must be > 0, got {dt}")
    v0 = np.zeros(dof) if v0 is None else np.asarray(v0, dtype=np.float64)
    if v0.shape != (dof,) or np.any(np.abs(v0) > v_max * (1 + 1e-9)):
        raise ValueError(f"v0 must have shape ({dof},) and |v0| <= v_max={v_max}, got {v0}")
    kernel = filter_kernel(v_max, a_max, j_max, dt)
    L = len(kernel)
    q0 = path[0]
    start = handoff_point(q0, v0, kernel, dt)
    verts = _drop_duplicates(np.concatenate([start[None], path[1:] if len(path) > 1 else path]))
    if len(verts) == 1:
        return path[:1].copy()
    # Densify so that slow-downs act locally: pieces of at most dt / 2 at full speed.
    seg_time = np.max(np.abs(np.diff(verts, axis=0)) / v_max, axis=1)  # (S,) s at full speed
    m = np.maximum(1, np.ceil(seg_time / (0.5 * dt))).astype(int)
    u = np.concatenate([np.arange(k) / k for k in m] + [[1.0]])  # fraction along each segment
    seg = np.concatenate([np.full(k, i) for i, k in enumerate(m)] + [[len(m) - 1]])
    verts = verts[seg] + u[:, None] * (verts[np.minimum(seg + 1, len(verts) - 1)] - verts[seg])
    piece_time = np.repeat(seg_time / m, m)  # (P,)
    slow = np.ones(len(piece_time))  # speed factor per piece, lowered by repairs
    # Input steps spent waiting at the handoff point before moving on. From a handoff at full
    # speed, reversing a joint at once needs an input velocity jump of more than v_max, which no
    # slow-down fixes; after n_acc + n_jerk steps of waiting the filter has come to rest there
    # (an S-curve stop), and any direction is feasible.
    dwell, max_dwell = 0, L + 1 if np.any(v0) else 0
    for _ in range(max_repairs + 1):
        t_vert = np.concatenate([[0.0], np.cumsum(piece_time / slow)])  # (P + 1,) input time
        K = int(math.ceil(t_vert[-1] / dt - 1e-9)) + dwell
        times = np.clip((np.arange(K + 1) - dwell) * dt, 0.0, t_vert[-1])
        x = np.stack([np.interp(times, t_vert, verts[:, j]) for j in range(dof)], axis=1)
        w = np.diff(x, axis=0) / dt  # (K, dof) input velocity, <= v_max per joint
        w_ext = np.concatenate([np.repeat(v0[None], L - 1, 0), w, np.zeros((L - 1, dof))])
        y = np.stack([np.convolve(w_ext[:, j], kernel, "valid") for j in range(dof)], axis=1)
        samples = q0 + np.concatenate([np.zeros((1, dof)), np.cumsum(y * dt, axis=0)])  # (T, dof)
        # >>> exercise 11: time parameterization under speed, acceleration and jerk limits (Sec. V)
        # Finite differences seen by the env, from sample -1 (q0 - v0 dt) to rest after the end.
        vel = np.concatenate([v0[None], v0[None], y, np.zeros((1, dof))])  # samples -1 .. T
        acc = np.diff(vel, axis=0) / dt  # acc[i] at sample i
        jerk = np.diff(acc, axis=0) / dt  # jerk[i] at sample i + 1
        bad = [np.flatnonzero(np.any(np.abs(vel) > v_max * (1 + 1e-9), axis=1)) - 1,
               np.flatnonzero(np.any(np.abs(acc) > a_max * (1 + 1e-9), axis=1)),
               np.flatnonzero(np.any(np.abs(jerk) > j_max * (1 + 1e-9), axis=1)) + 1]
        if in_collision is not None:
            free = edges_free(samples[:-1], samples[1:], in_collision, resolution)
            bad.append(np.flatnonzero(~free) + 1)
        bad = np.unique(np.concatenate(bad))
        # <<< exercise 11
        if len(bad) == 0:
            samples[-1] = path[-1]  # remove float round-off of the cumulative sum at the goal
            return samples
        # The failing sample k depends on input steps k - L - 1 .. k, i.e. input times in
        # [(k - L - 2 - dwell) dt, (k - dwell) dt]: slow every piece overlapping such a window,
        # and wait longer at the handoff if the failure is within reach of it.
        if dwell < max_dwell and bad.min() <= dwell + L + 2:
            dwell += 1
        lo, hi = (bad - L - 2 - dwell) * dt, (bad - dwell) * dt
        hit = np.any((t_vert[1:, None] > lo) & (t_vert[:-1, None] < hi), axis=1)
        slow[hit] *= repair_factor
        if slow.min() < min_speed_factor:
            break
    raise PlanningFailed(f"time parameterization: samples {bad[:5].tolist()} still violate limits "
                         f"or collide after slowing down to {slow.min():.3g} of full speed")


# ----------------------------------------------------------------------------------------------
# HG-DAgger gate helpers (env-generic)
# ----------------------------------------------------------------------------------------------
def rollout_chunk(env, chunk, q=None):
    """States (H + 1, dof) the env would visit executing `chunk` (H, dof) of absolute targets.

    The env's motion rule (envs.ArmEnv.clip_action):
    q_next = clip(q + clip(action - q, -max_step, max_step), lo, hi).
    """
    # >>> exercise 12: the HG-DAgger gate: predicted collision or stall (Sec. IV-A)
    lo, hi = env.joint_limits
    q = env.q if q is None else np.asarray(q, dtype=np.float64)
    states = [q]
    for action in np.asarray(chunk, dtype=np.float64):
        q = np.clip(q + np.clip(action - q, -env.max_step, env.max_step), lo, hi)
        states.append(q)
    return np.array(states)
    # <<< exercise 12


def stalled(distances, window, min_progress):
    """True if the best distance to the goal over the last `window` steps is not at least
    `min_progress` better than the best one before them (False while the history is shorter)."""
    # >>> exercise 12: the HG-DAgger gate: predicted collision or stall (Sec. IV-A)
    if len(distances) <= window:
        return False
    d = np.asarray(distances, dtype=np.float64)
    return bool(d[-window:].min() > d[:-window].min() - min_progress)
    # <<< exercise 12


@dataclass
class Plan:
    samples: np.ndarray  # (T, dof) trajectory at env.dt; samples[0] = start, samples[-1] = goal
    path: np.ndarray  # (N, dof) the smoothed geometric path it follows
    ee_length: float  # end-effector arc length of `path` (the selection criterion)
    velocity_matched: bool  # False if the handoff velocity had to be dropped (abrupt stop)
    planning_time: float  # s, wall clock (informative only; never used in a decision)


class Gate:
    """Per-episode HG-DAgger gate (one per env in a batched rollout), the authors' triggers
    (PAPER_SETUP.md §3). Create it right after env.reset (oracle.gate(env, rng)), call
    record(env, by_expert) after every env step whoever drove it, and should_intervene(env, pending)
    before every policy step with the policy's pending actions."""

    def __init__(self, oracle, env, rng=None):
        self.oracle = oracle
        self.rng = rng if rng is not None else np.random.default_rng(oracle.cfg.seed)
        self.distances = []  # ee distance to the goal at every recorded step
        self.policy_steps = 0  # steps the policy drove (time triggers count these)
        self.interventions = 0  # taken so far (at most cfg.max_interventions)
        self.next_time_trigger = oracle.cfg.time_trigger_first
        self.record(env, by_expert=True)

    def record(self, env, by_expert=False):
        ee = env.ee(env.q[None])[0]
        self.distances.append(float(np.linalg.norm(ee - env.goal)))
        self.policy_steps += 0 if by_expert else 1

    def should_intervene(self, env, chunk):
        """'collision', 'stall', 'time' or None; None once max_interventions were taken."""
        c = self.oracle.cfg
        if self.interventions >= c.max_interventions:
            return None
        reason = self.oracle.should_intervene(env, chunk, self.distances)
        if reason is None and self.policy_steps >= self.next_time_trigger:
            reason = "time"
            lo, hi = c.time_trigger_every
            self.next_time_trigger = self.policy_steps + int(self.rng.integers(lo, hi + 1))
        return reason

    def rewind_steps(self, n_recorded):
        """Steps to rewind before a stall or time intervention (at most n_recorded)."""
        lo, hi = self.oracle.cfg.rewind_steps
        return min(int(self.rng.integers(lo, hi + 1)), n_recorded)

    def rewound(self, n):
        """Forget the last n recorded steps (the env was put back n steps)."""
        if n:
            del self.distances[-n:]


# ----------------------------------------------------------------------------------------------
# The oracle
# ----------------------------------------------------------------------------------------------
class Oracle:
    """Deterministic RRT expert: demonstrations (D0) and HG-DAgger interventions (D1..DK)."""

    def __init__(self, config: OracleConfig | None = None):
        self.cfg = config or OracleConfig()
        if not self.cfg.margin > self.cfg.verify_margin >= 0.5:
            raise ValueError(f"OracleConfig needs margin > verify_margin >= 0.5 (sweeps: see the "
                             f"module docstring), got margin={self.cfg.margin}, "
                             f"verify_margin={self.cfg.verify_margin}")
        self.last_plan = None  # the most recent Plan (for benchmarks and figures)

    def sweep(self, env):
        """Max arm-point motion (m) between collision checks (OracleConfig.sweep_tolerance)."""
        if self.cfg.sweep_tolerance is not None:
            return self.cfg.sweep_tolerance
        if not hasattr(env, "link_radius"):
            raise ValueError("env has no link_radius: set OracleConfig.sweep_tolerance (m)")
        return 0.5 * env.link_radius

    def limits(self, env):
        """Per-joint (v_max, a_max, j_max) of the expert, in rad/s, rad/s^2, rad/s^3."""
        c = self.cfg
        v_max = np.full(env.dof, c.speed_fraction * env.max_step / env.dt)
        return v_max, np.full(env.dof, c.a_max), np.full(env.dof, c.j_max)

    def ee_length(self, env, path):
        """End-effector arc length of a joint-space polyline (edges interpolated finely)."""
        states, _, _, _ = interpolate_edges(path[:-1], path[1:], edge_resolution(
            env, self.sweep(env)))
        pts = env.ee(np.concatenate([path[:1], states]))
        return float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))

    def plan(self, env, q0, v0, rng):
        """Plan from q0 moving at v0 to the env's goal: IK, RRT-Connect attempts, shortcutting and
        corner smoothing, pick the minimum ee arc length, time-parameterize. Raises PlanningFailed.

        Handoff (Sec. V, "match the policy's induced pose and velocity"): the geometric plan starts
        at handoff_point(q0, v0) -- where the arm coasts while the filter absorbs v0 -- so the
        samples start at q0 with velocity exactly v0. If that coast leaves the joint limits or
        collides, or the handoff cannot be time-parameterized without collision, the handoff
        velocity is dropped (v0 = 0, an abrupt stop the env allows) and velocity_matched says so.
        """
        c, t0 = self.cfg, time.perf_counter()
        q0 = np.asarray(q0, dtype=np.float64)
        v0 = np.zeros(env.dof) if v0 is None else np.asarray(v0, dtype=np.float64)
        sweep = self.sweep(env)
        res = edge_resolution(env, sweep)
        v_max, a_max, j_max = self.limits(env)
        v0 = np.clip(v0, -v_max, v_max)  # the env's speed limit already bounds it; round-off
        lo, hi = env.joint_limits
        start = handoff_point(q0, v0, filter_kernel(v_max, a_max, j_max, env.dt), env.dt)
        coast = float(np.sum(np.abs(start - q0) * lever_arms(env)))  # m of arm motion
        matched = bool(np.all((start >= lo) & (start <= hi))) and not path_in_collision(
            np.stack([q0, start]), env.in_collision, res)
        if not matched:
            v0, start, coast = np.zeros(env.dof), q0, 0.0
        goals = solve_ik(env, env.goal, rng, q_start=start, n_seeds=c.n_ik_seeds, iters=c.ik_iters,
                         damping=c.ik_damping, tolerance=c.ik_tolerance, max_goals=c.max_goals,
                         dedup=c.goal_dedup)
        if len(goals) == 0:
            raise PlanningFailed("no collision-free IK solution for the goal")
        # Narrow passages can be closed by the margin: then search again with checks twice as
        # dense and margins (in sweeps) twice as thin, down to min_sweep_fraction of the sweep.
        failures = []
        while True:
            try:
                best, verify, res = self._search(env, q0, coast, start, goals, sweep, rng)
                break
            except PlanningFailed as e:
                failures.append(f"sweep {sweep:.4g} m: {e.reason}")
                sweep *= 0.5
                if sweep < c.min_sweep_fraction * self.sweep(env) - 1e-12:
                    raise PlanningFailed("; ".join(failures)) from None
        path = best[0] if not np.any(v0) else np.concatenate([q0[None], best[0]])
        try:
            samples = time_parameterize(path, v_max, a_max, j_max, env.dt, v0=v0,
                                        in_collision=verify, resolution=res)
        except PlanningFailed:
            if not np.any(v0):
                raise
            matched = False  # the S-curve stop of the handoff collides: stop abruptly instead
            samples = time_parameterize(path, v_max, a_max, j_max, env.dt, v0=None,
                                        in_collision=verify, resolution=res)
        self.last_plan = Plan(samples, best[0], best[1], matched, time.perf_counter() - t0)
        return self.last_plan

    def _search(self, env, q0, coast, start, goals, sweep, rng):
        """RRT-Connect attempts + shortcut + corners at one check density; the plan with the
        smallest ee arc length. Returns ((path, length), verify predicate, resolution)."""
        c = self.cfg
        res = edge_resolution(env, sweep)  # verification of the executed trajectory
        # Planning checks lie 2 (margin - verify_margin) sweeps of arm motion apart: every state
        # between two of them is within half that of one, so the planned polyline keeps a
        # clearance >= verify_margin sweeps everywhere (and passes the verification below).
        plan_res = edge_resolution(env, 2 * (c.margin - c.verify_margin) * sweep)
        # Margins everywhere except near q0 (and its coast) and near the goal configurations.
        zones = np.concatenate([q0[None], goals])
        radii = np.concatenate([[coast], np.zeros(len(goals))]) + c.relax_sweeps * sweep
        collides = with_margin(env, c.margin * sweep, zones, radii)
        verify = with_margin(env, c.verify_margin * sweep, zones, radii)
        best, failures = None, []
        for attempt, seed in enumerate(rng.integers(0, 2 ** 63, size=c.n_attempts)):
            attempt_rng = np.random.default_rng(seed)
            try:
                path = rrt_connect(start, goals, collides, env.joint_limits, attempt_rng,
                                   step_size=c.step_size, resolution=plan_res,
                                   max_iters=c.max_iters, max_time=c.max_time, batch=c.rrt_batch)
            except PlanningFailed as e:
                if attempt == 0:  # a full budget found nothing: more attempts rarely would
                    raise
                failures.append(e.reason)
                continue
            direct = len(path) == 2  # a straight line: every attempt would return the same one
            path = shortcut(path, collides, attempt_rng, c.shortcut_iters, plan_res)
            path = smooth_corners(path, collides, plan_res, c.corner_fraction, c.corner_points)
            length = self.ee_length(env, path)
            if best is None or length < best[1]:  # strict: ties keep the earlier attempt
                best = (path, length)
            if direct:
                break
        return best, verify, res

    # ---- D0: full demonstrations ----------------------------------------------------------
    def demonstrate(self, env, seed):
        """An expert episode for scenario `seed`; raises PlanningFailed.

        The plan's samples are the absolute joint targets, executed with env.step until the env
        terminates (goal reached or collision) or truncates. The episode dict holds 'obs' (T,
        obs_dim), 'q', 'action' (T, dof), 'expert' (T,) all True, 'seed', and 'success' (from the
        env): the format of envs.save_episodes.
        """
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng([self.cfg.seed, int(seed)])
        plan = self.plan(env, env.q, np.zeros(env.dof), rng)
        episode = {"obs": [], "q": [], "action": []}
        success = False
        for target in plan.samples[1:]:
            episode["obs"].append(obs)
            episode["q"].append(env.q)
            episode["action"].append(target)
            obs, _, terminated, truncated, info = env.step(target)
            success = info["success"]
            if terminated or truncated:
                break
        T = len(episode["q"])
        return {"obs": np.asarray(episode["obs"], dtype=np.float32).reshape(T, env.obs_dim),
                "q": np.asarray(episode["q"], dtype=np.float64).reshape(T, env.dof),
                "action": np.asarray(episode["action"], dtype=np.float64).reshape(T, env.dof),
                "expert": np.ones(T, dtype=bool), "seed": int(seed), "success": bool(success)}

    # ---- HG-DAgger gating --------------------------------------------------------------------
    def gate(self, env, rng=None):
        """A per-episode Gate for `env` (create it right after env.reset)."""
        return Gate(self, env, rng)

    def chunk_collides(self, env, chunk):
        """True if the next gate_lookahead steps of `chunk` (H, dof) from env.q come within
        gate_clearance (m) of a collision, checked at the edge resolution along every speed-limited
        step (the env moves straight within a step). Within gate_clearance of arm motion of the
        current state only the plain check applies: an arm already close to an obstacle may leave."""
        c = self.cfg
        states = rollout_chunk(env, chunk if c.gate_lookahead is None else chunk[:c.gate_lookahead])
        near = with_margin(env, c.gate_clearance, env.q[None], c.gate_clearance)
        return path_in_collision(states, near, edge_resolution(env, self.sweep(env)))

    def should_intervene(self, env, chunk, distances):
        """'collision' if the policy's chunk would collide, 'stall' if the ee made no progress
        toward the goal over the last stall_window steps (distances: one per step), else None."""
        # >>> exercise 12: the HG-DAgger gate: predicted collision or stall (Sec. IV-A)
        if self.chunk_collides(env, chunk):
            return "collision"
        if stalled(distances, self.cfg.stall_window, self.cfg.stall_progress):
            return "stall"
        return None
        # <<< exercise 12

    def intervention(self, env, rng=None):
        """Absolute joint targets (L, dof) for the expert to drive from the current state.

        Plans from env.q with the current velocity (env.q - env.q_prev) / env.dt matched at the
        handoff, then drives a random number of steps in cfg.handback_steps (the authors' human
        stand-in, PAPER_SETUP.md §3), or the whole plan if it is shorter, and hands back. The
        plan is deterministic (its rng is seeded by cfg.seed and the state); `rng` draws the
        hand-back length (default: seeded like the plan). Raises PlanningFailed.
        """
        q, q_prev = env.q, env.q_prev
        state_key = np.frombuffer(np.concatenate([q, q_prev]).tobytes(), dtype=np.uint32)
        plan_rng = np.random.default_rng([self.cfg.seed, *state_key.tolist()])
        plan = self.plan(env, q, (q - q_prev) / env.dt, plan_rng)
        lo, hi = self.cfg.handback_steps
        steps = int((rng if rng is not None else plan_rng).integers(lo, hi + 1))
        return plan.samples[1:steps + 1]


# ----------------------------------------------------------------------------------------------
# Figure 5 (planar part): a scenario with an expert demonstration drawn over it
# ----------------------------------------------------------------------------------------------
def plot_demonstration(env, episode, path, n_arms=8):
    """Save the scene of episode['seed'] with faded arms along the demo and the ee path.

    Arms are drawn by env.render(ax, q=..., alpha=..., color=..., show_scene=False) when the env
    offers those options (links to scale), else as fk polylines.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env.reset(seed=int(episode["seed"]))
    q = np.asarray(episode["q"])
    pts = env.fk(q)  # (T, n_points, dim)
    if pts.shape[-1] != 2:
        raise ValueError(f"plot_demonstration draws planar envs (dim 2), got dim {pts.shape[-1]}")
    fig, ax = plt.subplots(figsize=(5, 5))
    env.render(ax)  # scene and the arm at the start
    for i, t in enumerate(np.linspace(0, len(q) - 1, n_arms).astype(int)[1:], start=1):
        alpha = 0.15 + 0.6 * i / max(1, n_arms - 1)
        env.render(ax, q=q[t], alpha=alpha, color="tab:orange", show_scene=False)
    ax.plot(pts[:, -1, 0], pts[:, -1, 1], color="tab:red", lw=1.5, label="end-effector path")
    ax.set_aspect("equal")
    ax.set_title(f"expert demonstration, seed {episode['seed']} ({len(q)} steps; start in blue)")
    ax.legend(loc="lower left", fontsize=8)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


# ==== Beyond the paper (safe to skip) ====================================================
# The edge checks that every planning step above relies on, and a yardstick for the time
# parameterization.
#
# Why the edge checks cannot miss an obstacle. For a serial arm, a joint-space step dq moves any
# point of the arm by at most  sum_j R_j |dq_j|,  where R_j bounds the distance from joint j to the
# farthest point of the arm beyond it (the arm beyond joint j rotates about it).
# We interpolate every edge so that consecutive checked states satisfy sum_j R_j |dq_j| <= s (the
# check spacing, m), i.e. sum_j |dq_j| / eps_j <= 1 with eps_j = s / R_j (`edge_resolution`); R_j
# comes from env.fk (`lever_arms`), not from planar constants. (A Euclidean spacing |dq| <= eps is
# safe only for eps <= s / |R| (Cauchy-Schwarz), and then checks more states, never fewer.) Every
# state between two checks is within s / 2 of arm motion of one of them, so if every checked state
# keeps a clearance c >= s / 2 -- the env's check with obstacles inflated by c (`with_margin`) --
# every state of the edge is collision-free. Self-collisions too: in the frame of the lower of two
# links only the joints after it move the other one, with the same lever arms. Planning keeps a
# margin m and spaces its checks s = 2 (m - v) apart, so the planned path keeps a clearance >= v
# everywhere; the executed trajectory is verified with margin v at a spacing <= 2 v (OracleConfig:
# margin, verify_margin). Only near the start and the goal configurations the plain check applies
# (`with_margin` says why). Edges are checked in rounds of batched calls and stop at their first
# collision (`edge_free_fraction`, `edges_free`): most RRT-Connect edges collide early, and
# checking the rest of them was ~98 % of the planner's checks.


# ----------------------------------------------------------------------------------------------
# Geometry helpers: lever arms, edge interpolation, batched edge checks
# ----------------------------------------------------------------------------------------------
def lever_arms(env, n_probe=8):
    """R_j (dof,): bound on the distance from joint j to any point of the arm beyond it.

    Segment lengths between consecutive fk points are constant for a rigid serial chain; we take
    their maximum over the zero pose and a few probe poses (a fixed probe seed, so the bound is
    deterministic). If fk returns one point per joint plus the end effector, joint j sits at point
    j and R_j = sum of the segment lengths after it; otherwise every R_j = the total chain length
    (the maximal reach), which is always a valid, if looser, bound. An env whose bodies reach past
    its fk points (the planar gripper's finger corners) gives the bound itself: env.lever_arms.
    """
    if hasattr(env, "lever_arms"):  # an env that knows its body's extent beyond the chain points
        return np.asarray(env.lever_arms, dtype=np.float64).copy()
    lo, hi = env.joint_limits
    probe_rng = np.random.default_rng(0)  # geometry probe only, not a planning decision
    qs = np.concatenate([np.zeros((1, env.dof)), probe_rng.uniform(lo, hi, (n_probe, env.dof))])
    points = env.fk(qs)  # (B, n_points, dim)
    seg = np.linalg.norm(np.diff(points, axis=1), axis=-1).max(axis=0)  # (n_points - 1,)
    if len(seg) == env.dof:
        return np.cumsum(seg[::-1])[::-1].copy()  # R_j = sum_{i >= j} seg_i
    return np.full(env.dof, seg.sum())


def edge_resolution(env, sweep_tolerance):
    """eps_j (dof,) in rad: an edge is checked at states with sum_j |dq_j| / eps_j <= 1 apart,
    so that no point of the arm moves more than sweep_tolerance (m) between two checks."""
    if not sweep_tolerance > 0:
        raise ValueError(f"sweep_tolerance must be > 0 (m), got {sweep_tolerance}")
    return sweep_tolerance / lever_arms(env)


def interpolate_edges(q_from, q_to, resolution):
    """States along straight edges, spaced so that sum_j |dq_j| / resolution_j <= 1.

    q_from, q_to: (E, dof). Returns states (P, dof), their edge index (P,), their sub-step k (P,)
    and each edge's sub-step count n (E,): the states at fractions k / n, k = 1 .. n, of each
    edge (the start of an edge is assumed checked already).
    """
    dq = q_to - q_from  # (E, dof)
    n = np.maximum(1, np.ceil(np.sum(np.abs(dq) / resolution, axis=1) - 1e-9)).astype(int)  # (E,)
    edge, k = substeps(n)
    return q_from[edge] + (k / n[edge])[:, None] * dq[edge], edge, k, n


def substeps(n):
    """Edge index (P,) and sub-step k = 1 .. n_e (P,) of every sub-step of edges with n (E,)
    sub-steps each, edge by edge (P = n.sum())."""
    edge = np.repeat(np.arange(len(n)), n)  # (P,)
    first = np.cumsum(n) - n  # index of each edge's first sub-step
    return edge, np.arange(n.sum()) - np.repeat(first, n) + 1


def _check_in_rounds(states, edge, rounds, in_collision, n_edges):
    """in_collision of states (P, dof) of n_edges edges, one batched call per round (0, 1, ...).

    States of an edge that already collided in an earlier round are skipped (reported free): an
    edge needs only one collision to be rejected, and a planner's edges mostly collide early.
    Returns hit (P,) bool.
    """
    hit = np.zeros(len(states), dtype=bool)
    blocked = np.zeros(n_edges, dtype=bool)
    for r in range(int(rounds.max(initial=-1)) + 1):
        todo = np.flatnonzero((rounds == r) & ~blocked[edge])
        if len(todo):
            hit[todo] = in_collision(states[todo])
            blocked[edge[todo[hit[todo]]]] = True
    return hit


def edge_free_fraction(q_from, q_to, in_collision, resolution, first_round=4):
    """(E,) fraction of each edge q_from -> q_to that is collision-free from its start (1 = all).

    The states of every edge are checked in order, in rounds of doubling length (first_round,
    then 2x, 4x, ... states of every edge still free; one batched in_collision call per round),
    and an edge is no longer checked after its first collision: RRT-Connect's CONNECT edges run
    across the whole space and nearly all hit an obstacle early (checking every state of them
    spent ~98 % of the oracle's checks). Each edge reports the last free sub-step before its
    first colliding one. With doubling rounds, the states checked past that sub-step are at
    most about as many as those before it (plus first_round), in log2(edge length) calls.
    first_round = 4 planned faster than 8 or 16 on the planar scenes (measured: fewer wasted
    states; more calls would cost more, one call costs as much as a few hundred states there).
    """
    q_from, q_to = np.atleast_2d(q_from), np.atleast_2d(q_to)
    states, edge, k, n = interpolate_edges(q_from, q_to, resolution)
    # (P,) round of sub-step k (first_round 4): k = 1..4 -> 0, 5..12 -> 1, 13..28 -> 2, ...
    rounds = np.floor(np.log2((k - 1) / first_round + 1)).astype(int)
    hit = _check_in_rounds(states, edge, rounds, in_collision, len(n))
    first_hit = n + 1  # (E,) sub-step of the first collision; n + 1 = none
    np.minimum.at(first_hit, edge[hit], k[hit])
    return (first_hit - 1) / n


def edges_free(q_from, q_to, in_collision, resolution, coarse=4):
    """(E,) True where the whole edge q_from -> q_to is collision-free.

    Coarse to fine: every coarse-th state of all edges first (one batched call), then the
    remaining states of the edges not yet found colliding (a second call). An obstacle usually
    blocks a run of consecutive states, so most colliding edges are rejected by the coarse pass
    (coarse = 2, 4 or 8 planned equally fast on the planar scenes).
    """
    q_from, q_to = np.atleast_2d(q_from), np.atleast_2d(q_to)
    states, edge, k, n = interpolate_edges(q_from, q_to, resolution)
    rounds = (k % coarse != 0).astype(int)  # (P,) 0: the coarse pass, 1: the rest
    hit = _check_in_rounds(states, edge, rounds, in_collision, len(n))
    return ~np.bincount(edge[hit], minlength=len(n)).astype(bool)


def with_margin(env, margin, relax_at=None, relax_radius=0.0):
    """A stricter collision predicate for planning: True within ~margin (m) of a collision.

    Shortest paths hug obstacles, and two free checks s apart (in arm motion) do not rule out a
    graze between them (by the lever-arm bound a point moves at most s/2 from the nearer check,
    so it can dip up to s/2 into an obstacle). Planning against obstacles inflated by
    margin >= s/2 makes every interpolated state between two checks truly free. If
    env.in_collision accepts a `margin` keyword (distance inflation), it is used; otherwise the
    margin is approximated by probes: q counts as colliding if q or one of its 2 dof one-joint
    displacements of +-margin / R_j collides (each moves the arm by at most `margin`).
    Near relax_at (K, dof) (arm motion sum_j R_j |q_j - relax_at_kj| <= relax_radius_k for some
    k, in m) only the plain env check applies: a start inside the margin band (an intervention
    often begins close to an obstacle) must be able to leave it, and a goal configuration
    squeezed between obstacles must be reachable; grazes (at most s/2 deep) are then possible
    only in these zones.
    """
    lever = lever_arms(env)
    relax_at = None if relax_at is None else np.atleast_2d(relax_at)
    try:
        env.in_collision(np.zeros((1, env.dof)), margin=margin)
        inflated = lambda q: env.in_collision(q, margin=margin)  # noqa: E731
    except TypeError:
        step = margin / lever  # (dof,) rad
        offsets = np.concatenate([np.zeros((1, env.dof)), np.diag(step), -np.diag(step)])

        def inflated(q):  # (B, dof) -> (B,)
            probes = (q[:, None, :] + offsets).reshape(-1, env.dof)  # (B * (2 dof + 1), dof)
            return env.in_collision(probes).reshape(len(q), -1).any(axis=1)

    def in_collision(q):
        q = np.atleast_2d(q)
        if relax_at is None:
            return inflated(q)
        hit = inflated(q)
        # only states that hit with the margin can differ under the plain check (a second call)
        motion = np.sum(np.abs(q[hit, None] - relax_at[None]) * lever, axis=2)  # (hits, K)
        near = np.flatnonzero(hit)[np.any(motion <= relax_radius, axis=1)]  # radius () or (K,)
        if len(near):
            hit[near] = env.in_collision(q[near])
        return hit

    return in_collision


def path_in_collision(path, in_collision, resolution):
    """True if any edge of the polyline path (N, dof) or its first state collides."""
    path = np.atleast_2d(path)
    if in_collision(path[:1])[0]:
        return True
    if len(path) < 2:
        return False
    return not np.all(edges_free(path[:-1], path[1:], in_collision, resolution))


def min_time_lower_bound(path, v_max, a_max):
    """Lower bound (s) on any rest-to-rest traversal of `path`: the slowest joint's bang-bang time.

    Joint j must travel at least its total variation D_j along the path with |v| <= v_max_j and
    |a| <= a_max_j, which takes at least the trapezoid time D/v + v/a (or 2 sqrt(D/a) if the joint
    never reaches v_max). Jerk limits and path shape only add to it.
    """
    path = np.atleast_2d(np.asarray(path, dtype=np.float64))
    dof = path.shape[1]
    v_max, a_max = _per_joint(v_max, dof, "v_max"), _per_joint(a_max, dof, "a_max")
    travel = np.sum(np.abs(np.diff(path, axis=0)), axis=0)  # (dof,)
    cruise = travel >= v_max ** 2 / a_max
    t = np.where(cruise, travel / v_max + v_max / a_max, 2 * np.sqrt(travel / a_max))
    return float(t.max())


if __name__ == "__main__":
    import os

    import envs

    env = envs.make_env("planar")
    oracle = Oracle()
    seed = env.eval_seeds()[0]
    t0 = time.perf_counter()
    episode = oracle.demonstrate(env, seed)
    plan = oracle.last_plan
    v_max, a_max, _ = oracle.limits(env)
    print(f"seed {seed}: success {episode['success']}, {len(episode['q'])} steps, "
          f"planning {plan.planning_time:.2f} s, total {time.perf_counter() - t0:.2f} s, "
          f"ee arc length {plan.ee_length:.2f} m, duration / bang-bang bound "
          f"{(len(plan.samples) - 1) * env.dt / min_time_lower_bound(plan.path, v_max, a_max):.2f}")
    # an intervention: the arm 30 % into the demo, drifted off it and moving
    t = int(0.3 * len(episode["q"]))
    q, step = episode["q"][t] + 0.1, episode["q"][t] - episode["q"][t - 1]
    env.set_state(q, q - step)
    gate = oracle.gate(env)
    reason = gate.should_intervene(env, episode["action"][t:t + oracle.cfg.horizon])
    print(f"gate on the expert's old chunk from the drifted state: {reason}")
    actions = oracle.intervention(env)
    print(f"intervention from a drifted state: drives {len(actions)} steps, handoff velocity "
          f"matched: {oracle.last_plan.velocity_matched}")
    os.makedirs("runs", exist_ok=True)
    plot_demonstration(env, episode, os.path.join("runs", "oracle_demo.png"))
    print("wrote runs/oracle_demo.png")
