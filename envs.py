"""Environments of the paper's experiments (Sec. V, Fig. 5, Table I).

PlanarReacher: the 2D planar 3-link reacher of Sec. V. A 3-link arm with thick links (capsules)
must bring its end effector to a goal position in a cluttered scene whose obstacles make narrow
passages, so that the arm's own links are often what collides and it must sometimes take a
roundabout route to untangle itself (the paper's description). Self-collision between
non-adjacent links (link 0 vs link 2) counts.

Every environment in this file has the same interface (gymnasium conventions, no dependency):

    env = make_env('planar')                  # or PlanarReacher()
    env.dof, env.obs_dim                      # joint count, observation length
    env.max_step                              # per-step joint speed limit (rad/step)
    env.max_steps                             # episode step limit (truncation)
    env.dt                                    # seconds per step (for velocities in figures)
    env.joint_limits                          # (lo (dof,), hi (dof,))
    obs, info = env.reset(seed=s)             # deterministic scenario from s; info: 'q', 'goal'
    obs, reward, terminated, truncated, info = env.step(action)   # action: absolute joint target
    env.q, env.q_prev                         # current / previous joint positions (read-only)
    env.set_state(q, q_prev=None, step_count=0)
    env.make_obs(q, q_prev)                   # batched observations for the current scenario
    env.in_collision(q, margin=0.0)           # (B,) bool, True = in collision (vectorized numpy);
                                              # margin (m) inflates every pair's contact distance
    env.fk(q)                                 # (B, n_points, dim) joint points, base .. end effector
    env.ee(q)                                 # (B, dim) end effector
    env.goal_reached(q)                       # (B,) bool, True = end effector within tolerance
    env.goal                                  # (dim,) goal of the current scenario
    env.render(ax, q=None, alpha=1.0)         # matplotlib drawing of the scene (and arm at q)
    env.eval_seeds(), env.train_seeds(n, start=0)
PlanarReacher extras: set_scene(obstacles, goal) installs a hand-built scene; goal_configurations()
gives collision-free closed-form IK solutions of the goal; pymunk_in_collision(q) is the
simulator's (slow) version of in_collision; clip_action(q, action) is step's motion rule.

Step semantics (CONTRACT.md): q_next = clip(q + clip(action - q, -max_step, max_step), lo, hi).
Targets beyond the joint limits are therefore clipped, not errors; NaN/inf/wrong shape raise
ValueError. An episode ends on success (goal reached, no collision), on collision (terminated),
or after max_steps steps (truncated).

Geometry (PlanarReacher): every body is a capsule = segment (p0, p1) plus radius. Obstacles are
stored as one array (N, 5) of (x0, y0, x1, y1, radius) -- a disc is a zero-length capsule. This one
definition feeds both
  * the pymunk space (the simulator): kinematic link bodies with pymunk.Segment shapes, static
    obstacle shapes, contacts from space.shape_query -- used by step();
  * the vectorized numpy check `in_collision` (segment-segment distances) -- used by planners,
    relabeling and evaluation, which need millions of checks.
The two agree (tests/test_envs.py): on 12,000 random configurations in 4 scenes, and 1e-9 rad on
either side of contact-boundary points found by bisection (tested down to 1e-10 rad on 1,575
boundary points: no disagreement). Known exception, of measure zero: exactly collinear capsules,
for which pymunk's GJK reports a zero-depth contact.

Episode files: save_episodes / load_episodes (one .npz, ragged arrays concatenated with offsets);
median_step(episodes) gives the paper's "median step size" unit of noise levels (Sec. V).
"""
import math
from dataclasses import dataclass

import numpy as np
import pymunk

# Seed ranges. Evaluation scenarios never appear in training (paper Sec. V: 100 fixed scenarios).
EVAL_SEED_START = 10_000
N_EVAL_SEEDS = 100
TRAIN_SEED_END = EVAL_SEED_START  # training seeds are 0 .. 9_999


def eval_seeds():
    """The 100 fixed evaluation scenarios (paper Sec. V): seeds 10_000 .. 10_099."""
    return list(range(EVAL_SEED_START, EVAL_SEED_START + N_EVAL_SEEDS))


def train_seeds(n, start=0):
    """n training seeds start .. start + n - 1, from 0 .. 9_999 (disjoint from eval_seeds)."""
    if n < 0 or start < 0 or start + n > TRAIN_SEED_END:
        raise ValueError(f"train_seeds(n={n}, start={start}): need 0 <= start and "
                         f"start + n <= {TRAIN_SEED_END} (the training seed range)")
    return list(range(start, start + n))


