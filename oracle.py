"""The RRT oracle expert (paper Sec. V; the gate of Sec. IV-A; the authors' setup: benchmarks/SETUP.md §3).

A deterministic planner with privileged simulator information stands in for HG-DAgger's human, for any serial
arm behind the env interface of envs.py. In the paper's order:

  solve_ik            goal configurations: damped least squares from many seeds
  edge checks         lever-arm spacing and a clearance margin, so that no check misses an obstacle
  rrt_connect         bidirectional RRT-Connect in joint space, batched edge checks, several goals
  shortcut            random shortcutting (after one greedy batched pass)
  smooth_corners      quadratic-Bezier corner rounding (no separate trajectory optimization)
  time_parameterize   speed / acceleration / jerk limits without TOPP-RA: a double moving-average filter
  Gate, Oracle        demonstrations (D0); the HG-DAgger gate and interventions that hand back early
  plot_demonstration  Fig. 5: a scene with an expert demonstration
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np


class PlanningFailed(RuntimeError):
    """The planner found no plan within its budget (or the problem has none); `reason` says why."""

    def __init__(self, reason):
        super().__init__(reason)
        self.reason = reason


@dataclass
class OracleConfig:
    """The authors' planner and gate (benchmarks/SETUP.md §3), counts in our 10 Hz steps (theirs: 30 Hz frames). A
    sweep: Oracle.sweep."""
    max_goals: int = 32  # IK goal configurations handed to the planner, nearest first (theirs: 32)
    speed_fraction: float = 1.0  # v_max = speed_fraction * env.max_step / env.dt (theirs: 0.5 rad/s)
    a_max: float = 1.0  # rad/s^2 per joint (theirs)
    j_max: float = 10.0  # rad/s^3 per joint (theirs)
    gate_lookahead: int | None = 3  # steps of the pending chunk the gate checks (theirs: 8 frames); None: all
    gate_clearance: float = 0.010  # m, just inside our planner's 0.011 m (theirs: 0.019 m inside their 0.02 m)
    stall_window: int = 40  # steps without stall_progress of ee progress to the goal: a stall (theirs: "stuck")
    stall_progress: float = 0.02  # m of ee progress that counts in the stall window
    time_trigger_first: int = 200  # policy steps before the first time trigger (theirs: 600 frames)
    time_trigger_every: tuple = (67, 100)  # policy steps between time triggers (theirs: 200-300 frames)
    rewind_steps: tuple = (17, 33)  # steps a stall or time trigger first rewinds (theirs: 50-100 frames)
    handback_steps: tuple = (20, 67)  # steps the expert drives, or its whole plan if shorter (theirs: 60-200)
    max_interventions: int = 5  # per episode (theirs: 5 per scenario)
    # our planner (its other knobs are the defaults of solve_ik, rrt_connect, shortcut and smooth_corners)
    seed: int = 0  # base seed of the planner's randomness (mixed with the scenario seed or the state)
    n_attempts: int = 3  # RRT-Connect runs per plan; the one with the smallest ee arc length wins
    max_iters: int = 500  # RRT iterations per attempt (a failure falls back to thinner margins instead)
    max_time: float = 10.0  # s per attempt: a guard against hanging, not the normal budget
    margin: float = 1.5  # sweeps of planning clearance; planning checks lie 2 (margin - verify_margin) sweeps apart
    verify_margin: float = 0.5  # sweeps the executed trajectory keeps (>= 0.5: no graze between its checks)
    relax_sweeps: float = 4.0  # sweeps of arm motion around the start and the goals with the plain check only
    min_sweep_fraction: float = 0.125  # no path: halve the sweep down to this fraction


# ---- Inverse kinematics (goal configurations) -------------------------------------------------
def solve_ik(env, goal, rng, max_goals, q_start, n_seeds=512, iters=40, damping=0.05, tolerance=1e-3,
             dedup=0.2, in_collision=None):
    """Free goal configurations (M <= max_goals, dof), nearest to q_start first: damped least squares from q_start
    and uniform seeds, kept within `tolerance` m of the goal, env.goal_reached, free (in_collision, default the
    env's) and over `dedup` rad (max-norm) apart. An env with env.goal_is_pose gives them in closed form."""
    in_collision = in_collision or env.in_collision
    goal = np.asarray(goal, dtype=np.float64)
    if env.goal_is_pose:
        q = env.goal_configurations()
    else:
        lo, hi = env.joint_limits
        q = rng.uniform(lo, hi, size=(n_seeds, env.dof))  # (S, dof)
        q[0] = q_start
        for _ in range(iters):
            # dq = J^T (J J^T + damping^2 I)^-1 (goal - ee(q)), clipped to the joint limits
            err = goal - env.ee(q)  # (S, dim)
            J = env.ee_jacobian(q)  # (S, dim, dof), central differences
            JJt = J @ J.transpose(0, 2, 1) + damping ** 2 * np.eye(J.shape[1])  # (S, dim, dim)
            dq = (J.transpose(0, 2, 1) @ np.linalg.solve(JJt, err[..., None]))[..., 0]  # (S, dof)
            q = np.clip(q + dq, lo, hi)
        close = np.linalg.norm(env.ee(q) - goal, axis=1) <= tolerance
        q = q[close & env.goal_reached(q)]
    q = q[~in_collision(q)] if len(q) else q
    q = q[np.argsort(np.linalg.norm(q - q_start, axis=1), kind="stable")]
    kept = []
    for cand in q:
        if all(np.max(np.abs(cand - k)) > dedup for k in kept):
            kept.append(cand)
        if len(kept) == max_goals:
            break
    return np.array(kept).reshape(-1, env.dof)


# ---- Collision checks along edges ---------------------------------------------------------------
# Why no check misses an obstacle: a joint step dq moves any arm point by at most sum_j R_j |dq_j| (`lever_arms`).
# Checks spaced so that no arm point moves more than s m between two (`edge_resolution`) leave every state of an
# edge within s/2 of a checked one, so obstacles inflated by a margin >= s/2 (`with_margin`) clear the whole edge.
# Planning: margin m, checks 2 (m - v) apart, so the plan keeps clearance v; the executed trajectory is verified
# with margin v. Edges stop at their first collision.
def lever_arms(env, n_probe=8):
    """R_j (dof,): a bound on the distance from joint j to any point of the arm beyond it: env.lever_arms if
    given, else sums of env.fk's segment lengths after joint j (largest over the zero pose and n_probe others)."""
    if hasattr(env, "lever_arms"):
        return np.array(env.lever_arms, dtype=np.float64)
    lo, hi = env.joint_limits
    probe_rng = np.random.default_rng(0)  # geometry probe only, not a planning decision
    qs = np.concatenate([np.zeros((1, env.dof)), probe_rng.uniform(lo, hi, (n_probe, env.dof))])
    seg = np.linalg.norm(np.diff(env.fk(qs), axis=1), axis=-1).max(axis=0)  # (dof,) segment lengths
    return np.cumsum(seg[::-1])[::-1].copy()  # R_j = sum_{i >= j} seg_i


def edge_resolution(env, sweep):
    """eps_j (dof,) rad: checks with sum_j |dq_j| / eps_j <= 1 apart move no arm point more than sweep m."""
    return sweep / lever_arms(env)


def interpolate_edges(q_from, q_to, resolution):
    """States (P, dof) at fractions k / n_e, k = 1 .. n_e, of the edges q_from -> q_to (E, dof), at most one
    `resolution` step apart; their edge index (P,), sub-step k (P,) and each edge's count n (E,)."""
    dq = q_to - q_from  # (E, dof)
    n = np.maximum(1, np.ceil(np.sum(np.abs(dq) / resolution, axis=1) - 1e-9)).astype(int)  # (E,)
    edge, k = substeps(n)
    return q_from[edge] + (k / n[edge])[:, None] * dq[edge], edge, k, n


def substeps(n):
    """Edge index (P,) and sub-step k = 1 .. n_e (P,) of every sub-step of edges with n (E,) sub-steps."""
    edge = np.repeat(np.arange(len(n)), n)  # (P,)
    first = np.cumsum(n) - n  # index of each edge's first sub-step
    return edge, np.arange(n.sum()) - np.repeat(first, n) + 1


def edge_free_fraction(q_from, q_to, in_collision, resolution, first_round=4):
    """(E,) fraction of each edge q_from -> q_to that is free from its start (1 = all). States in order, in rounds
    of doubling length (first_round, 2x, 4x, ... states of each edge still free): long CONNECT edges nearly all
    collide early, and an edge stops at its first collision."""
    q_from, q_to = np.atleast_2d(q_from), np.atleast_2d(q_to)
    states, edge, k, n = interpolate_edges(q_from, q_to, resolution)
    # (P,) round of sub-step k (first_round 4): k = 1..4 -> 0, 5..12 -> 1, 13..28 -> 2, ...
    rounds = np.floor(np.log2((k - 1) / first_round + 1)).astype(int)
    hit = np.zeros(len(states), dtype=bool)
    blocked = np.zeros(len(n), dtype=bool)
    for r in range(int(rounds.max(initial=-1)) + 1):
        todo = np.flatnonzero((rounds == r) & ~blocked[edge])  # states of edges that have not collided yet
        if len(todo):
            hit[todo] = in_collision(states[todo])
            blocked[edge[todo[hit[todo]]]] = True
    first_hit = n + 1  # (E,) sub-step of the first collision; n + 1 = none
    np.minimum.at(first_hit, edge[hit], k[hit])
    return (first_hit - 1) / n


def edges_free(q_from, q_to, in_collision, resolution):
    """(E,) True where the whole edge q_from -> q_to is collision-free."""
    return edge_free_fraction(q_from, q_to, in_collision, resolution) == 1.0


def path_in_collision(path, in_collision, resolution):
    """True if the first state of the polyline path (N, dof) or any of its edges collides."""
    path = np.atleast_2d(path)
    return bool(in_collision(path[:1])[0]) or not np.all(edges_free(path[:-1], path[1:], in_collision, resolution))


def with_margin(env, margin, relax_at=None, relax_radius=0.0):
    """The planner's predicate: True within margin (m) of a collision. Near relax_at (K, dof), within arm motion
    sum_j R_j |q_j - relax_at_kj| <= relax_radius (m, scalar or (K,)), only the plain check applies: a start in
    the margin band must be able to leave it, a goal squeezed between obstacles be reachable."""
    lever = lever_arms(env)
    relax_at = None if relax_at is None else np.atleast_2d(relax_at)

    def in_collision(q):
        q = np.atleast_2d(q)
        hit = env.in_collision(q, margin=margin)
        if relax_at is not None:
            # only states that hit with the margin can differ under the plain check (a second call)
            motion = np.sum(np.abs(q[hit, None] - relax_at[None]) * lever, axis=2)  # (hits, K)
            near = np.flatnonzero(hit)[np.any(motion <= relax_radius, axis=1)]
            if len(near):
                hit[near] = env.in_collision(q[near])
        return hit

    return in_collision


# ---- RRT-Connect (Kuffner & LaValle 2000), joint space, several goal roots ------------------------
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
        # |q - x|^2 = |x|^2 - 2 q.x + |q|^2, and |q|^2 is the same for every node x: one matrix product
        return np.argmin(self.sq_norm[:self.n] - 2 * q @ self.nodes[:self.n].T, axis=1)

    def branch(self, i):
        """Nodes from node i back to its root, (k, dof)."""
        out = []
        while i >= 0:
            out.append(self.nodes[i])
            i = self.parent[i]
        return np.array(out)


def _grow(tree, near, targets, free, step_size):
    """Add the free part (fraction free (E,)) of the edges near[i] -> targets[i] to `tree`, a node every
    step_size. Returns the index of each edge's last node (E,)."""
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
    """A free path (N, dof) from q_start to one of q_goals (M, dof), or PlanningFailed. Per iteration tree A
    EXTENDs toward `batch` uniform samples, tree B CONNECTs toward every new node; the trees swap. Edges checked at `resolution` (rad); max_time (s) is a hang guard."""
    q_start = np.asarray(q_start, dtype=np.float64)
    q_goals = np.atleast_2d(np.asarray(q_goals, dtype=np.float64))
    lo, hi = (np.asarray(x, dtype=np.float64) for x in joint_limits)
    if q_start.ndim != 1 or q_goals.shape[1:] != q_start.shape or step_size <= 0 or max_iters < 0 or batch < 1:
        raise ValueError(f"need q_start (dof,) and q_goals (M, dof), step_size > 0, max_iters >= 0, batch >= 1; "
                         f"got {q_start.shape}, {q_goals.shape}, {step_size}, {max_iters}, {batch}")
    if in_collision(q_start[None])[0]:
        raise PlanningFailed("start configuration is in collision")
    q_goals = q_goals[~in_collision(q_goals)]
    if len(q_goals) == 0:
        raise PlanningFailed("every goal configuration is in collision")
    # Straight lines first (one batched check): the common easy case costs a single call.
    free = edges_free(np.repeat(q_start[None], len(q_goals), 0), q_goals, in_collision, resolution)
    if np.any(free):
        direct = np.flatnonzero(free)
        best = direct[np.argmin(np.linalg.norm(q_goals[direct] - q_start, axis=1))]
        return np.stack([q_start, q_goals[best]])
    trees = [_Tree([q_start]), _Tree(q_goals)]  # [start tree, goal tree]
    t0 = time.perf_counter()
    for it in range(max_iters):
        if time.perf_counter() - t0 > max_time:
            raise PlanningFailed(f"time budget of {max_time} s exhausted after {it} iterations")
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
    raise PlanningFailed(f"no path within max_iters={max_iters}")


def _drop_duplicates(path, tol=1e-12):
    """Remove consecutive repeated states from a polyline (N, dof)."""
    keep = np.concatenate([[True], np.linalg.norm(np.diff(path, axis=0), axis=1) > tol])
    return path[keep]


# ---- Path post-processing: shortcutting and corner smoothing -------------------------------------
def shortcut(path, in_collision, rng, iters=64, resolution=0.05, batch=8):
    """A shorter free polyline with the same end points: a greedy pass (from each kept vertex to the farthest
    later one in free straight reach), then `iters` random proposals of two points along the path in batches;
    the free proposal of each batch that saves the most length is applied."""
    path = _drop_duplicates(np.asarray(path, dtype=np.float64))
    out, i = [path[0]], 0
    while i < len(path) - 1:
        later = np.arange(i + 1, len(path))
        free = edges_free(np.repeat(path[i][None], len(later), 0), path[later], in_collision, resolution)
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


def smooth_corners(path, in_collision, resolution=0.05, n_points=8, n_halvings=3):
    """Replace each interior vertex v (neighbours a, b) by a quadratic Bezier blend where it stays free:
    B(u) = (1-u)^2 p_in + 2u(1-u) v + u^2 p_out, p_in = v + d (a - v)/|a - v|, p_out likewise toward b, tangent
    to both edges. A blend that collides is retried with d halved, n_halvings times; then the sharp corner stays."""
    path = _drop_duplicates(np.asarray(path, dtype=np.float64))
    if len(path) < 3:
        return path
    v, a, b = path[1:-1], path[:-2], path[2:]  # (C, dof) each
    len_a = np.linalg.norm(a - v, axis=1)[:, None]
    len_b = np.linalg.norm(b - v, axis=1)[:, None]
    d = 0.4 * np.minimum(len_a, len_b)  # (C, 1); a factor <= 0.5: neighbouring blends never overlap
    u = np.linspace(0.0, 1.0, n_points)[None, :, None]  # (1, n_points, 1)
    blends = list(path[1:-1, None])  # (1, dof) each: the sharp corner until a blend is free
    todo = np.arange(len(v))
    for _ in range(n_halvings + 1):
        p_in = v[todo] + d[todo] * (a[todo] - v[todo]) / len_a[todo]
        p_out = v[todo] + d[todo] * (b[todo] - v[todo]) / len_b[todo]
        curve = ((1 - u) ** 2 * p_in[:, None] + 2 * u * (1 - u) * v[todo][:, None]
                 + u ** 2 * p_out[:, None])  # (C', n_points, dof)
        edges = edges_free(curve[:, :-1].reshape(-1, path.shape[1]), curve[:, 1:].reshape(-1, path.shape[1]),
                           in_collision, resolution)
        ok = np.all(edges.reshape(len(todo), -1), axis=1)  # p_in itself lies on a checked edge of the path
        for row in np.flatnonzero(ok):
            blends[todo[row]] = curve[row]
        todo = todo[~ok]
        d[todo] *= 0.5
        if len(todo) == 0:
            break
    return _drop_duplicates(np.concatenate([path[:1], *blends, path[-1:]]))


# ---- Time parameterization with velocity / acceleration / jerk limits (TOPP-free) ----------------
def filter_kernel(v_max, a_max, j_max, dt):
    """Impulse response (n_acc + n_jerk - 1,) of two moving averages, summing to 1 (the FIR form of an S-curve):
    over n_acc steps a velocity jump <= v_max ramps at <= a_max, over n_jerk steps an acceleration step at <= j_max."""
    # >>> exercise 11: time parameterization under speed, acceleration and jerk limits (Sec. V)
    n_acc = int(math.ceil(np.max(v_max / (a_max * dt)) - 1e-9))
    n_jerk = int(math.ceil(np.max(a_max / (j_max * dt)) - 1e-9))
    return np.convolve(np.ones(n_acc) / n_acc, np.ones(n_jerk) / n_jerk)
    # <<< exercise 11


def handoff_point(q0, v0, kernel, dt):
    """Where the filter input starts so that the output starts at q0 with velocity v0: the input moved at v0
    forever before t = 0, which puts it v0 * dt * (the kernel's mean delay) ahead of q0 (a "coast")."""
    delay = np.sum(np.arange(len(kernel)) * kernel)  # mean delay in steps
    return np.asarray(q0, dtype=np.float64) + np.asarray(v0, dtype=np.float64) * dt * delay


def time_parameterize(path, v_max, a_max, j_max, dt, v0=None, in_collision=None, resolution=None,
                      max_repairs=60, repair_factor=0.7, min_speed_factor=1e-2):
    """Samples (T, dof) at dt along `path`, from path[0] moving at v0 to path[-1] at rest, with |v| <= v_max,
    |a| <= a_max, |jerk| <= j_max per joint at EVERY sample (finite differences, sample -1 = q0 - v0 dt).
    (1) Traverse the path at full speed, sampled at dt: input velocities w; (2) filter w (after the v0 history)
    with `filter_kernel` and integrate; (3) where a sample breaks a limit or an output edge collides, slow the
    input over the window that sample depends on by repair_factor, and repeat; PlanningFailed under
    min_speed_factor of full speed or after max_repairs. A straight move takes L / v_max + (n_acc + n_jerk - 2) dt.
    """
    path = np.atleast_2d(np.asarray(path, dtype=np.float64))
    dof = path.shape[1]
    v_max, a_max, j_max = (np.broadcast_to(np.asarray(x, dtype=np.float64), (dof,)) for x in (v_max, a_max, j_max))
    v0 = np.zeros(dof) if v0 is None else np.asarray(v0, dtype=np.float64)
    if not (np.all(v_max > 0) and np.all(a_max > 0) and np.all(j_max > 0) and dt > 0 and v0.shape == (dof,)
            and np.all(np.abs(v0) <= v_max * (1 + 1e-9))):
        raise ValueError(f"need v_max, a_max, j_max (per joint), dt > 0 and v0 ({dof},) with |v0| <= v_max; got "
                         f"v_max={v_max}, a_max={a_max}, j_max={j_max}, dt={dt}, v0={v0}")
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
    # Input steps waited at the handoff point: reversing a joint from a full-speed handoff needs an input jump
    # above v_max that no slow-down fixes; after L + 1 steps the filter is at rest there (an S-curve stop).
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
        # Failing sample k depends on input times in [(k - L - 2 - dwell) dt, (k - dwell) dt]: slow every piece
        # there (the filter's corner cut shrinks too), and wait longer at the handoff if k is within its reach.
        if dwell < max_dwell and bad.min() <= dwell + L + 2:
            dwell += 1
        lo, hi = (bad - L - 2 - dwell) * dt, (bad - dwell) * dt
        hit = np.any((t_vert[1:, None] > lo) & (t_vert[:-1, None] < hi), axis=1)
        slow[hit] *= repair_factor
        if slow.min() < min_speed_factor:
            break
    raise PlanningFailed(f"time parameterization: samples {bad[:5].tolist()} still violate limits "
                         f"or collide after slowing down to {slow.min():.3g} of full speed")


# ---- The HG-DAgger gate (Sec. IV-A): predicted collision, stall, the authors' time triggers --------
def rollout_chunk(env, chunk, q=None):
    """States (H + 1, dof) the env visits executing `chunk` (H, dof) of absolute targets from q (default env.q)
    by its motion rule: q_next = clip(q + clip(action - q, -max_step, max_step), lo, hi)."""
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
    """True if the best distance to the goal over the last `window` steps is not at least `min_progress`
    better than the best one before them (False while the history is shorter)."""
    # >>> exercise 12: the HG-DAgger gate: predicted collision or stall (Sec. IV-A)
    if len(distances) <= window:
        return False
    d = np.asarray(distances, dtype=np.float64)
    return bool(d[-window:].min() > d[:-window].min() - min_progress)
    # <<< exercise 12


class Gate:
    """Per-episode HG-DAgger gate (one per env): create it right after env.reset (oracle.gate), call record
    after every env step whoever drove, should_intervene before every policy step with the pending actions."""

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


# ---- The oracle ----------------------------------------------------------------------------------
@dataclass
class Plan:
    samples: np.ndarray  # (T, dof) trajectory at env.dt; samples[0] = start, samples[-1] = goal
    ee_length: float  # end-effector arc length of the smoothed path it follows (the selection criterion)
    velocity_matched: bool  # False if the handoff velocity had to be dropped (abrupt stop)


class Oracle:
    """Deterministic RRT expert: demonstrations (D0) and HG-DAgger interventions (D1..DK)."""

    def __init__(self, config: OracleConfig | None = None):
        self.cfg = config or OracleConfig()
        # the edge checks' argument: planning checks 2 (margin - verify_margin) sweeps apart, no graze below 0.5
        assert self.cfg.margin > self.cfg.verify_margin >= 0.5, "OracleConfig: need margin > verify_margin >= 0.5"

    def sweep(self, env):
        """Max arm-point motion (m) between two checks of the executed trajectory: half the link radius."""
        return 0.5 * env.link_radius

    def limits(self, env):
        """Per-joint (v_max, a_max, j_max) of the expert, in rad/s, rad/s^2, rad/s^3."""
        c = self.cfg
        v_max = np.full(env.dof, c.speed_fraction * env.max_step / env.dt)
        return v_max, np.full(env.dof, c.a_max), np.full(env.dof, c.j_max)

    def ee_length(self, env, path):
        """End-effector arc length of a joint-space polyline (edges interpolated finely)."""
        states, _, _, _ = interpolate_edges(path[:-1], path[1:], edge_resolution(env, self.sweep(env)))
        pts = env.ee(np.concatenate([path[:1], states]))
        return float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))

    def plan(self, env, q0, v0, rng):
        """Plan from q0 moving at v0 to the env's goal: IK, RRT-Connect attempts, shortcut, corners, the least ee
        arc length, time parameterization; raises PlanningFailed. The geometric plan starts at handoff_point(q0, v0)
        so that the samples leave q0 at exactly v0 (Sec. V); if that coast leaves the limits or collides, or the
        handoff cannot be time-parameterized free, v0 is dropped (an abrupt stop) and velocity_matched is False."""
        c = self.cfg
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
        goals = solve_ik(env, env.goal, rng, c.max_goals, q_start=start)
        if len(goals) == 0:
            raise PlanningFailed("no collision-free IK solution for the goal")
        # Narrow passages can be closed by the margin: search again with the sweep (checks and margins) halved,
        # down to min_sweep_fraction of it.
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
            samples = time_parameterize(path, v_max, a_max, j_max, env.dt, v0=v0, in_collision=verify, resolution=res)
        except PlanningFailed:
            if not np.any(v0):
                raise
            matched = False  # the S-curve stop of the handoff collides: stop abruptly instead
            samples = time_parameterize(path, v_max, a_max, j_max, env.dt, v0=None, in_collision=verify, resolution=res)
        return Plan(samples, best[1], matched)

    def _search(self, env, q0, coast, start, goals, sweep, rng):
        """RRT-Connect attempts + shortcut + corners at one sweep; the plan of least ee arc length.
        Returns ((path, length), verify predicate, resolution)."""
        c = self.cfg
        res = edge_resolution(env, sweep)  # verification of the executed trajectory
        # planning checks 2 (margin - verify_margin) sweeps apart keep verify_margin everywhere (edge checks)
        plan_res = edge_resolution(env, 2 * (c.margin - c.verify_margin) * sweep)
        # margins everywhere except near q0 (and its coast) and near the goal configurations
        zones = np.concatenate([q0[None], goals])
        radii = np.concatenate([[coast], np.zeros(len(goals))]) + c.relax_sweeps * sweep
        collides = with_margin(env, c.margin * sweep, zones, radii)
        verify = with_margin(env, c.verify_margin * sweep, zones, radii)
        best = None
        for attempt, seed in enumerate(rng.integers(0, 2 ** 63, size=c.n_attempts)):
            attempt_rng = np.random.default_rng(seed)
            try:
                path = rrt_connect(start, goals, collides, env.joint_limits, attempt_rng, resolution=plan_res,
                                   max_iters=c.max_iters, max_time=c.max_time)
            except PlanningFailed:
                if attempt == 0:  # a full budget found nothing: more attempts rarely would
                    raise
                continue
            direct = len(path) == 2  # a straight line: every attempt would return the same one
            path = shortcut(path, collides, attempt_rng, resolution=plan_res)
            path = smooth_corners(path, collides, plan_res)
            length = self.ee_length(env, path)
            if best is None or length < best[1]:  # strict: ties keep the earlier attempt
                best = (path, length)
            if direct:
                break
        return best, verify, res

    def demonstrate(self, env, seed):
        """An expert episode (D0) for scenario `seed`, the plan's samples as absolute joint targets until the env
        ends it: 'obs', 'q', 'action', 'expert' (all True), 'seed', 'success' (experiment/run_folder.py writes them)."""
        obs, _ = env.reset(seed=seed)
        plan = self.plan(env, env.q, np.zeros(env.dof), np.random.default_rng([self.cfg.seed, int(seed)]))
        observations, qs, success = [], [], False
        for target in plan.samples[1:]:
            observations.append(obs)
            qs.append(env.q)
            obs, _, terminated, truncated, info = env.step(target)
            success = info["success"]
            if terminated or truncated:
                break
        T = len(qs)
        return {"obs": np.asarray(observations, dtype=np.float32).reshape(T, env.obs_dim),
                "q": np.asarray(qs, dtype=np.float64).reshape(T, env.dof),
                "action": plan.samples[1:T + 1].copy(),  # the targets stepped
                "expert": np.ones(T, dtype=bool), "seed": int(seed), "success": bool(success)}

    def gate(self, env, rng=None):
        """A per-episode Gate for `env` (create it right after env.reset)."""
        return Gate(self, env, rng)

    def chunk_collides(self, env, chunk):
        """True if the next gate_lookahead steps of `chunk` (H, dof) come within gate_clearance (m) of a collision
        (every step checked along its straight edge); near env.q only the plain check applies (it may leave)."""
        c = self.cfg
        states = rollout_chunk(env, chunk if c.gate_lookahead is None else chunk[:c.gate_lookahead])
        near = with_margin(env, c.gate_clearance, env.q[None], c.gate_clearance)
        return path_in_collision(states, near, edge_resolution(env, self.sweep(env)))

    def should_intervene(self, env, chunk, distances):
        """'collision' if the policy's chunk would collide, 'stall' if the ee made no progress toward the goal
        over the last stall_window steps (distances: one per step), else None."""
        # >>> exercise 12: the HG-DAgger gate: predicted collision or stall (Sec. IV-A)
        if self.chunk_collides(env, chunk):
            return "collision"
        if stalled(distances, self.cfg.stall_window, self.cfg.stall_progress):
            return "stall"
        return None
        # <<< exercise 12

    def intervention(self, env, rng=None):
        """Absolute joint targets (L, dof) for the expert to drive from env.q: a plan with the handoff velocity
        (env.q - env.q_prev) / env.dt, seeded by cfg.seed and the state, cut after a random number of steps in
        cfg.handback_steps drawn from `rng` (default: the plan's). Raises PlanningFailed."""
        q, q_prev = env.q, env.q_prev
        state_key = np.frombuffer(np.concatenate([q, q_prev]).tobytes(), dtype=np.uint32)
        plan_rng = np.random.default_rng([self.cfg.seed, *state_key.tolist()])
        plan = self.plan(env, q, (q - q_prev) / env.dt, plan_rng)
        lo, hi = self.cfg.handback_steps
        steps = int((rng if rng is not None else plan_rng).integers(lo, hi + 1))
        return plan.samples[1:steps + 1]


# ---- Figure 5 (planar part): a scenario with an expert demonstration drawn over it ----------------
def plot_demonstration(env, episode, path, n_arms=8):
    """Save the scene of episode['seed'] with faded arms along the demo (env.render) and the ee path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env.reset(seed=int(episode["seed"]))
    q = np.asarray(episode["q"])
    pts = env.fk(q)  # (T, n_points, 2): a planar env
    fig, ax = plt.subplots(figsize=(5, 5))
    env.render(ax)  # scene and the arm at the start
    for i, t in enumerate(np.linspace(0, len(q) - 1, n_arms).astype(int)[1:], start=1):
        env.render(ax, q=q[t], alpha=0.15 + 0.6 * i / max(1, n_arms - 1), color="tab:orange", show_scene=False)
    ax.plot(pts[:, -1, 0], pts[:, -1, 1], color="tab:red", lw=1.5, label="end-effector path")
    ax.set_aspect("equal")
    ax.set_title(f"expert demonstration, seed {episode['seed']} ({len(q)} steps; start in blue)")
    ax.legend(loc="lower left", fontsize=8)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    import os

    import envs

    env = envs.make_env("planar")
    oracle = Oracle()
    episode = oracle.demonstrate(env, env.eval_seeds()[0])
    print(f"seed {episode['seed']}: success {episode['success']}, {len(episode['q'])} steps")
    # an intervention: the arm 30 % into the demo, drifted 0.1 rad per joint off it and moving
    t = int(0.3 * len(episode["q"]))
    env.set_state(episode["q"][t] + 0.1, episode["q"][t - 1] + 0.1)
    print(f"gate on the next 20 expert actions: {oracle.gate(env).should_intervene(env, episode['action'][t:t + 20])}")
    print(f"intervention: the expert drives {len(oracle.intervention(env))} steps")
    os.makedirs("runs", exist_ok=True)
    plot_demonstration(env, episode, os.path.join("runs", "oracle_demo.png"))
    print("wrote runs/oracle_demo.png")