# ----------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------
@dataclass
class PlanarConfig:
    link_lengths: tuple = (0.35, 0.30, 0.25)  # m, base to end effector; total reach 0.9 m
    link_radius: float = 0.03  # m, half the link thickness (links are capsules)
    base: tuple = (0.0, 0.0)  # m, fixed position of joint 0
    # rad; joint 0 turns fully, joints 1-2 stop before the links fold onto each other
    joint_lo: tuple = (-math.pi, -2.6, -2.6)
    joint_hi: tuple = (math.pi, 2.6, 2.6)
    max_step: float = 0.05  # rad/step, per-joint speed limit (0.5 rad/s at dt = 0.1 s)
    dt: float = 0.1  # s per step
    # Episode step limit, ~4x a typical expert episode. Measured: shortest joint-grid paths over the
    # 100 eval scenes take 58 steps (median), 88 (90th pct), 132 (max) (scene_difficulty.py); the
    # oracle's time-parameterized demos 78 / 121 / 210 (bench_oracle.py, first 30 eval scenes).
    max_steps: int = 300
    goal_tolerance: float = 0.04  # m, end effector within this distance of the goal = reached
    # States checked for contact within one step (the end state and evenly spaced states before it).
    # At max_step = 0.05 rad on all joints a point of the arm moves at most 0.085 m per step, i.e.
    # 0.021 m between checks -- far less than the thinnest forbidden band a link centre line must
    # cross (2 * (link_radius + thinnest obstacle radius 0.025) = 0.11 m): nothing tunnels through.
    n_substeps: int = 4
    n_max_obstacles: int = 8  # obstacle slots in the observation (absent ones are zeros)
    # --- scene generator (see PlanarReacher._draw_scene) ---
    goal_radius: tuple = (0.6, 0.85)  # m, distance of the goal from the base (reach 0.9)
    base_clearance: float = 0.02  # m, obstacles stay this far outside the disc link 0 sweeps
    wall_gap: tuple = (0.15, 0.22)  # m, clear width of the gap in the wall (link diameter 0.06)
    wall_radius: float = 0.025  # m, half thickness of the wall pieces
    wall_length: tuple = (0.2, 0.4)  # m, length of each of the two wall pieces
    wall_to_goal: float = 0.1  # m, the wall's centre line is at least this far before the goal
    gap_offset: float = 0.2  # m, the gap's centre lies within +-gap_offset of the base-goal line
    gap_clearance: float = 0.06  # m, clutter keeps this far beyond the gap's half width from its centre
    n_clutter: tuple = (2, 5)  # number of posts / short capsules besides the wall (inclusive)
    clutter_radius: tuple = (0.03, 0.06)  # m
    clutter_half_length: float = 0.1  # m, half length of the capsules (discs: 0)
    start_goal_min_dist: float = 0.5  # m, start end effector at least this far from the goal
    n_goal_angles: int = 180  # last-link orientations tried when searching goal configurations
    # A scene is kept only if at least this many of the 2 n_goal_angles IK candidates are free: a
    # goal reachable in only a sliver of joint space is a needle-eye no planner finds reliably.
    min_goal_configurations: int = 8


# ----------------------------------------------------------------------------------------------
# Vectorized capsule geometry (numpy). x and y components are kept in separate arrays (no
# trailing axis of length 2), so every operation runs on contiguous memory.
# ----------------------------------------------------------------------------------------------
def _point_segment_dist_sq(px, py, ax, ay, dx, dy, inv_len_sq):
    """Squared distance from point p to segment a + s d, s in [0, 1] (all arrays broadcast)."""
    s = np.minimum(np.maximum(((px - ax) * dx + (py - ay) * dy) * inv_len_sq, 0.0), 1.0)
    ex = px - ax - s * dx
    ey = py - ay - s * dy
    return ex * ex + ey * ey


def segment_distance_sq(ax, ay, ux, uy, bx, by, vx, vy):
    """Squared distance between segments a + s u and b + t v (s, t in [0, 1]), broadcasting.

    Two segments in the plane either cross (distance 0) or their closest pair of points involves an
    endpoint of one of them, so the distance is the smallest of four point-segment distances.
    """
    inv_u = 1.0 / np.maximum(ux * ux + uy * uy, 1e-300)  # zero-length segment (disc): s = 0
    inv_v = 1.0 / np.maximum(vx * vx + vy * vy, 1e-300)
    d = np.minimum(
        np.minimum(_point_segment_dist_sq(bx, by, ax, ay, ux, uy, inv_u),
                   _point_segment_dist_sq(bx + vx, by + vy, ax, ay, ux, uy, inv_u)),
        np.minimum(_point_segment_dist_sq(ax, ay, bx, by, vx, vy, inv_v),
                   _point_segment_dist_sq(ax + ux, ay + uy, bx, by, vx, vy, inv_v)))
    # Proper crossing: each segment's endpoints lie strictly on opposite sides of the other's line.
    wx, wy = bx - ax, by - ay
    side_b0 = ux * wy - uy * wx
    side_b1 = ux * (wy + vy) - uy * (wx + vx)
    side_a0 = vy * wx - vx * wy
    side_a1 = vx * (uy - wy) - vy * (ux - wx)
    crossing = (side_b0 * side_b1 < 0.0) & (side_a0 * side_a1 < 0.0)
    return np.where(crossing, 0.0, d)


def _as_batch(q, dof, name="q"):
    """(dof,) or (B, dof) finite array -> ((B, dof) float64, was_single)."""
    q = np.asarray(q, dtype=np.float64)
    single = q.ndim == 1
    if single:
        q = q[None]
    if q.ndim != 2 or q.shape[1] != dof:
        raise ValueError(f"{name} must have shape ({dof},) or (B, {dof}), got {np.shape(q)}")
    return q, single


# ----------------------------------------------------------------------------------------------
# The planar reacher
# ----------------------------------------------------------------------------------------------
class PlanarReacher:
    """3-link planar arm among capsule obstacles (paper Sec. V, Fig. 5 right).

    Observation layout (float32, obs_dim = 2 dof + 2 + 5 n_max_obstacles = 48):
        [0:3]    q       current joint positions (rad)
        [3:6]    q_prev  joint positions one step earlier (rad)
        [6:8]    goal    end-effector goal (x, y) in m
        [8:48]   obstacles, n_max_obstacles slots of (x0, y0, x1, y1, radius) in m; absent = zeros
    """

    dim = 2  # workspace dimension

    def __init__(self, config: PlanarConfig | None = None):
        self.cfg = cfg = config or PlanarConfig()
        self.dof = len(cfg.link_lengths)
        if self.dof != 3:
            raise ValueError(f"PlanarReacher models a 3-link arm, got link_lengths={cfg.link_lengths}")
        self.link_lengths = np.asarray(cfg.link_lengths, dtype=np.float64)
        self.link_radius = float(cfg.link_radius)
        self.base = np.asarray(cfg.base, dtype=np.float64)
        self.max_step = float(cfg.max_step)
        self.max_steps = int(cfg.max_steps)
        self.dt = float(cfg.dt)
        self.goal_tolerance = float(cfg.goal_tolerance)
        self.obs_dim = 2 * self.dof + self.dim + 5 * cfg.n_max_obstacles
        self._lo = np.asarray(cfg.joint_lo, dtype=np.float64)
        self._hi = np.asarray(cfg.joint_hi, dtype=np.float64)
        # scenario state (set by reset)
        self.seed = None
        self.obstacles = np.zeros((0, 5))  # (N, 5): x0, y0, x1, y1, radius
        self._goal = np.zeros(self.dim)
        self._q = np.zeros(self.dof)
        self._q_prev = np.zeros(self.dof)
        self.step_count = 0
        self._has_state = False  # step() needs reset() or set_state() first
        self.set_scene(np.zeros((0, 5)))

    # ---- read-only state ---------------------------------------------------------------------
    @property
    def joint_limits(self):
        return self._lo.copy(), self._hi.copy()

    @property
    def q(self):
        return self._q.copy()

    @property
    def q_prev(self):
        return self._q_prev.copy()

    @property
    def goal(self):
        return self._goal.copy()

    # ---- seeds (shared by every env of this file) --------------------------------------------
    @staticmethod
    def eval_seeds():
        """The 100 evaluation seeds (module function eval_seeds)."""
        return eval_seeds()

    @staticmethod
    def train_seeds(n, start=0):
        """n training seeds from start (module function train_seeds)."""
        return train_seeds(n, start)

    # ---- kinematics and geometry -------------------------------------------------------------
    def fk(self, q):
        """Joint points (B, 4, 2): base, elbow 1, elbow 2, end effector. (dof,) -> (4, 2)."""
        q, single = _as_batch(q, self.dof)
        angles = np.cumsum(q, axis=1)  # (B, 3) absolute link angles
        points = np.empty((len(q), self.dof + 1, 2))  # (B, 4, 2)
        points[:, 0] = self.base
        points[:, 1:, 0] = self.base[0] + np.cumsum(self.link_lengths * np.cos(angles), axis=1)
        points[:, 1:, 1] = self.base[1] + np.cumsum(self.link_lengths * np.sin(angles), axis=1)
        return points[0] if single else points

    def ee(self, q):
        """End-effector positions (B, 2); (dof,) -> (2,)."""
        return self.fk(q)[..., -1, :]

    def goal_reached(self, q):
        """True where the end effector is within goal_tolerance of the goal. (B,) bool."""
        return np.linalg.norm(self.ee(q) - self._goal, axis=-1) <= self.goal_tolerance

    def in_collision(self, q, margin=0.0):
        """True where configuration q touches an obstacle or itself (links 0 and 2). (B,) bool.

        A capsule pair collides when the distance of its segments is < the sum of the radii
        (+ margin: with margin > 0, True also where a pair is closer than margin m -- the
        inflated check planners use to keep clear of obstacles between their collision checks).
        Adjacent links share a joint and never count. Vectorized over the batch in two phases:
          broad phase: bounding circles of every (config, link, obstacle) pair -- a cheap test that
            rules out most pairs (about 5 in 6 in the generated scenes);
          narrow phase: exact segment-segment distances for the remaining pairs only.
        Large batches run in chunks so the temporaries stay in cache.
        """
        q, single = _as_batch(q, self.dof)
        if not np.all(np.isfinite(q)):
            raise ValueError("in_collision: q contains NaN or inf")
        if not (np.isfinite(margin) and margin >= 0):
            raise ValueError(f"in_collision: margin must be a finite distance >= 0 m, got {margin}")
        chunk = 2048  # configurations per pass: temporaries stay in cache (faster than 4096 here)
        hit = np.concatenate([self._in_collision_chunk(q[i:i + chunk], float(margin))
                              for i in range(0, len(q), chunk)])
        return hit[0] if single else hit

    def _in_collision_chunk(self, q, margin):
        B = len(q)
        angles = np.cumsum(q.T, axis=0)  # (3, B) absolute link angles
        ux = np.cos(angles) * self.link_lengths[:, None]  # (3, B) link vectors
        uy = np.sin(angles) * self.link_lengths[:, None]
        ax = np.empty_like(ux)  # (3, B) link start points: base, then running sums
        ay = np.empty_like(uy)
        ax[0], ay[0] = self.base
        ax[1:] = self.base[0] + np.cumsum(ux[:-1], axis=0)
        ay[1:] = self.base[1] + np.cumsum(uy[:-1], axis=0)
        g = self._geom  # obstacle arrays precomputed by set_scene
        # broad phase: link bounding circle (centre = link midpoint) vs obstacle bounding circle
        dx = (ax + 0.5 * ux)[:, :, None] - g["cx"]  # (3, B, N)
        dy = (ay + 0.5 * uy)[:, :, None] - g["cy"]
        near = dx * dx + dy * dy < ((g["reach"] + margin) ** 2)[:, None, :]  # (3, B, N)
        link, b, o = np.nonzero(near)
        flat = link * B + b  # index into the raveled (3, B) link arrays
        # narrow phase on the candidate pairs (link, obstacle) plus, for every configuration, the
        # non-adjacent link pair (0, 2): segment A = a link, segment B = an obstacle or link 2
        d2 = segment_distance_sq(
            np.concatenate([ax.ravel()[flat], ax[0]]), np.concatenate([ay.ravel()[flat], ay[0]]),
            np.concatenate([ux.ravel()[flat], ux[0]]), np.concatenate([uy.ravel()[flat], uy[0]]),
            np.concatenate([g["bx"][o], ax[2]]), np.concatenate([g["by"][o], ay[2]]),
            np.concatenate([g["vx"][o], ux[2]]), np.concatenate([g["vy"][o], uy[2]]))
        contact = np.concatenate([g["contact"][o], np.full(B, 2 * self.link_radius)]) + margin
        contact_sq = contact * contact
        hit = np.zeros(B, dtype=bool)
        hit[np.concatenate([b, np.arange(B)])[d2 < contact_sq]] = True
        return hit

    def set_scene(self, obstacles, goal=None):
        """Install a scene: obstacles (N, 5) rows (x0, y0, x1, y1, radius), goal (2,).

        reset() calls this with a generated scene; tests and figures may call it with a built one.
        Derives everything both collision checks need from this one array.
        """
        obstacles = np.asarray(obstacles, dtype=np.float64).reshape(-1, 5)
        if len(obstacles) > self.cfg.n_max_obstacles:
            raise ValueError(f"set_scene: {len(obstacles)} obstacles, the observation holds at "
                             f"most n_max_obstacles={self.cfg.n_max_obstacles}")
        if not np.all(np.isfinite(obstacles)) or np.any(obstacles[:, 4] < 0):
            raise ValueError("set_scene: obstacles must be finite with radius >= 0")
        self.obstacles = obstacles
        if goal is not None:
            self._goal = np.asarray(goal, dtype=np.float64).reshape(self.dim).copy()
        bx, by = obstacles[:, 0], obstacles[:, 1]
        vx, vy = obstacles[:, 2] - bx, obstacles[:, 3] - by
        bound = 0.5 * np.hypot(vx, vy) + obstacles[:, 4]  # obstacle bounding-circle radius
        link_bound = 0.5 * self.link_lengths + self.link_radius  # (3,)
        self._geom = dict(bx=bx, by=by, vx=vx, vy=vy, cx=bx + 0.5 * vx, cy=by + 0.5 * vy,
                          reach=link_bound[:, None] + bound,  # (3, N) centre distance for overlap
                          contact=self.link_radius + obstacles[:, 4])  # (N,) radii sums
        self._obstacle_obs = np.zeros(5 * self.cfg.n_max_obstacles, dtype=np.float32)
        self._obstacle_obs[: obstacles.size] = obstacles.ravel()
        self._build_space()

    # ---- pymunk mirror (the simulator) -------------------------------------------------------
    def _build_space(self):
        """pymunk space of the current scene: kinematic link bodies + static obstacle shapes."""
        space = pymunk.Space()
        self._link_bodies, self._link_shapes = [], []
        for length in self.link_lengths:
            body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
            shape = pymunk.Segment(body, (0.0, 0.0), (float(length), 0.0), self.link_radius)
            space.add(body, shape)
            self._link_bodies.append(body)
            self._link_shapes.append(shape)
        self._obstacle_shapes = []
        for x0, y0, x1, y1, rad in self.obstacles:
            # discs too are Segments (zero length): pymunk 7.3 reports Segment-Circle contacts
            # from shape_query with the sign of the distance flipped
            shape = pymunk.Segment(space.static_body, (x0, y0), (x1, y1), float(rad))
            space.add(shape)
            self._obstacle_shapes.append(shape)
        space.reindex_static()  # compute the static shapes' world geometry once
        self._space = space

    def pymunk_in_collision(self, q):
        """Same predicate as in_collision, from pymunk contacts (one config at a time, slow)."""
        q, single = _as_batch(q, self.dof)
        points = self.fk(q)
        angles = np.cumsum(q, axis=1)
        out = np.zeros(len(q), dtype=bool)
        for b in range(len(q)):
            for i, body in enumerate(self._link_bodies):
                body.position = (float(points[b, i, 0]), float(points[b, i, 1]))
                body.angle = float(angles[b, i])
                # shape_query reads the other shapes' cached world geometry: refresh it
                self._space.reindex_shapes_for_body(body)
            out[b] = self._pymunk_contact()
        return out[0] if single else out

    def _pymunk_contact(self):
        """True if a link penetrates an obstacle or a non-adjacent link in the posed space."""
        links = self._link_shapes
        for i, shape in enumerate(links):
            for hit in self._space.shape_query(shape):
                other = hit.shape
                if other in links and abs(links.index(other) - i) <= 1:
                    continue  # adjacent links share a joint: not a collision
                if any(pt.distance < 0.0 for pt in hit.contact_point_set.points):
                    return True
        return False

    # ---- scenarios ---------------------------------------------------------------------------
    def _draw_scene(self, rng):
        """One candidate scene: (obstacles (N, 5), goal (2,)). May be rejected by reset.

        Layout: a wall with a narrow gap lies across the line from the base to the goal, so the
        arm has to thread links 1-2 through the gap, often with a bent elbow; posts and loose
        clutter around the elbow's workspace block the obvious ways of bending, so the arm must
        sometimes untangle itself (switch elbow sides) on a roundabout route.
        Nothing enters the disc that link 0 sweeps (radius l1 + link_radius + base_clearance):
        an obstacle there would cut joint 0's range in two and make many scenes unsolvable.
        """
        cfg = self.cfg
        keep_out = self.link_lengths[0] + self.link_radius + cfg.base_clearance
        goal_angle = rng.uniform(-math.pi, math.pi)
        goal_dist = rng.uniform(*cfg.goal_radius)
        normal = np.array([math.cos(goal_angle), math.sin(goal_angle)])
        tangent = np.array([-normal[1], normal[0]])
        goal = self.base + goal_dist * normal
        obstacles = []
        keep_clear = [(self.base, keep_out)]  # (centre, radius) discs clutter must not enter
        # wall across the approach to the goal, its gap offset sideways
        wr = cfg.wall_radius
        wall_dist = rng.uniform(keep_out + wr, goal_dist - cfg.wall_to_goal)
        gap = rng.uniform(*cfg.wall_gap)
        gap_center = rng.uniform(-cfg.gap_offset, cfg.gap_offset)
        for side in (-1.0, 1.0):
            inner = gap_center + side * (gap / 2 + wr)
            outer = inner + side * rng.uniform(*cfg.wall_length)
            p0 = self.base + wall_dist * normal + inner * tangent
            p1 = self.base + wall_dist * normal + outer * tangent
            obstacles.append([*p0, *p1, wr])
        # the gap itself stays open (a post right in it would leave only a sliver of a passage)
        keep_clear.append((self.base + wall_dist * normal + gap_center * tangent,
                           gap / 2 + cfg.gap_clearance))
        # posts (discs) and short capsules anywhere in the elbow's and wrist's workspace
        n_extra = rng.integers(cfg.n_clutter[0], cfg.n_clutter[1] + 1)
        while len(obstacles) < 2 + n_extra:
            ang = rng.uniform(-math.pi, math.pi)
            reach = self.link_lengths.sum()
            centre = self.base + rng.uniform(keep_out, reach) * np.array([math.cos(ang), math.sin(ang)])
            half = rng.uniform(0.0, cfg.clutter_half_length) * (rng.random() < 0.5)  # half are discs
            orient = rng.uniform(0, math.pi)
            h = half * np.array([math.cos(orient), math.sin(orient)])
            rad = rng.uniform(*cfg.clutter_radius)
            p0, p1 = centre - h, centre + h
            d = p1 - p0
            inv = 1.0 / max(d @ d, 1e-300)
            if all(math.sqrt(_point_segment_dist_sq(*c, *p0, *d, inv)) - rad >= clear
                   for c, clear in keep_clear):
                obstacles.append([*p0, *p1, rad])
        return np.asarray(obstacles, dtype=np.float64), goal

    def goal_configurations(self, goal=None, n_angles=None):
        """Collision-free joint configurations whose end effector is exactly at the goal. (M, 3).

        Closed-form IK of the 3-link arm: for each orientation phi of the last link the wrist is
        at goal - l3 (cos phi, sin phi), and the 2-link IK of the wrist has two elbow solutions.
        Configurations outside the joint limits or in collision are dropped.
        """
        goal = self._goal if goal is None else np.asarray(goal, dtype=np.float64)
        n = n_angles or self.cfg.n_goal_angles
        l1, l2, l3 = self.link_lengths
        phi = np.linspace(-math.pi, math.pi, n, endpoint=False)
        wx = goal[0] - self.base[0] - l3 * np.cos(phi)  # (n,) wrist positions
        wy = goal[1] - self.base[1] - l3 * np.sin(phi)
        cos_q1 = (wx ** 2 + wy ** 2 - l1 ** 2 - l2 ** 2) / (2 * l1 * l2)
        ok = np.abs(cos_q1) <= 1.0
        wx, wy, phi, cos_q1 = wx[ok], wy[ok], phi[ok], cos_q1[ok]
        sols = []
        for elbow in (1.0, -1.0):
            q1 = elbow * np.arccos(cos_q1)
            q0 = np.arctan2(wy, wx) - np.arctan2(l2 * np.sin(q1), l1 + l2 * np.cos(q1))
            q2 = phi - q0 - q1
            sols.append(np.stack([q0, q1, q2], axis=1))
        q = np.concatenate(sols)  # (M, 3)
        q = (q + math.pi) % (2 * math.pi) - math.pi  # wrap every joint into [-pi, pi)
        q = q[np.all((q >= self._lo) & (q <= self._hi), axis=1)]
        return q[~self.in_collision(q)] if len(q) else q

    def reset(self, seed=None):
        """Draw the scenario of `seed` (obstacles, goal, start) and put the arm at the start.

        Rejection sampling with one rng stream, so the scene is a deterministic function of seed:
        scenes whose goal has fewer than min_goal_configurations collision-free IK candidates are
        re-drawn; the start is the first of 256 uniform joint samples that is collision-free with
        its end effector at least start_goal_min_dist from the goal (none: re-draw the scene).
        """
        if seed is None:
            seed = int(np.random.default_rng().integers(0, 2 ** 31))  # fresh entropy, recorded
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"reset: seed must be a non-negative int or None, got {seed!r}")
        rng = np.random.default_rng(int(seed))
        while True:
            self.set_scene(*self._draw_scene(rng))
            if len(self.goal_configurations()) < self.cfg.min_goal_configurations:
                continue
            candidates = rng.uniform(self._lo, self._hi, size=(256, self.dof))
            far = np.linalg.norm(self.ee(candidates) - self._goal, axis=1) >= self.cfg.start_goal_min_dist
            ok = far & ~self.in_collision(candidates)
            if ok.any():
                start = candidates[np.argmax(ok)]
                break
        self.seed = int(seed)
        self.set_state(start)
        return self.make_obs(self._q, self._q_prev), {"q": self.q, "goal": self.goal, "seed": self.seed}

    # ---- state, observations, stepping -------------------------------------------------------
    def set_state(self, q, q_prev=None, step_count=0):
        """Put the arm at q (previous position q_prev, default q); the step counter to step_count."""
        q = self._check_q(q, "q")
        q_prev = q.copy() if q_prev is None else self._check_q(q_prev, "q_prev")
        self._q, self._q_prev = q, q_prev
        self.step_count = int(step_count)
        self._has_state = True

    def _check_q(self, q, name):
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.dof,):
            raise ValueError(f"{name} must have shape ({self.dof},), got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"{name} must be finite, got {q}")
        if np.any(q < self._lo - 1e-9) or np.any(q > self._hi + 1e-9):
            raise ValueError(f"{name}={q} is outside the joint limits lo={self._lo}, hi={self._hi}")
        return q.copy()

    def make_obs(self, q, q_prev):
        """Observations (B, obs_dim) float32 for the current scenario; (dof,) -> (obs_dim,)."""
        q, single = _as_batch(q, self.dof, "q")
        q_prev, _ = _as_batch(q_prev, self.dof, "q_prev")
        q_prev = np.broadcast_to(q_prev, q.shape)
        obs = np.empty((len(q), self.obs_dim), dtype=np.float32)
        d = self.dof
        obs[:, :d] = q
        obs[:, d:2 * d] = q_prev
        obs[:, 2 * d:2 * d + 2] = self._goal
        obs[:, 2 * d + 2:] = self._obstacle_obs
        return obs[0] if single else obs

    def clip_action(self, q, action):
        """The next joint positions from `action` (absolute targets): speed limit, then limits."""
        return np.clip(q + np.clip(action - q, -self.max_step, self.max_step), self._lo, self._hi)

    def step(self, action):
        """Move toward the absolute joint target `action` (dof,) by at most max_step per joint.

        Collision is judged by pymunk contacts at the end state and at n_substeps - 1 evenly
        spaced states before it (see PlanarConfig.n_substeps: nothing tunnels through an obstacle).
        reward = 1 on success else 0 (the method does not use rewards).
        """
        if not self._has_state:
            raise ValueError("step called before reset (or set_state)")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.dof,):
            raise ValueError(f"action must have shape ({self.dof},), got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite (no NaN/inf), got {action}")
        q_next = self.clip_action(self._q, action)
        fractions = np.arange(1, self.cfg.n_substeps + 1)[:, None] / self.cfg.n_substeps
        sweep = self._q + fractions * (q_next - self._q)  # (n_substeps, dof), last = q_next
        collision = bool(any(self.pymunk_in_collision(sweep)))
        self._q_prev, self._q = self._q, q_next
        self.step_count += 1
        success = (not collision) and bool(self.goal_reached(q_next))
        terminated = collision or success
        truncated = (not terminated) and self.step_count >= self.max_steps
        info = {"collision": collision, "success": success, "q": self.q, "step": self.step_count}
        return self.make_obs(self._q, self._q_prev), float(success), terminated, truncated, info

    # ---- drawing -----------------------------------------------------------------------------
    def render(self, ax, q=None, alpha=1.0, color="tab:blue", show_scene=True):
        """Draw obstacles, goal and the arm at q (default: current state; (dof,) or (B, dof)).

        Capsules are drawn as exact polygons in data units, so link thickness is to scale.
        alpha / color style the arm; show_scene=False draws only the arm (for paths over a scene).
        """
        from matplotlib.patches import Circle, Polygon

        if show_scene:
            for row in self.obstacles:
                ax.add_patch(Polygon(_capsule_outline(*row), closed=True, color="0.35", lw=0))
            ax.add_patch(Circle(self._goal, self.goal_tolerance, color="tab:green", alpha=0.7, lw=0))
            ax.plot(*self.base, "ks", markersize=5)
            reach = self.link_lengths.sum() + self.link_radius
            ax.set_xlim(self.base[0] - reach, self.base[0] + reach)
            ax.set_ylim(self.base[1] - reach, self.base[1] + reach)
            ax.set_aspect("equal")
        q = self._q if q is None else q
        for pts in self.fk(np.atleast_2d(q)):  # (4, 2) per configuration
            for i in range(self.dof):
                ax.add_patch(Polygon(_capsule_outline(*pts[i], *pts[i + 1], self.link_radius),
                                     closed=True, color=color, alpha=alpha, lw=0))
            ax.plot(pts[:-1, 0], pts[:-1, 1], "o", color="k", markersize=2, alpha=alpha)
        return ax


def _capsule_outline(x0, y0, x1, y1, radius, n_arc=13):
    """Polygon (2 n_arc, 2) of a capsule: two half circles joined by straight sides."""
    heading = math.atan2(y1 - y0, x1 - x0)
    arc = np.linspace(-math.pi / 2, math.pi / 2, n_arc)
    end1 = np.c_[x1 + radius * np.cos(heading + arc), y1 + radius * np.sin(heading + arc)]
    end0 = np.c_[x0 + radius * np.cos(heading + math.pi + arc), y0 + radius * np.sin(heading + math.pi + arc)]
    return np.concatenate([end1, end0])


ENVIRONMENTS = {"planar": (PlanarReacher, PlanarConfig)}  # name -> (env class, its config)


def make_env(name="planar", **config):
    """Environment by name, e.g. make_env('planar', max_steps=200) (keywords: config fields)."""
    if name not in ENVIRONMENTS:
        raise ValueError(f"make_env: unknown environment {name!r}; valid: {sorted(ENVIRONMENTS)}")
    env_class, config_class = ENVIRONMENTS[name]
    return env_class(config_class(**config))


# ----------------------------------------------------------------------------------------------
# Episode files and the noise unit
# ----------------------------------------------------------------------------------------------
def save_episodes(path, episodes):
    """Write a list of episode dicts to one .npz: per-step arrays concatenated, plus offsets.

    A key is per-step when its value's first axis is the episode length T in every episode
    ('obs', 'q', 'action', 'expert', ...): these are concatenated along time and cut back with
    'offsets'. Other keys ('seed', 'success', a goal vector) must have one shape in all episodes and
    are stacked per episode. ('seed' is always per-episode.)
    """
    if len(episodes) == 0:
        raise ValueError("save_episodes: empty episode list")
    lengths = np.array([len(ep["q"]) for ep in episodes], dtype=np.int64)
    keys = sorted(set().union(*[ep.keys() for ep in episodes]))
    data = {"offsets": np.concatenate([[0], np.cumsum(lengths)])}
    for key in keys:
        if any(key not in ep for ep in episodes):
            raise ValueError(f"save_episodes: key {key!r} is missing from some episodes")
        values = [np.asarray(ep[key]) for ep in episodes]
        if key != "seed" and all(v.ndim >= 1 and len(v) == n for v, n in zip(values, lengths)):
            data["step/" + key] = np.concatenate(values, axis=0)
        elif all(v.shape == values[0].shape for v in values):
            data["episode/" + key] = np.stack(values)
        else:
            raise ValueError(f"save_episodes: key {key!r} is neither per-step (first axis T) nor "
                             f"of one shape in every episode")
    np.savez_compressed(path, **data)


def load_episodes(path):
    """Inverse of save_episodes: a list of episode dicts."""
    try:
        data = np.load(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"load_episodes: no episode file at {path}") from None
    offsets = data["offsets"]
    episodes = [dict() for _ in range(len(offsets) - 1)]
    for name in data.files:
        kind, _, key = name.partition("/")
        values = data[name]
        for i, ep in enumerate(episodes):
            if kind == "step":
                ep[key] = values[offsets[i]:offsets[i + 1]]
            elif kind == "episode":
                v = values[i]
                if key == "seed":
                    v = int(v)
                elif v.ndim == 0 and v.dtype == bool:
                    v = bool(v)
                ep[key] = v
    return episodes


def median_step(episodes):
    """Median per-step joint displacement |q[t+1] - q[t]| over all steps and joints (Sec. V unit).

    Only moving entries count: exact zeros (a joint pinned at a limit, or the arm standing still at
    the end of an episode) are ignored, so a demo that waits does not shrink the unit.
    """
    steps = [np.abs(np.diff(np.asarray(ep["q"], dtype=np.float64), axis=0)).ravel() for ep in episodes]
    steps = np.concatenate(steps) if steps else np.zeros(0)
    steps = steps[steps > 0]
    if len(steps) == 0:
        raise ValueError("median_step: the episodes contain no joint motion")
    return float(np.median(steps))


if __name__ == "__main__":
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env = make_env("planar")
    fig, axes = plt.subplots(1, 4, figsize=(16, 4))
    for ax, seed in zip(axes, env.eval_seeds()):
        obs, info = env.reset(seed=seed)
        env.render(ax)
        goal_q = env.goal_configurations()
        env.render(ax, q=goal_q[np.argmin(np.abs(goal_q - env.q).sum(1))], alpha=0.4,
                   color="tab:orange", show_scene=False)
        ax.set_title(f"seed {seed}: {len(env.obstacles)} obstacles")
    fig.savefig("planar_scenes.png", dpi=80)
    print("wrote planar_scenes.png; obs_dim", env.obs_dim, "collision at start:",
          bool(env.in_collision(env.q)))
