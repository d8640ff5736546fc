"""The two environments of the paper's experiments (Sec. V; Tables I and II; Fig. 5).

    Sec. V, Table I    the planar 3-link reacher ............... PlanarConfig, PlanarReacher
    Sec. V, Table II   the UR5 reaching an engine lever ........ EngineConfig, EngineReach3D
    Sec. V             100 fixed evaluation scenarios .......... eval_seeds (train_seeds, unseen_seeds: disjoint)
    Sec. V, Fig. 4     the "median step" unit of noise levels .. median_step (the paper's own: paper_median_step)
    Fig. 5             the two scenes .......................... PlanarReacher.render, render_scene_image

Both envs share ArmEnv and one interface (gymnasium conventions without the dependency):

    env = make_env('planar')                  # or 'engine3d'; keywords: config fields
    obs, info = env.reset(seed=s)             # the deterministic scenario of s; info: 'q', 'goal', 'seed'
    obs, reward, terminated, truncated, info = env.step(action)   # action: absolute joint target (dof,)
    env.dof, env.dim, env.obs_dim             # joints, workspace dimension, observation length
    env.max_step, env.max_steps, env.dt       # rad per step per joint, episode step limit, s per step
    env.joint_limits, env.q, env.q_prev, env.goal, env.set_state(q, q_prev=None, step_count=0)
    env.in_collision(q, margin=0.0)           # (B,) bool, True = in collision (vectorized numpy)
    env.fk(q), env.ee(q), env.ee_jacobian(q)  # joint points (B, n, dim), end effector (B, dim), d ee / d q
    env.goal_reached(q)                       # (B,) bool, True = end effector within goal_tolerance
    env.goal_configurations()                 # (M, dof) collision-free closed-form IK of the goal
    env.make_obs(q, q_prev), env.clip_action(q, action), env.render(ax), env.draw_noise_ellipses(...)

The simulator (pymunk planar, pybullet 3-D) judges a step's contacts; the same geometry feeds the vectorized
numpy check that the planner, the gate and relabeling call millions of times (tests: the two agree).
"""
import math
from dataclasses import dataclass

import numpy as np
import pymunk


# ---- The planar reacher's configuration (Table I; the authors' setup: docs/AUTHORS_SETUP.md §1) ---------
@dataclass
class PlanarConfig:
    # --- the arm: the authors' planar_3joint.urdf ---
    link_lengths: tuple = (0.30, 0.25, 0.10)  # m, joint to joint (shoulder, elbow, wrist link)
    link_widths: tuple = (0.04, 0.035, 0.03)  # m, thickness of each box link
    gripper_reach: float = 0.15  # m, gripper base (end of the wrist link) to the end-effector point
    joint_lo: tuple = (-math.pi, -math.pi, -math.pi)  # rad, the URDF's limits on every joint
    joint_hi: tuple = (math.pi, math.pi, math.pi)  # rad
    # --- the task ---
    speed_limit: float = 0.5  # rad/s per joint; max_step = speed_limit * dt rad per step
    episode_seconds: float = 1000 / 30  # s (the authors' 1000 steps at 30 Hz); max_steps = it / dt
    goal_tolerance: float = 0.06  # m, success: end effector within this distance of the target centre
    contact_margin: float = 0.005  # m, bodies closer than this are in collision (the authors' 5 mm)
    # --- the scene: target and obstacle blocks placed polar around the shoulder (PlanarReacher.reset) ---
    target_size: float = 0.05  # m, the target cube (touching it is not a collision)
    obstacle_size: float = 0.07  # m, each obstacle cube
    n_obstacles: int = 2  # obstacle blocks per scene
    target_radius: tuple = (0.30, 0.55)  # m, distance of the target centre from the shoulder
    obstacle_radius: tuple = (0.20, 0.62)  # m, distance of each obstacle centre from the shoulder
    # --- not in the paper: the gripper (a Robotiq 2F-85 held open) as a palm and two fingers on the wrist
    #     link, this project's approximation of its 85 mm outline ---
    palm_size: tuple = (0.07, 0.09)  # m, (length along the link, width across it)
    finger_size: tuple = (0.08, 0.015)  # m, each finger; the pair spans 0.07 .. 0.15 past the base
    finger_gap: float = 0.075  # m, clear width between the two fingers (fixed open)
    base: tuple = (0.0, 0.0)  # m, the shoulder pivot in the (x, z) plane of the arm
    dt: float = 0.1  # s per step: 10 Hz, a third of the authors' 30 Hz steps on a CPU (1/30 gives theirs)
    # States checked for contact per step: the farthest arm point moves <= 0.08 m a step, 0.02 m between
    # checks, less than the thinnest band a part must cross (a 1.5 cm finger and the 3.5 cm link 2: 5 cm).
    n_substeps: int = 4
    block_clearance: float = 0.02  # m, blocks closer than this to each other overlap (re-draw)
    n_goal_angles: int = 180  # last-link orientations tried when searching goal configurations
    min_goal_configurations: int = 8  # a scene needs this many free IK candidates of the target centre


# ---- Scenarios: seed ranges (Sec. V: 100 fixed evaluation scenarios, never seen in training) -----
EVAL_SEED_START = 10_000
N_EVAL_SEEDS = 100
TRAIN_SEED_END = EVAL_SEED_START  # training seeds are 0 .. 9_999
# Not in the paper: HG-DAgger collects on the evaluation scenarios (the authors' protocol); these are held out.
UNSEEN_SEED_START = 20_000
N_UNSEEN_SEEDS = 100


def eval_seeds():
    """The 100 fixed evaluation scenarios (paper Sec. V): seeds 10_000 .. 10_099."""
    return list(range(EVAL_SEED_START, EVAL_SEED_START + N_EVAL_SEEDS))


def train_seeds(n, start=0):
    """n training seeds start .. start + n - 1, from 0 .. 9_999 (disjoint from eval_seeds)."""
    assert 0 <= start and 0 <= n and start + n <= TRAIN_SEED_END, f"train_seeds({n}, {start}) leaves 0 .. 9_999"
    return list(range(start, start + n))


def unseen_seeds():
    """100 scenarios no policy ever trains on: seeds 20_000 .. 20_099."""
    return list(range(UNSEEN_SEED_START, UNSEEN_SEED_START + N_UNSEEN_SEEDS))


# ---- What both arm envs share: state, the motion rule, the episode step, the end effector --------
def _as_batch(q, dof):
    """(dof,) or (B, dof) array -> ((B, dof) float64, was_single)."""
    q = np.asarray(q, dtype=np.float64)
    single = q.ndim == 1
    if single:
        q = q[None]
    assert q.ndim == 2 and q.shape[1] == dof, f"q of shape {q.shape}, want ({dof},) or (B, {dof})"
    return q, single


class ArmEnv:
    """The part of the env interface (module docstring) that PlanarReacher and EngineReach3D share. A subclass sets
    dof, dim, max_step, max_steps, obs_dim and supplies fk, _in_collision_chunk, simulator_in_collision (judges a
    step), make_obs, _draw_scenario, render; its config gives dt, goal_tolerance, joint_lo/hi and n_substeps."""

    # How a policy reads the observation (diffusion.OBS_ENCODERS; dagger.make_policy copies both into its config)
    obs_encoder = "flat"
    obs_encoder_args = {}
    goal_is_pose = False  # the goal is a position; True: goal_configurations is the whole goal set (oracle.py)

    def __init__(self, cfg):
        self.cfg = cfg
        self.dt, self.goal_tolerance = float(cfg.dt), float(cfg.goal_tolerance)
        self._lo = np.asarray(cfg.joint_lo, dtype=np.float64)
        self._hi = np.asarray(cfg.joint_hi, dtype=np.float64)
        self.seed = None  # the scenario (set by reset)
        self._goal = np.zeros(self.dim)
        self._q = np.zeros(self.dof)
        self._q_prev = np.zeros(self.dof)
        self.step_count = 0

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

    # the module's seed ranges, also as methods of every env (env.eval_seeds())
    eval_seeds = staticmethod(eval_seeds)
    train_seeds = staticmethod(train_seeds)
    unseen_seeds = staticmethod(unseen_seeds)

    def reset(self, seed=None):
        """Draw the scenario of `seed` (a non-negative int; None: fresh entropy, then recorded) and put the arm at
        its start. The scenario is a deterministic function of seed: the subclass's _draw_scenario(rng)."""
        if seed is None:
            seed = int(np.random.default_rng().integers(0, 2 ** 31))
        start = self._draw_scenario(np.random.default_rng(int(seed)))
        self.seed = int(seed)
        self.set_state(start)
        return self.make_obs(self._q, self._q_prev), {"q": self.q, "goal": self.goal, "seed": self.seed}

    def in_collision(self, q, margin=0.0):
        """True where the arm at q touches an obstacle or itself (the subclass's _in_collision_chunk). (B,) bool.
        margin > 0 (m): True also where closer than margin (planners keep clear between their checks)."""
        q, single = _as_batch(q, self.dof)
        n = self.collision_chunk
        hit = np.concatenate([self._in_collision_chunk(q[k:k + n], float(margin)) for k in range(0, len(q), n)])
        return hit[0] if single else hit

    def set_state(self, q, q_prev=None, step_count=0):
        """Put the arm at q (previous position q_prev, default q); the step counter to step_count."""
        q = np.array(q, dtype=np.float64)
        q_prev = q.copy() if q_prev is None else np.array(q_prev, dtype=np.float64)
        assert q.shape == q_prev.shape == (self.dof,), f"set_state: q {q.shape}, q_prev {q_prev.shape}"
        self._q, self._q_prev = q, q_prev
        self.step_count = int(step_count)

    # ---- the motion rule and the episode step ------------------------------------------------
    def clip_action(self, q, action):
        """The next joint positions from `action` (absolute targets): speed limit, then limits."""
        return np.clip(q + np.clip(action - q, -self.max_step, self.max_step), self._lo, self._hi)

    def step(self, action):
        """Move toward the absolute joint target `action` (dof,) by at most max_step per joint; the simulator's
        contacts judge the end state and n_substeps - 1 evenly spaced states before it (nothing tunnels)."""
        action = np.asarray(action, dtype=np.float64)
        assert action.shape == (self.dof,), f"step: action of shape {action.shape}, want ({self.dof},)"
        q_next = self.clip_action(self._q, action)
        fractions = np.arange(1, self.cfg.n_substeps + 1)[:, None] / self.cfg.n_substeps
        sweep = self._q + fractions * (q_next - self._q)  # (n_substeps, dof), last = q_next
        collision = bool(any(self.simulator_in_collision(sweep)))
        self._q_prev, self._q = self._q, q_next
        self.step_count += 1
        success = (not collision) and bool(self.goal_reached(q_next))
        terminated = collision or success
        truncated = (not terminated) and self.step_count >= self.max_steps
        info = {"collision": collision, "success": success, "q": self.q, "step": self.step_count}
        return self.make_obs(self._q, self._q_prev), float(success), terminated, truncated, info

    def _joint_goal_obs(self, q, q_prev):
        """make_obs's first part: (obs (B, obs_dim) float32 with q, q_prev and the goal in [0:2 dof + dim], the
        rest for the caller to fill; q (B, dof) float64; single: q was (dof,))."""
        q, single = _as_batch(q, self.dof)
        q_prev, _ = _as_batch(q_prev, self.dof)
        obs = np.empty((len(q), self.obs_dim), dtype=np.float32)
        d = self.dof
        obs[:, :d] = q
        obs[:, d:2 * d] = np.broadcast_to(q_prev, q.shape)
        obs[:, 2 * d:2 * d + self.dim] = self._goal
        return obs, q, single

    def make_obs_near(self, q, q_prev, recorded):
        """Observations of noised states near recorded ones (relabel.py): make_obs (an image variant's differs)."""
        return self.make_obs(q, q_prev)

    def plot_policy_view(self, episode, path):
        """A figure of what the policy sees beyond numbers (an image variant's); none here: returns False."""
        return False

    # ---- the end effector and the goal ---------------------------------------------------------
    def ee(self, q):
        """End-effector positions (B, dim); (dof,) -> (dim,). The last point of fk."""
        return self.fk(q)[..., -1, :]

    def ee_jacobian(self, q, h=1e-6):
        """d ee / d q by central differences, batched: q (B, dof) -> (B, dim, dof)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        B, dof = q.shape
        offsets = h * np.eye(dof)                                              # (dof, dof)
        plus = self.ee((q[:, None] + offsets).reshape(-1, dof)).reshape(B, dof, -1)
        minus = self.ee((q[:, None] - offsets).reshape(-1, dof)).reshape(B, dof, -1)
        return ((plus - minus) / (2 * h)).transpose(0, 2, 1)                  # (B, dim, dof)

    def goal_reached(self, q):
        """True where the end effector is within goal_tolerance of the goal. (B,) bool."""
        return np.linalg.norm(self.ee(q) - self._goal, axis=-1) <= self.goal_tolerance

    # ---- drawing helpers of the figures (calibrate.py, relabel.py, partial_denoise.py) ---------
    def square_view(self, axes, points, margin=0.0):
        """Square limits around workspace points (N, 2) in m, plus `margin` m and 10 %, on one axis or a list."""
        lo, hi = np.min(points, axis=0), np.max(points, axis=0)
        center, half = (lo + hi) / 2, 1.1 * (0.5 * float(np.max(hi - lo)) + margin)
        for ax in (axes if isinstance(axes, (list, tuple, np.ndarray)) else [axes]):
            ax.set_xlim(center[0] - half, center[0] + half)
            ax.set_ylim(center[1] - half, center[1] + half)

    def draw_noise_ellipses(self, ax, q, cov, color, n_std=2.0, alpha=0.3):
        """n_std ellipses of joint covariances cov (B, dof, dof) at q (B, dof), pushed to the end effector to
        first order, Sigma_ee = J Sigma J^T, drawn in the workspace's first two axes."""
        from matplotlib.patches import Ellipse
        q = np.atleast_2d(q)
        J = self.ee_jacobian(q)[:, :2]                                         # (B, 2, dof)
        cov_ee = J @ np.asarray(cov) @ J.transpose(0, 2, 1)                   # (B, 2, 2)
        for c, S in zip(self.ee(q)[:, :2], cov_ee):
            vals, vecs = np.linalg.eigh(S)
            vals = np.maximum(vals, 0.0)
            angle = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
            ax.add_patch(Ellipse(c, 2 * n_std * math.sqrt(vals[1]), 2 * n_std * math.sqrt(vals[0]), angle=angle,
                                 facecolor=color, edgecolor=color, alpha=alpha, lw=0.7))


# ---- The planar reacher (Sec. V, Table I) --------------------------------------------------------
class PlanarReacher(ArmEnv):
    """3-link planar arm with a gripper among two box obstacles (paper Sec. V, Table I, Fig. 5).

    From its start (often folded) the arm must reach the target within 6 cm without touching an obstacle or
    itself (contact within 5 mm ends the episode). Every body is an oriented box: the arm's six (three links, a
    palm, two fingers; `parts`) in their links' frames, the obstacles rows (centre x, y, half x, half y, angle).

    Observation layout (float32, obs_dim = 2 dof + 8 = 14; the authors' observation.state and
    observation.environment_state, docs/AUTHORS_SETUP.md §1):
        [0:3]    q        current joint positions (rad)
        [3:6]    q_prev   joint positions one step earlier (rad)
        [6:8]    target   centre of the target block (x, z) in m
        [8:10]   obstacle 1 centre (x, z) in m
        [10:12]  obstacle 2 centre (x, z) in m
        [12:14]  end effector (x, z) in m: forward kinematics of q (a noised state gets its own)
    The arm moves in the vertical (x, z) plane of the URDF; arrays call the second axis y.
    """

    dim, dof = 2, 3  # workspace dimension, joints
    collision_chunk = 4096  # configurations per pass of in_collision: the temporaries stay in cache
    # Self-collision pairs: parts of links not joined by a joint (link 1 vs link 3 and the gripper; link 2 vs
    # the gripper, a child of link 3 in the URDF). Adjacent links share a joint and never count.
    SELF_PAIRS = ((0, 2), (0, 3), (0, 4), (0, 5), (1, 3), (1, 4), (1, 5))

    def __init__(self, config: PlanarConfig | None = None):
        cfg = config or PlanarConfig()
        super().__init__(cfg)
        self.link_lengths = np.asarray(cfg.link_lengths, dtype=np.float64)
        self.base = np.asarray(cfg.base, dtype=np.float64)
        self.max_step = float(cfg.speed_limit * cfg.dt)  # rad per step (0.05 at 10 Hz)
        self.max_steps = int(round(cfg.episode_seconds / cfg.dt))  # 333 at 10 Hz, 1000 at 30 Hz
        self.contact_margin = float(cfg.contact_margin)
        self.link_radius = 0.5 * float(min(cfg.link_widths))  # oracle.py's check spacing derives from it
        # The end effector lies gripper_reach past the wrist link: a 3-link chain of reach 0.80 m.
        self.chain_lengths = np.array([*self.link_lengths[:2], self.link_lengths[2] + cfg.gripper_reach])
        l3 = self.link_lengths[2]
        (palm_len, palm_w), (finger_len, finger_w) = cfg.palm_size, cfg.finger_size
        finger_side = 0.5 * (cfg.finger_gap + finger_w)
        self.parts = np.array([  # (link, along, across, half length, half width)
            [0, 0.5 * self.link_lengths[0], 0.0, 0.5 * self.link_lengths[0], 0.5 * cfg.link_widths[0]],
            [1, 0.5 * self.link_lengths[1], 0.0, 0.5 * self.link_lengths[1], 0.5 * cfg.link_widths[1]],
            [2, 0.5 * l3, 0.0, 0.5 * l3, 0.5 * cfg.link_widths[2]],
            [2, l3 + 0.5 * palm_len, 0.0, 0.5 * palm_len, 0.5 * palm_w],
            [2, l3 + palm_len + 0.5 * finger_len, finger_side, 0.5 * finger_len, 0.5 * finger_w],
            [2, l3 + palm_len + 0.5 * finger_len, -finger_side, 0.5 * finger_len, 0.5 * finger_w],
        ])
        # R_j (dof,): no arm point is farther than this from joint j (the links beyond j straight, plus each
        # part's farthest corner), so a joint step dq moves any point <= sum_j R_j |dq_j| (oracle.py).
        corner = np.hypot(np.abs(self.parts[:, 1]) + self.parts[:, 3], np.abs(self.parts[:, 2]) + self.parts[:, 4])
        link = self.parts[:, 0].astype(int)
        self.lever_arms = np.array([max(self.link_lengths[j:k].sum() + corner[p]
                                        for p, k in enumerate(link) if k >= j) for j in range(3)])
        self.obs_dim = 2 * self.dof + 2 * (2 + cfg.n_obstacles)
        self.set_scene(np.zeros((0, 5)))

    # ---- kinematics and the collision check ---------------------------------------------------
    def fk(self, q):
        """Chain points (B, 4, 2): shoulder, elbow, wrist, end effector. (dof,) -> (4, 2)."""
        q, single = _as_batch(q, self.dof)
        angles = np.cumsum(q, axis=1)  # (B, 3) absolute link angles
        points = np.empty((len(q), self.dof + 1, 2))  # (B, 4, 2)
        points[:, 0] = self.base
        points[:, 1:, 0] = self.base[0] + np.cumsum(self.chain_lengths * np.cos(angles), axis=1)
        points[:, 1:, 1] = self.base[1] + np.cumsum(self.chain_lengths * np.sin(angles), axis=1)
        return points[0] if single else points

    def part_boxes(self, q):
        """The arm's boxes at q: (cx, cy, cos, sin, hx, hy), each (n_parts, B)."""
        angles = np.cumsum(q.T, axis=0)  # (3, B) absolute link angles
        cos, sin = np.cos(angles), np.sin(angles)
        jx = np.empty_like(cos)  # (3, B) joint positions: shoulder, elbow, wrist
        jy = np.empty_like(sin)
        jx[0], jy[0] = self.base
        jx[1:] = self.base[0] + np.cumsum(self.link_lengths[:2, None] * cos[:2], axis=0)
        jy[1:] = self.base[1] + np.cumsum(self.link_lengths[:2, None] * sin[:2], axis=0)
        link = self.parts[:, 0].astype(int)
        along, across = self.parts[:, 1:2], self.parts[:, 2:3]  # (n_parts, 1)
        c, s = cos[link], sin[link]  # (n_parts, B)
        cx = jx[link] + along * c - across * s
        cy = jy[link] + along * s + across * c
        hx = np.broadcast_to(self.parts[:, 3:4], c.shape)
        hy = np.broadcast_to(self.parts[:, 4:5], c.shape)
        return cx, cy, c, s, hx, hy

    def _in_collision_chunk(self, q, margin):
        """in_collision: two boxes touch when closer than contact_margin (the authors' 5 mm) + margin. Pairs:
        every arm part with every obstacle, and SELF_PAIRS. The target block is not an obstacle."""
        margin = self.contact_margin + margin
        B = len(q)
        # the scene's boxes (n_parts + N, B) each: the arm's parts at q, then the obstacles; pairs index them
        boxes = [np.concatenate([x, np.broadcast_to(g[:, None], (len(g), B))])
                 for x, g in zip(self.part_boxes(q), self._obstacle_boxes)]
        pairs_a, pairs_b = [x[self._pairs[0]] for x in boxes], [x[self._pairs[1]] for x in boxes]  # (n_pairs, B)
        # broad phase: bounding circles (centre, half diagonal) rule out most pairs cheaply
        cxa, cya, cxb, cyb = pairs_a[0], pairs_a[1], pairs_b[0], pairs_b[1]
        reach = self._pair_reach[:, None] + margin  # (n_pairs, 1): the two half diagonals + margin
        near = (cxa - cxb) ** 2 + (cya - cyb) ** 2 < reach * reach  # (n_pairs, B)
        pair, b = np.nonzero(near)
        hit = np.zeros(B, dtype=bool)
        if len(pair):  # narrow phase: exact box distances of the remaining pairs
            d = box_distance(tuple(x[pair, b] for x in pairs_a), tuple(x[pair, b] for x in pairs_b))
            hit[b[d < margin]] = True
        return hit

    def set_scene(self, obstacles, goal=None):
        """Install a scene, for both collision checks: obstacles (N, 5) rows (centre x, y, half x, half y, angle),
        goal (2,)."""
        obstacles = np.asarray(obstacles, dtype=np.float64).reshape(-1, 5)
        self.obstacles = obstacles
        if goal is not None:
            self._goal = np.asarray(goal, dtype=np.float64).reshape(self.dim).copy()
        cx, cy, hx, hy, angle = obstacles.T
        self._obstacle_boxes = (cx, cy, np.cos(angle), np.sin(angle), hx, hy)
        # the pairs the numpy check measures, as indices into [arm parts, obstacles]: SELF_PAIRS, then every part
        # with every obstacle; and each pair's two half diagonals (its bounding circles' radii)
        n_parts, (i, j) = len(self.parts), np.array(self.SELF_PAIRS).T
        self._pairs = (np.concatenate([i, np.repeat(np.arange(n_parts), len(obstacles))]),
                       np.concatenate([j, n_parts + np.tile(np.arange(len(obstacles)), n_parts)]))
        half_diagonals = np.hypot(np.concatenate([self.parts[:, 3], hx]), np.concatenate([self.parts[:, 4], hy]))
        self._pair_reach = half_diagonals[self._pairs[0]] + half_diagonals[self._pairs[1]]
        centres = np.zeros(2 * self.cfg.n_obstacles)  # absent obstacles (hand-built scenes): zeros
        centres[:obstacles[:, :2].size] = obstacles[:, :2].ravel()
        self._obstacle_obs = centres.astype(np.float32)
        self._build_space()

    # ---- pymunk mirror (the simulator) -------------------------------------------------------
    def _build_space(self):
        """pymunk space of the scene: kinematic bodies carrying the arm's parts, static obstacle boxes; every
        polygon rounded by half the contact margin, so shapes touch exactly when boxes are closer than it."""
        space = pymunk.Space()
        rounding = 0.5 * self.contact_margin
        self._link_bodies = [pymunk.Body(body_type=pymunk.Body.KINEMATIC) for _ in range(self.dof)]
        space.add(*self._link_bodies)
        self._part_shapes = []
        for link, along, across, hx, hy in self.parts:
            corners = [(along + sx * hx, across + sy * hy) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
            shape = pymunk.Poly(self._link_bodies[int(link)], corners, radius=rounding)
            space.add(shape)
            self._part_shapes.append(shape)
        # each part its own category; its mask leaves out the parts that may touch it (the same or an adjacent
        # link: not in SELF_PAIRS), so that a shape query meets only obstacles and the pairs that count
        counted = {frozenset(p) for p in self.SELF_PAIRS}
        for i, shape in enumerate(self._part_shapes):
            may_touch = sum(1 << j for j in range(len(self.parts)) if j != i and frozenset((i, j)) not in counted)
            shape.filter = pymunk.ShapeFilter(categories=1 << i, mask=pymunk.ShapeFilter.ALL_MASKS() ^ may_touch)
        for cx, cy, hx, hy, angle in self.obstacles:
            xs, ys = box_corners(cx, cy, math.cos(angle), math.sin(angle), hx, hy)
            space.add(pymunk.Poly(space.static_body, list(zip(xs, ys)), radius=rounding))
        space.reindex_static()  # compute the static shapes' world geometry once
        self._space = space

    def pymunk_in_collision(self, q):
        """Same predicate as in_collision, from pymunk contacts (one config at a time, slow): True where a part
        penetrates an obstacle or a part of SELF_PAIRS (the shapes' filters leave out the rest)."""
        q, single = _as_batch(q, self.dof)
        points = self.fk(q)
        angles = np.cumsum(q, axis=1)
        out = np.zeros(len(q), dtype=bool)
        for b in range(len(q)):
            for i, body in enumerate(self._link_bodies):
                body.position = (float(points[b, i, 0]), float(points[b, i, 1]))
                body.angle = float(angles[b, i])
                self._space.reindex_shapes_for_body(body)  # shape_query reads the cached world geometry
            # distance <= 0, not < 0: for a box centred exactly across a link (a tie between two penetration
            # directions) pymunk 7 reports a contact of distance 0.0
            out[b] = any(pt.distance <= 0.0 for shape in self._part_shapes for hit in self._space.shape_query(shape)
                         for pt in hit.contact_point_set.points)
        return out[0] if single else out

    # ---- scenarios ---------------------------------------------------------------------------
    def _draw_scene(self, rng):
        """One candidate scene: (obstacles (N, 5), goal (2,)), or None where blocks overlap. The authors'
        placement (docs/AUTHORS_SETUP.md §1): each block at an angle uniform in [0, 2 pi) around the shoulder, at a
        distance uniform in target_radius / obstacle_radius; the obstacles may or may not block the way."""
        cfg = self.cfg

        def polar(radius_range):
            angle, radius = rng.uniform(0.0, 2 * math.pi), rng.uniform(*radius_range)
            return self.base + radius * np.array([math.cos(angle), math.sin(angle)])

        goal = polar(cfg.target_radius)
        centres = np.array([polar(cfg.obstacle_radius) for _ in range(cfg.n_obstacles)])
        half = 0.5 * np.array([cfg.target_size] + [cfg.obstacle_size] * cfg.n_obstacles)
        blocks = np.concatenate([goal[None], centres])  # axis-aligned squares: the gap is the larger per-axis gap
        for i in range(len(blocks)):
            for j in range(i):
                gap = np.max(np.abs(blocks[i] - blocks[j]) - half[i] - half[j])
                if gap < cfg.block_clearance:
                    return None
        h = 0.5 * cfg.obstacle_size
        obstacles = np.c_[centres, np.full((cfg.n_obstacles, 2), h), np.zeros(cfg.n_obstacles)]
        return obstacles, goal

    def goal_configurations(self, n_angles=None):
        """Collision-free joint configurations, within the limits, with the end effector exactly at the goal.
        (M, 3). Closed-form IK: for each orientation phi of the last link the wrist is at goal - l3 (cos phi,
        sin phi), and its 2-link IK has two elbow solutions."""
        goal, n = self._goal, n_angles or self.cfg.n_goal_angles
        l1, l2, l3 = self.chain_lengths
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

    def _shoulder_can_reach(self, start, goal_qs, n=720):
        """A necessary condition for a path from start to one of goal_qs: joint 0 stops at +-pi and an obstacle
        within link 1's reach blocks some of its angles, so the start's and a goal's joint 0 share a free interval."""
        q0 = np.linspace(self._lo[0], self._hi[0], n)
        cx, cy, c, s, hx, hy = (x[:1] for x in self.part_boxes(np.c_[q0, np.zeros((n, 2))]))
        free = np.ones(n, dtype=bool)
        for box in zip(*self._obstacle_boxes):
            free &= box_distance((cx, cy, c, s, hx, hy), tuple(np.asarray(v) for v in box))[0] >= self.contact_margin
        # the interval of free samples around the start (a blocked sample ends it)
        i = int(np.clip(np.searchsorted(q0, start[0]), 0, n - 1))
        blocked = np.flatnonzero(~free)
        lo = q0[blocked[blocked < i].max()] if np.any(blocked < i) else -np.inf
        hi = q0[blocked[blocked >= i].min()] if np.any(blocked >= i) else np.inf
        return bool(np.any((goal_qs[:, 0] > lo) & (goal_qs[:, 0] < hi)))

    def _draw_scenario(self, rng):
        """reset's scenario: install the scene and return the start (3,). Rejection sampling from one rng stream:
        a scene is re-drawn when blocks overlap, when it has fewer than min_goal_configurations free IK solutions,
        or when none of 64 uniform starts is free, off the target and able to turn its shoulder to a goal."""
        while True:
            scene = self._draw_scene(rng)
            if scene is None:
                continue
            self.set_scene(*scene)
            goal_qs = self.goal_configurations()
            if len(goal_qs) < self.cfg.min_goal_configurations:
                continue
            candidates = rng.uniform(self._lo, self._hi, size=(64, self.dof))
            ok = ~self.in_collision(candidates) & ~self.goal_reached(candidates)
            if not ok.any():
                continue
            start = candidates[np.argmax(ok)]
            if self._shoulder_can_reach(start, goal_qs):
                return start

    # ---- observations ---------------------------------------------------------------------------
    def make_obs(self, q, q_prev):
        """Observations (B, obs_dim) float32 for the current scenario, the end effector from q; (dof,) -> (obs_dim,)."""
        obs, q, single = self._joint_goal_obs(q, q_prev)
        obs[:, 2 * self.dof + self.dim:-2] = self._obstacle_obs  # obstacle centres
        obs[:, -2:] = self.ee(q)
        return obs[0] if single else obs

    simulator_in_collision = pymunk_in_collision  # the contact check that judges a step: the simulator's

    # ---- drawing -----------------------------------------------------------------------------
    def render(self, ax, q=None, alpha=1.0, color="tab:blue", show_scene=True):
        """Fig. 5: obstacles, the target (dashed: the success radius) and the arm at q (default: current; (dof,)
        or (B, dof)) as polygons to scale. alpha / color style the arm; show_scene=False draws only the arm."""
        from matplotlib.patches import Circle, Polygon

        if show_scene:
            for cx, cy, hx, hy, angle in self.obstacles:
                xs, ys = box_corners(cx, cy, math.cos(angle), math.sin(angle), hx, hy)
                ax.add_patch(Polygon(np.c_[xs, ys], closed=True, color="0.35", lw=0))
            h = 0.5 * self.cfg.target_size
            ax.add_patch(Polygon(self._goal + np.array([[h, h], [-h, h], [-h, -h], [h, -h]]),
                                 closed=True, color="tab:green", alpha=0.8, lw=0))
            ax.add_patch(Circle(self._goal, self.goal_tolerance, fill=False, color="tab:green",
                                linestyle="--", lw=1))
            ax.plot(*self.base, "ks", markersize=5)
            reach = self.chain_lengths.sum() + 0.05
            ax.set(xlim=(self.base[0] - reach, self.base[0] + reach), ylim=(self.base[1] - reach, self.base[1] + reach),
                   aspect="equal", xlabel="x [m]", ylabel="z [m]")  # the arm's vertical plane (the URDF's x-z)
        q = np.atleast_2d(self._q if q is None else q)
        cx, cy, c, s, hx, hy = self.part_boxes(q)  # (n_parts, B) each
        for b in range(len(q)):
            for p in range(len(self.parts)):
                xs, ys = box_corners(cx[p, b], cy[p, b], c[p, b], s[p, b], hx[p, b], hy[p, b])
                ax.add_patch(Polygon(np.c_[xs, ys], closed=True, color=color, alpha=alpha, lw=0))
            joints = self.fk(q[b])[:-1]
            ax.plot(joints[:, 0], joints[:, 1], "o", color="k", markersize=2, alpha=alpha)
        return ax


# ---- The planar check's box geometry (numpy) -----------------------------------------------------
# A box is its centre (x, y), cos and sin of its angle, and half extents (hx, hy) along its own axes.
def point_box_distance(px, py, cx, cy, cos, sin, hx, hy):
    """Distance from point p to the box (0 inside): in the box's frame, |max(|p_local| - h, 0)|."""
    dx, dy = px - cx, py - cy
    lx = np.maximum(np.abs(dx * cos + dy * sin) - hx, 0.0)  # local x = p . u
    ly = np.maximum(np.abs(-dx * sin + dy * cos) - hy, 0.0)  # local y = p . n
    return np.sqrt(lx * lx + ly * ly)


CORNER_SIGNS = np.array([(1, 1), (-1, 1), (-1, -1), (1, -1)], dtype=float).T  # (2, 4): each corner's (sx, sy)


def box_corners(cx, cy, cos, sin, hx, hy):
    """The four corners of each box: (xs, ys), each (4, *cx's shape)."""
    sx, sy = (signs.reshape((4,) + (1,) * np.ndim(cx)) for signs in CORNER_SIGNS)
    return cx + sx * hx * cos - sy * hy * sin, cy + sx * hx * sin + sy * hy * cos


def box_distance(a, b):
    """Distance between boxes a and b (0 if they overlap). a, b: tuples (cx, cy, cos, sin, hx, hy). Exact:
    overlap <=> no separating axis among the four edge normals (the separating axis theorem), and two disjoint
    convex polygons are closest at a vertex of one of them: the smallest of the 8 corner-to-box distances."""
    both = np.broadcast_arrays(*a, *b)  # every entry of the same shape S
    a, b = both[:6], both[6:]
    acx, acy, ac, as_, ahx, ahy = a
    bcx, bcy, bc, bs, bhx, bhy = b
    dx, dy = bcx - acx, bcy - acy
    ex, ey = np.stack([ac, -as_, bc, -bs]), np.stack([as_, ac, bs, bc])  # (4, *S): the axes u_a, n_a, u_b, n_b
    ra = ahx * np.abs(ac * ex + as_ * ey) + ahy * np.abs(-as_ * ex + ac * ey)  # a's half shadow on each
    rb = bhx * np.abs(bc * ex + bs * ey) + bhy * np.abs(-bs * ex + bc * ey)
    overlap = np.all(np.abs(dx * ex + dy * ey) <= ra + rb, axis=0)
    d = np.minimum(point_box_distance(*box_corners(*a), *b).min(axis=0),  # a's 4 corners to box b
                   point_box_distance(*box_corners(*b), *a).min(axis=0))  # b's 4 corners to box a
    return np.where(overlap, 0.0, d)


# ---- The UR5 engine lever's configuration (Table II; benchmarks/HISTORY.md, "The UR5 engine-lever task") --
# The authors' small-engine cell in our frame: their URDF base turned 180 deg about z; the table top is z = 0.
@dataclass
class EngineConfig:
    # --- the UR5 (radii from its datasheet's outer diameters) ---
    link_radii: tuple = (0.06, 0.06, 0.05, 0.045, 0.045, 0.045, 0.025, 0.02)  # m, per ENGINE_LINK_NAMES
    # rad. One turn per joint (the UR5 allows +-2 pi) spares the planner copies of each configuration; the
    # shoulder in [-pi, 0] keeps the upper arm above the table; the elbow stops at +-160 deg before the
    # forearm folds onto the upper arm (adjacent capsules, which the checks ignore).
    joint_lo: tuple = (-math.pi, -math.pi, -2.8, -math.pi, -math.pi, -math.pi)
    joint_hi: tuple = (math.pi, 0.0, 2.8, math.pi, math.pi, math.pi)  # rad
    # --- the task: "the robot moves at similar velocities as the 2D planar reacher" (Sec. V) ---
    max_step: float = 0.05  # rad/step, per-joint speed limit (0.5 rad/s at dt = 0.1 s), as planar
    dt: float = 0.1  # s per step (the authors run at 30 Hz; dt = 1/30 gives theirs)
    goal_tolerance: float = 0.03  # m, success: the TCP this close to the goal (+ 10 deg: experiment/oriented_goal.py)
    max_steps: int = 333  # steps: the authors evaluate 1000 frames at 30 Hz (33 s), the same seconds here
    start_clearance: float = 0.02  # m, a start keeps this from everything (the authors' planning clearance)
    start_goal_min_dist: float = 0.5  # m, start TCP at least this far from the goal
    # --- the scene (EngineReach3D._draw_authors_scene) ---
    # rad, the goal posture: the authors' q_goal_bias (their demos' IK seed); the goal is its TCP
    goal_q: tuple = (1.223, -1.587, 2.082, -0.925, -0.496, -1.124)
    # The small engine, fixed: a block capsule and a fuel-tank capsule on top, (x0, y0, z0, x1, y1, z1, radius) m
    engine_parts: tuple = ((0.50, -0.46, 0.15, 0.50, -0.26, 0.15, 0.15),
                           (0.47, -0.45, 0.36, 0.47, -0.28, 0.36, 0.06))
    wall_y: float = 0.225  # m, a wall behind the robot: everything at y >= wall_y is solid (theirs: a cuboid)
    # The two boxes on the table, drawn per seed: capsules lying on the table with centre x, y ranges (m), an
    # axis ('x' or 'y'), length (m) and radius (m, = half its height), both scaled by one box_scale factor
    box_x: tuple = ((-0.50, -0.15), (-0.30, 0.40))  # m
    box_y: tuple = ((-0.50, -0.30), (-0.80, -0.60))  # m
    box_axis: tuple = ("y", "x")  # the two boxes stand at 90 deg to each other
    box_length: tuple = (0.30, 0.30)  # m, centre line (the box's long side minus its height)
    box_radius: tuple = (0.09, 0.09)  # m
    box_scale: tuple = (0.9, 1.1)  # uniform factor on length and radius
    lever_offset: float = 0.08  # m, goal (TCP) to the lever handle's axis along the tool axis
    # A scene needs this many free goal_configurations (a goal reached from a sliver of joint space is a needle's eye)
    min_goal_configurations: int = 40
    n_goal_directions: int = 48  # tool axes tried by goal_configurations (Fibonacci sphere) ...
    n_goal_rolls: int = 4  # ... times rotations of the fingers about it (0, 45, 90, 135 deg)
    # --- not in the paper ---
    tool_length: float = 0.10  # m, flange to tool centre point (TCP) along z6 (this project's tool)
    finger_half_width: float = 0.045  # m, the fingers: a bar along x6 across the probe's tip (joint 6 matters)
    # States checked for contact per step: an arm point moves <= 0.21 m a step, 0.052 m between checks, less
    # than the thinnest band to pass through, 2 x (fingers 0.02 + lever shaft 0.015) = 0.07 m
    n_substeps: int = 4
    n_max_obstacles: int = 16  # obstacle slots in the observation (absent = zeros); the authors' scenes have 6


# ---- UR5 engine-lever reaching (Sec. V, Table II) ------------------------------------------------
pb = None  # the pybullet module, imported by the first EngineReach3D (the planar env never needs it)

# UR5 (CB3) standard Denavit-Hartenberg parameters, as published by Universal Robots
# ("DH parameters for calculations of kinematics and dynamics", universal-robots.com, UR5 row).
# Frame i follows frame i-1 by T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i); frame 6 is the flange.
UR5_D = np.array([0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823])  # m, offsets along z_{i-1}
UR5_A = np.array([0.0, -0.425, -0.39225, 0.0, 0.0, 0.0])  # m, lengths along x_i
UR5_ALPHA = np.array([math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0])  # rad, twists

# The arm as 8 capsules (link_segments): wrist 3 from its centre to the flange, the probe from there to the TCP
ENGINE_LINK_NAMES = ("base", "upper_arm", "forearm", "wrist1", "wrist2", "wrist3", "probe", "fingers")
# The fixed camera of Fig. 5 and of the image variant: in front of the robot, looking at the engine and goal
ENGINE_CAMERA = dict(eye=(-0.35, -1.45, 1.0), target=(0.15, -0.3, 0.2), fov=60.0)
_CAPSULE_START = [0, 1, 2, 3, 4, 5, 6, 8]  # rows of EngineReach3D._capsule_points where each
_CAPSULE_END = [1, 2, 3, 4, 5, 6, 7, 9]  # capsule of ENGINE_LINK_NAMES starts / ends
# Self-collision pairs: those that can meet when the arm folds. Consecutive capsules share a joint; in the wrist
# the DH offsets hold the other pairs apart whatever the angles (e.g. forearm-wrist 2: d4 = 0.109 m, radii 0.095):
# they never touch, and a planner's margin of a few mm would flag every configuration
ENGINE_SELF_PAIRS = np.array([(0, j) for j in range(2, 8)]  # base column vs forearm .. fingers
                             + [(1, j) for j in range(3, 8)]  # upper arm vs wrist 1 .. fingers
                             + [(2, 5), (2, 6), (2, 7), (3, 7)])  # forearm / wrist 1 vs the tool


class EngineReach3D(ArmEnv):
    """UR5 reaching an engine lever through a cluttered, narrow passage (Sec. V, Table II, Fig. 5).

    The paper's mockup is Gaussian splats; here the authors' small-engine cell is capsules: the engine and its
    lever fixed, the goal the TCP of their goal posture (the witness), a wall behind the robot (the half-space
    y >= wall_y), the table (the ground z = 0) and two boxes drawn per seed. One geometry (capsules: segment +
    radius, `self.obstacles` and `link_segments`) feeds pybullet (step's simulator) and the numpy in_collision.

    Observation layout (float32, obs_dim = 2 dof + 3 + 7 n_max_obstacles = 127):
        [0:6]     q       current joint positions (rad)
        [6:12]    q_prev  joint positions one step earlier (rad)
        [12:15]   goal    TCP goal (x, y, z) in m
        [15:127]  obstacles, n_max_obstacles slots of (x0, y0, z0, x1, y1, z1, radius) in m
    The paper's policy sees a camera image instead of the obstacles: the variant 'engine3d_image'
    (experiment/image_obs.py) replaces [15:] by it.
    """

    dim, dof = 3, 6  # workspace dimension, joints
    collision_chunk = 1024  # configurations per pass of in_collision: the temporaries stay in cache

    def __init__(self, config: EngineConfig | None = None):
        global pb
        if pb is None:  # the simulator, imported with the first UR5 env
            import pybullet
            pb = pybullet
        cfg = config or EngineConfig()
        super().__init__(cfg)
        self._wall_y = float(cfg.wall_y)  # the wall of the authors' cell: a half-space y >= wall_y
        self.link_radii = np.asarray(cfg.link_radii, dtype=np.float64)  # (8,) per ENGINE_LINK_NAMES
        self.link_radius = float(self.link_radii.min())  # oracle.py's check spacing derives from it
        self.max_step = float(cfg.max_step)
        self.max_steps = int(cfg.max_steps)
        self.obs_dim = 2 * self.dof + self.dim + 7 * cfg.n_max_obstacles
        self.witness = None  # (6,) the collision-free goal posture the scene was built around
        self._client = None  # pybullet DIRECT client, created by the first set_scene
        seg = self.link_segments(np.zeros(self.dof))[0]
        self.link_lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)  # (8,) rigid: same at every q
        i, j = ENGINE_SELF_PAIRS.T
        self._self_contact = self.link_radii[i] + self.link_radii[j]  # (P,) radii sums
        self.set_scene(np.zeros((0, 7)))

    # ---- kinematics and geometry -------------------------------------------------------------
    def _capsule_points(self, q):
        """(B, 10, 3): base, shoulder, elbow, wrist 1-3 centres, flange, TCP, the two finger ends: the DH chain of
        ur5_frames point by point. Joints 2-4 are parallel: shoulder, elbow and wrist 1 move in the vertical plane
        at angle q1, in-plane angles q2, q2 + q3, q2 + q3 + q4; the lateral axis z1 = (sin q1, -cos q1, 0)."""
        B = len(q)
        c1, s1 = np.cos(q[:, 0:1]), np.sin(q[:, 0:1])  # (B, 1)
        radial = np.concatenate([c1, s1, np.zeros_like(c1)], axis=1)  # (B, 3) in the arm's plane
        lateral = np.concatenate([s1, -c1, np.zeros_like(c1)], axis=1)  # (B, 3) z1 = z2 = z3
        up = np.array([0.0, 0.0, 1.0])
        angles = np.cumsum(q[:, 1:4], axis=1)  # (B, 3) q2, q2 + q3, q2 + q3 + q4
        cos, sin = np.cos(angles), np.sin(angles)
        p = np.empty((B, 10, 3))
        p[:, 0] = 0.0
        p[:, 1] = UR5_D[0] * up  # shoulder
        p[:, 2] = p[:, 1] + UR5_A[1] * (cos[:, 0:1] * radial + sin[:, 0:1] * up)  # elbow
        p[:, 3] = p[:, 2] + UR5_A[2] * (cos[:, 1:2] * radial + sin[:, 1:2] * up)  # wrist 1
        p[:, 4] = p[:, 3] + UR5_D[3] * lateral  # wrist 2
        x4 = cos[:, 2:3] * radial + sin[:, 2:3] * up  # (B, 3) axes of frame 4
        z4 = sin[:, 2:3] * radial - cos[:, 2:3] * up
        p[:, 5] = p[:, 4] + UR5_D[4] * z4  # wrist 3
        c5, s5, c6, s6 = np.cos(q[:, 4:5]), np.sin(q[:, 4:5]), np.cos(q[:, 5:6]), np.sin(q[:, 5:6])
        z6 = c5 * lateral - s5 * x4  # = z5: the flange axis
        x5 = c5 * x4 + s5 * lateral
        x6 = c6 * x5 + s6 * np.cross(z6, x5)  # joint 6 turns the fingers about z6
        p[:, 6] = p[:, 5] + UR5_D[5] * z6  # flange
        p[:, 7] = p[:, 6] + self.cfg.tool_length * z6  # TCP: the probe runs along the flange axis
        # The finger bar crosses the probe just behind the TCP, its tips exactly as far from the wrist-3 centre
        # as the TCP: no arm point is farther from joint j than the fk chain beyond j (planners' lever arms).
        reach = UR5_D[5] + self.cfg.tool_length  # wrist-3 centre to TCP
        w = self.cfg.finger_half_width
        centre = p[:, 5] + math.sqrt(reach * reach - w * w) * z6
        p[:, 8], p[:, 9] = centre - w * x6, centre + w * x6
        return p

    def fk(self, q):
        """Joint points (B, 7, 3): the origins of the DH frames 0..5 (base, shoulder, elbow, wrist 1-3; the DH
        model puts the real arm's shoulder and elbow offsets into d4) and the TCP, the end effector."""
        q, single = _as_batch(q, self.dof)
        points = self._capsule_points(q)[:, [0, 1, 2, 3, 4, 5, 7]]
        return points[0] if single else points

    def link_segments(self, q):
        """Arm capsules (B, 8, 2, 3): end points in ENGINE_LINK_NAMES order (radii: link_radii)."""
        q, _ = _as_batch(q, self.dof)
        p = self._capsule_points(q)  # (B, 10, 3)
        return np.stack([p[:, _CAPSULE_START], p[:, _CAPSULE_END]], axis=2)

    def _arm_components(self, q):
        """Arm capsule end points, components first: a0, a1 (3, B, 8) (contiguous, for speed)."""
        p = self._capsule_points(q).transpose(2, 0, 1)  # (3, B, 10)
        return np.ascontiguousarray(p[:, :, _CAPSULE_START]), np.ascontiguousarray(p[:, :, _CAPSULE_END])

    def _ground_clearance(self, a0, a1):
        """(B,) lowest point of the forearm .. fingers above the ground z = 0 (the upper arm points upward)."""
        return (np.minimum(a0[2, :, 2:], a1[2, :, 2:]) - self.link_radii[2:]).min(axis=1)

    def _wall_clearance(self, a0, a1):
        """(B,) distance from the arm's capsules to the wall's face y = wall_y (at a capsule's end point)."""
        return (self._wall_y - np.maximum(a0[1], a1[1]) - self.link_radii).min(axis=1)

    def _in_collision_chunk(self, q, margin):
        """in_collision: the arm within margin of an obstacle, the wall, the ground or itself (ENGINE_SELF_PAIRS).
        Axis-aligned boxes rule out most pairs, segment distances decide the rest; the base column never moves."""
        a0, a1 = self._arm_components(q)  # (3, B, 8) each
        hit = (self._ground_clearance(a0, a1) < margin) | (self._base_clearance < margin)  # (B,)
        hit |= self._wall_clearance(a0, a1) < margin
        # broad phase: capsules whose axis-aligned boxes, grown by the margin, do not overlap are not closer
        lo = np.minimum(a0, a1) - self.link_radii - margin  # (3, B, 8)
        hi = np.maximum(a0, a1) + self.link_radii + margin
        g = self._geom  # obstacle boxes precomputed by set_scene
        n_obs = len(self.obstacles)
        near = np.ones((len(q), 7, n_obs), dtype=bool)  # arm capsules 1..7 vs obstacles
        for k in range(3):
            near &= (lo[k][:, 1:, None] <= g["hi"][k]) & (hi[k][:, 1:, None] >= g["lo"][k])
        b_obs, rest = np.divmod(np.flatnonzero(near), 7 * n_obs)
        link, o = np.divmod(rest, n_obs) if n_obs else (rest, rest)
        link += 1
        i, j = ENGINE_SELF_PAIRS.T
        near = np.ones((len(q), len(i)), dtype=bool)  # self-collision pairs, (B, P)
        for k in range(3):
            near &= (lo[k][:, i] <= hi[k][:, j] + margin) & (hi[k][:, i] >= lo[k][:, j] - margin)
        b_self, pair = np.divmod(np.flatnonzero(near), len(i))
        # narrow phase: an arm capsule (flat index config * 8 + capsule) against an obstacle or an arm capsule
        a0, a1 = a0.reshape(3, -1), a1.reshape(3, -1)
        arm = np.concatenate([b_obs * 8 + link, b_self * 8 + i[pair]])
        other = b_self * 8 + j[pair]
        dist = segment_distance_3d(a0[:, arm], a1[:, arm],
                                   np.concatenate([g["start"][:, o], a0[:, other]], axis=1),
                                   np.concatenate([g["end"][:, o], a1[:, other]], axis=1))
        contact = np.concatenate([g["contact"][link, o], self._self_contact[pair]]) + margin
        hit[np.concatenate([b_obs, b_self])[dist < contact]] = True
        return hit

    # ---- scene installation -------------------------------------------------------------------
    def set_scene(self, obstacles, goal=None, kinds=None):
        """Install a scene: obstacles (N, 7) rows (x0, y0, z0, x1, y1, z1, radius), goal (3,), for both collision
        checks; kinds: 'engine', 'lever', 'pipe' (the default) or 'box' per obstacle (colours only)."""
        self._set_obstacles(obstacles, kinds)
        if goal is not None:
            self._goal = np.array(goal, dtype=np.float64).reshape(self.dim)
        self._obstacle_obs = np.zeros(7 * self.cfg.n_max_obstacles, dtype=np.float32)
        self._obstacle_obs[: self.obstacles.size] = self.obstacles.ravel()
        self._build_bullet()

    def _set_obstacles(self, obstacles, kinds=None):
        """Obstacle array and the broad-phase geometry of in_collision (no pybullet rebuild)."""
        obstacles = np.asarray(obstacles, dtype=np.float64).reshape(-1, 7)
        kinds = ["pipe"] * len(obstacles) if kinds is None else list(kinds)
        self.obstacles, self.obstacle_kinds = obstacles, kinds
        start, end, radius = obstacles[:, 0:3].T, obstacles[:, 3:6].T, obstacles[:, 6]  # (3, N)
        self._geom = dict(start=start.copy(), end=end.copy(),
                          lo=np.minimum(start, end) - radius, hi=np.maximum(start, end) + radius,
                          contact=self.link_radii[:, None] + radius)  # (8, N) radii sums
        base_a, base_b = self.link_segments(np.zeros(self.dof))[0, 0]  # the same at every q
        base = segment_distance_3d(base_a[:, None], base_b[:, None], start, end)  # (N,)
        self._base_clearance = float(np.min(base - self.link_radii[0] - radius, initial=np.inf))

    # ---- pybullet mirror (the simulator) -----------------------------------------------------
    def _build_bullet(self):
        """pybullet DIRECT world of the current scene: arm capsule bodies, obstacles, ground, wall, goal."""
        if self._client is None:
            self._client = pb.connect(pb.DIRECT)
        cid = self._client
        pb.resetSimulation(physicsClientId=cid)
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=cid)
        floor_visual = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[1.5, 1.5, 0.005], rgbaColor=[0.85, 0.85, 0.82, 1],
                                            visualFramePosition=[0, 0, -0.005], physicsClientId=cid)
        self._ground = pb.createMultiBody(0, plane, floor_visual, physicsClientId=cid)
        # arm: one capsule body per link, placed by our FK. Mass > 0 makes them dynamic bodies, which pybullet
        # tests against the static obstacles; we never call stepSimulation, so nothing moves by itself.
        self._link_bodies = []
        for name, length, radius in zip(ENGINE_LINK_NAMES, self.link_lengths, self.link_radii):
            color = [0.2, 0.5, 0.85, 1] if name in ("probe", "fingers") else [0.75, 0.78, 0.82, 1]
            self._link_bodies.append(self._capsule_body(float(length), float(radius), color, mass=1.0))
        bodies, checked = self._link_bodies, {tuple(pair) for pair in ENGINE_SELF_PAIRS.tolist()}
        for i in range(len(bodies)):  # arm pairs outside ENGINE_SELF_PAIRS: no contacts
            for j in range(i + 1, len(bodies)):
                if (i, j) not in checked:
                    pb.setCollisionFilterPair(bodies[i], bodies[j], -1, -1, 0, physicsClientId=cid)
        for body in bodies[:2]:  # base, upper arm never reach the ground (_ground_clearance)
            pb.setCollisionFilterPair(body, self._ground, -1, -1, 0, physicsClientId=cid)
        half = [1.5, 0.25, 0.75]  # the wall: a 0.5 m thick slab whose face is the plane y = wall_y
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=cid)
        visual = pb.createVisualShape(pb.GEOM_BOX, halfExtents=half, rgbaColor=[0.87, 0.8, 0.75, 1],
                                      physicsClientId=cid)
        pb.createMultiBody(0, shape, visual, basePosition=[0.0, self._wall_y + half[1], half[2]], physicsClientId=cid)
        colors = {"engine": [0.25, 0.25, 0.28, 1],
                  "lever": [0.85, 0.15, 0.1, 1], "pipe": [0.9, 0.55, 0.1, 1], "box": [0.62, 0.45, 0.3, 1]}
        for (x0, y0, z0, x1, y1, z1, radius), kind in zip(self.obstacles, self.obstacle_kinds):
            a, b = np.array([x0, y0, z0]), np.array([x1, y1, z1])
            body = self._capsule_body(float(np.linalg.norm(b - a)), float(radius), colors[kind], mass=0.0)
            quat = _quaternion_z_to(((b - a) / max(np.linalg.norm(b - a), 1e-12))[None])[0]  # z axis along b - a
            pb.resetBasePositionAndOrientation(body, ((a + b) / 2).tolist(), quat.tolist(), physicsClientId=cid)
        goal_visual = pb.createVisualShape(pb.GEOM_SPHERE, radius=self.goal_tolerance / 2, rgbaColor=[0.1, 0.8, 0.2, 1],
                                           physicsClientId=cid)
        pb.createMultiBody(0, -1, goal_visual, basePosition=self._goal.tolist(), physicsClientId=cid)

    def _capsule_body(self, length, radius, color, mass):
        """A capsule body along its local z axis."""
        cid = self._client
        shape = pb.createCollisionShape(pb.GEOM_CAPSULE, radius=radius, height=length, physicsClientId=cid)
        visual = pb.createVisualShape(pb.GEOM_CAPSULE, radius=radius, length=length, rgbaColor=color,
                                      physicsClientId=cid)
        return pb.createMultiBody(mass, shape, visual, physicsClientId=cid)

    def _pose_arm(self, q):
        """Place the arm's capsule bodies at configuration q (dof,)."""
        seg = self.link_segments(q)[0]  # (8, 2, 3)
        centres = seg.mean(axis=1)
        directions = seg[:, 1] - seg[:, 0]
        quats = _quaternion_z_to(directions / np.linalg.norm(directions, axis=1, keepdims=True))
        for body, c, quat in zip(self._link_bodies, centres, quats):
            pb.resetBasePositionAndOrientation(body, c.tolist(), quat.tolist(), physicsClientId=self._client)

    def pybullet_in_collision(self, q):
        """Same predicate as in_collision, from pybullet contacts (one config at a time, slower)."""
        q, single = _as_batch(q, self.dof)
        out = np.zeros(len(q), dtype=bool)
        for b in range(len(q)):
            self._pose_arm(q[b])
            pb.performCollisionDetection(physicsClientId=self._client)
            # contacts are reported a little before touching; penetration = negative distance
            out[b] = any(c[8] < 0.0 for c in pb.getContactPoints(physicsClientId=self._client))
        return out[0] if single else out

    # ---- scenarios ---------------------------------------------------------------------------
    def goal_configurations(self):
        """Collision-free joint configurations (M, 6), within the limits, with the TCP exactly at the goal: ur5_ik
        for n_goal_directions tool axes z6 over the sphere times n_goal_rolls finger rotations, 8 branches each."""
        goal, n_dir, n_roll = self._goal, self.cfg.n_goal_directions, self.cfg.n_goal_rolls
        axes = fibonacci_sphere(n_dir)  # (D, 3) tool axes z6
        helper = np.where(np.abs(axes[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
        x0 = np.cross(helper, axes)
        x0 /= np.linalg.norm(x0, axis=1, keepdims=True)  # (D, 3) a finger direction _|_ z6
        y0 = np.cross(axes, x0)
        roll = np.arange(n_roll) * math.pi / n_roll  # the finger bar is symmetric under a half turn
        x6 = np.cos(roll)[:, None, None] * x0 + np.sin(roll)[:, None, None] * y0  # (R, D, 3)
        z6 = np.broadcast_to(axes, x6.shape)
        flange = np.zeros(x6.shape[:2] + (4, 4))  # (R, D, 4, 4)
        flange[..., :3, 0], flange[..., :3, 1], flange[..., :3, 2] = x6, np.cross(z6, x6), z6
        flange[..., :3, 3] = goal - self.cfg.tool_length * z6  # TCP on the goal
        flange[..., 3, 3] = 1.0
        q = ur5_ik(flange.reshape(-1, 4, 4)).reshape(-1, self.dof)  # (R D 8, 6)
        q = q[~np.isnan(q).any(axis=1)]
        q = q[np.all((q >= self._lo) & (q <= self._hi), axis=1)]
        return q[~self.in_collision(q)] if len(q) else q

    def _draw_authors_scene(self, rng):
        """One candidate scene of the authors' cell: (obstacles (N, 7), kinds, goal (3,), witness (6,)). Fixed:
        the engine, the goal posture cfg.goal_q, its TCP (the goal), a T-handle lever just beyond it along the tool
        axis, its shaft on into the engine. Drawn: the two boxes, centre uniform in box_x x box_y, scaled."""
        cfg = self.cfg
        q_goal = np.asarray(cfg.goal_q, dtype=np.float64)
        frame6 = ur5_frames(q_goal[None])[0, 6]
        tool_axis, handle_axis = frame6[:3, 2], frame6[:3, 1]
        goal = self.ee(q_goal)
        obstacles, kinds = [list(part) for part in cfg.engine_parts], ["engine"] * len(cfg.engine_parts)
        handle = goal + cfg.lever_offset * tool_axis  # T-handle across the fingers' grasp
        obstacles.append([*(handle - 0.05 * handle_axis), *(handle + 0.05 * handle_axis), 0.02])
        obstacles.append([*handle, *(handle + 0.25 * tool_axis), 0.015])  # shaft, on into the engine
        kinds += ["lever", "lever"]
        for (x_lo, x_hi), (y_lo, y_hi), axis, length, radius in zip(
                cfg.box_x, cfg.box_y, cfg.box_axis, cfg.box_length, cfg.box_radius):
            scale = rng.uniform(*cfg.box_scale)
            centre = np.array([rng.uniform(x_lo, x_hi), rng.uniform(y_lo, y_hi), radius * scale])
            half = 0.5 * length * scale * (np.array([1.0, 0, 0]) if axis == "x" else np.array([0, 1.0, 0]))
            obstacles.append([*(centre - half), *(centre + half), radius * scale])
            kinds.append("box")
        return np.asarray(obstacles, dtype=np.float64), kinds, goal, q_goal

    def _draw_scenario(self, rng):
        """reset's scenario: install the scene and return the start (6,). Rejection sampling from one rng stream:
        a scene is re-drawn when its witness collides, when it has fewer than min_goal_configurations free IK
        solutions (EngineReach3D's own goal set, also in a variant: the same scenes), or when none of 256 uniform
        starts is clear by start_clearance with its TCP start_goal_min_dist from the goal (the authors' start)."""
        cfg = self.cfg
        while True:
            obstacles, kinds, goal, self.witness = self._draw_authors_scene(rng)
            self._set_obstacles(obstacles, kinds)
            self._goal = goal
            if self.in_collision(self.witness):
                continue
            if len(EngineReach3D.goal_configurations(self)) < cfg.min_goal_configurations:
                continue
            q = rng.uniform(self._lo, self._hi, size=(256, self.dof))
            far = np.linalg.norm(self.ee(q) - self._goal, axis=1) >= cfg.start_goal_min_dist
            ok = far & ~self.in_collision(q, margin=cfg.start_clearance)
            if ok.any():
                self.set_scene(self.obstacles, self._goal, self.obstacle_kinds)
                return q[np.argmax(ok)]

    # ---- observations -------------------------------------------------------------------------
    def make_obs(self, q, q_prev):
        """Observations (B, obs_dim) float32 for the current scenario; (dof,) -> (obs_dim,)."""
        obs, _, single = self._joint_goal_obs(q, q_prev)
        obs[:, 2 * self.dof + self.dim:] = self._obstacle_obs
        return obs[0] if single else obs

    simulator_in_collision = pybullet_in_collision  # the contact check that judges a step: the simulator's

    # ---- images and drawing ------------------------------------------------------------------
    def camera_image(self, q=None, width=640, height=480):
        """RGB image (height, width, 3) uint8 of the scene with the arm at q (default: current), from the fixed
        camera ENGINE_CAMERA with pybullet's software renderer (ER_TINY_RENDERER: no display or GPU needed)."""
        self._pose_arm(self._q if q is None else q)
        cam = ENGINE_CAMERA
        view = pb.computeViewMatrix(list(cam["eye"]), list(cam["target"]), [0, 0, 1])
        projection = pb.computeProjectionMatrixFOV(cam["fov"], width / height, 0.05, 5.0)
        _, _, rgba, _, _ = pb.getCameraImage(width, height, view, projection, renderer=pb.ER_TINY_RENDERER,
                                             lightDirection=[0.6, -0.5, 1.0], shadow=0, physicsClientId=self._client)
        return np.reshape(np.asarray(rgba, dtype=np.uint8), (height, width, 4))[..., :3]

    def render(self, ax, q=None):
        """Fig. 5: camera_image of the scene with the arm at q (default: current; (dof,) or (B, dof): the first)."""
        q = self._q if q is None else np.asarray(q, dtype=np.float64)
        ax.imshow(self.camera_image(np.atleast_2d(q)[0], 480, 360))
        ax.set_axis_off()
        return ax

    def close(self):
        """Disconnect the pybullet client (set_scene or reset connects a new one)."""
        if self._client is not None:
            pb.disconnect(physicsClientId=self._client)
            self._client = None

    def __del__(self):  # free the pybullet client when the env is garbage-collected
        try:
            self.close()
        except Exception:  # interpreter shutdown: pybullet may already be gone
            pass


# ---- Capsule geometry and UR5 kinematics (EngineReach3D) -----------------------------------------
def segment_distance_3d(a0, a1, b0, b1):
    """Distance between segments [a0, a1] and [b0, b1], broadcasting; COMPONENTS FIRST: (3, ...) (contiguous
    memory). Ericson, Real-Time Collision Detection, Sec. 5.1.9: the closest points of the infinite
    lines, clamped to the segments, re-projected once (a zero-length segment: squared length floored at 1e-18)."""
    (ax, ay, az), (bx, by, bz) = a0, b0
    ux, uy, uz = a1[0] - ax, a1[1] - ay, a1[2] - az
    vx, vy, vz = b1[0] - bx, b1[1] - by, b1[2] - bz
    wx, wy, wz = ax - bx, ay - by, az - bz
    uu = np.maximum(ux * ux + uy * uy + uz * uz, 1e-18)
    vv = np.maximum(vx * vx + vy * vy + vz * vz, 1e-18)
    uv = ux * vx + uy * vy + uz * vz
    uw = ux * wx + uy * wy + uz * wz
    vw = vx * wx + vy * wy + vz * wz
    denom = uu * vv - uv * uv  # >= 0; ~0 for parallel segments, where any s works: take s = 0
    s = np.minimum(np.maximum((uv * vw - uw * vv) / np.maximum(denom, 1e-300), 0.0), 1.0)
    s = np.where(denom > 1e-12 * uu * vv, s, 0.0)
    t = (uv * s + vw) / vv  # closest point of b's line to a(s)
    # t outside [0, 1]: clamp it and recompute s as the closest point of a to that end of b
    s = np.where(t < 0, np.minimum(np.maximum(-uw / uu, 0.0), 1.0),
                 np.where(t > 1, np.minimum(np.maximum((uv - uw) / uu, 0.0), 1.0), s))
    t = np.minimum(np.maximum(t, 0.0), 1.0)
    dx, dy, dz = wx + s * ux - t * vx, wy + s * uy - t * vy, wz + s * uz - t * vz
    return np.sqrt(dx * dx + dy * dy + dz * dz)


def dh_transform(theta, d, a, alpha):
    """Standard DH link transform Rz(theta) Tz(d) Tx(a) Rx(alpha), batched: (...) -> (..., 4, 4)."""
    theta = np.asarray(theta, dtype=np.float64)
    d, a, alpha = (np.broadcast_to(np.asarray(x, dtype=np.float64), theta.shape) for x in (d, a, alpha))
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    T = np.zeros(theta.shape + (4, 4))
    T[..., 0, 0], T[..., 0, 1], T[..., 0, 2], T[..., 0, 3] = ct, -st * ca, st * sa, a * ct
    T[..., 1, 0], T[..., 1, 1], T[..., 1, 2], T[..., 1, 3] = st, ct * ca, -ct * sa, a * st
    T[..., 2, 1], T[..., 2, 2], T[..., 2, 3] = sa, ca, d
    T[..., 3, 3] = 1.0
    return T


def ur5_frames(q):
    """World frames of the UR5 DH chain: (B, 7, 4, 4) = base, frames 1..6 (frame 6 = flange)."""
    T = dh_transform(q, UR5_D, UR5_A, UR5_ALPHA)  # (B, 6, 4, 4): frame i in frame i-1
    frames = np.empty((len(T), 7, 4, 4))
    frames[:, 0] = np.eye(4)
    for i in range(6):
        frames[:, i + 1] = frames[:, i] @ T[:, i]
    return frames


def ur5_ik(flange):
    """Closed-form inverse kinematics: flange poses (P, 4, 4) -> joint solutions (P, 8, 6).

    The 8 branches are shoulder left/right x wrist up/down x elbow up/down; NaN rows where a branch
    does not exist (pose out of reach). Angles wrapped to [-pi, pi). The geometry of the UR5's DH
    chain (the derivation of Hawkins, "Analytic inverse kinematics for the Universal Robots
    UR-5/UR-10 arms", 2013, redone for the frames of ur5_frames):
      * the wrist-3 centre p5 = p6 - d6 z6 lies at distance d4 from the plane of the shoulder and
        elbow, which contains the base axis: p5 . z1 = d4, with z1 = (sin q1, -cos q1, 0)
        => q1 = atan2(p5y, p5x) + pi/2 +- acos(d4 / |p5xy|);
      * z1 seen from the flange is (sin q5 cos q6, -sin q5 sin q6, cos q5) => q5 = +-acos, then q6;
      * frame 4 = flange T6^-1 T5^-1, seen from frame 1, is a planar 2-link problem in q2, q3
        (lengths a2, a3), and q2 + q3 + q4 is the angle of its x axis.
    """
    P = len(flange)
    d1, d4, d5, d6 = UR5_D[0], UR5_D[3], UR5_D[4], UR5_D[5]
    a2, a3 = UR5_A[1], UR5_A[2]
    R, p5 = flange[:, :3, :3], flange[:, :3, 3] - d6 * flange[:, :3, 2]  # (P, 3, 3), (P, 3)
    rho = np.hypot(p5[:, 0], p5[:, 1])
    shoulder = np.arccos(np.clip(d4 / np.maximum(rho, 1e-12), -1.0, 1.0))
    out = np.full((P, 2, 2, 2, 6), np.nan)  # (P, shoulder, wrist, elbow, 6)
    for i, s1 in enumerate((1.0, -1.0)):
        q1 = np.arctan2(p5[:, 1], p5[:, 0]) + math.pi / 2 + s1 * shoulder  # (P,)
        z1 = np.stack([np.sin(q1), -np.cos(q1), np.zeros(P)], axis=1)
        v = np.einsum("pji,pj->pi", R, z1)  # z1 in flange coordinates
        for j, s5 in enumerate((1.0, -1.0)):
            q5 = s5 * np.arccos(np.clip(v[:, 2], -1.0, 1.0))
            sin5 = np.sin(q5)
            singular = np.abs(sin5) < 1e-9  # wrist singularity: q6 is free, take 0
            sin5 = np.where(singular, 1.0, sin5)
            q6 = np.where(singular, 0.0, np.arctan2(-v[:, 1] / sin5, v[:, 0] / sin5))
            frame4 = (np.linalg.inv(dh_transform(q1, d1, 0.0, math.pi / 2)) @ flange
                      @ np.linalg.inv(dh_transform(q6, d6, 0.0, 0.0))
                      @ np.linalg.inv(dh_transform(q5, d5, 0.0, -math.pi / 2)))  # (P, 4, 4) in frame 1
            x, y = frame4[:, 0, 3], frame4[:, 1, 3]
            cos3 = (x * x + y * y - a2 * a2 - a3 * a3) / (2 * a2 * a3)
            for k, s3 in enumerate((1.0, -1.0)):
                q3 = s3 * np.arccos(np.clip(cos3, -1.0, 1.0))
                q2 = np.arctan2(y, x) - np.arctan2(a3 * np.sin(q3), a2 + a3 * np.cos(q3))
                q4 = np.arctan2(frame4[:, 1, 0], frame4[:, 0, 0]) - q2 - q3
                q = np.stack([q1, q2, q3, q4, q5, q6], axis=1)
                q = (q + math.pi) % (2 * math.pi) - math.pi
                q[(rho < d4) | (np.abs(cos3) > 1.0)] = np.nan
                out[:, i, j, k] = q
    return out.reshape(P, 8, 6)


def fibonacci_sphere(n):
    """n unit vectors (n, 3) spread evenly over the sphere (golden-angle spiral)."""
    z = 1.0 - 2.0 * (np.arange(n) + 0.5) / n
    angle = np.arange(n) * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(angle), r * np.sin(angle), z], axis=1)


def _quaternion_z_to(direction):
    """Quaternions (x, y, z, w) (N, 4) turning the z axis onto unit vectors direction (N, 3)."""
    x, y, z = direction[:, 0], direction[:, 1], direction[:, 2]
    # half-angle form: q = (z_hat x d, 1 + z_hat . d), normalised; z_hat x d = (-y, x, 0)
    quat = np.stack([-y, x, np.zeros_like(z), 1.0 + z], axis=1)
    flipped = 1.0 + z < 1e-9  # d = -z: any half turn about a horizontal axis
    quat[flipped] = (1.0, 0.0, 0.0, 0.0)
    return quat / np.linalg.norm(quat, axis=1, keepdims=True)


# ---- Environments by name ------------------------------------------------------------------------
# name -> (env class, its config); a research variant (an EngineReach3D subclass) adds its own on import of its
# module: experiment/image_obs.py 'engine3d_image', experiment/oriented_goal.py 'engine3d_oriented'
ENVIRONMENTS = {"planar": (PlanarReacher, PlanarConfig), "engine3d": (EngineReach3D, EngineConfig)}
PAPER_ENVS = ("planar", "engine3d")  # the paper's two envs: what is keyed by env (its unit, its table) names these


def make_env(name="planar", **config):
    """Environment by name, e.g. make_env('planar', max_steps=200) (keywords: config fields)."""
    env_class, config_class = ENVIRONMENTS[name]
    return env_class(config_class(**config))


def paper_env(env):
    """The paper's env (PAPER_ENVS) that env is or derives from -- a variant's env subclasses one, and is that
    env for the paper's unit, table and sizes -- or None. env: a name of ENVIRONMENTS or an env object."""
    env_class = ENVIRONMENTS.get(env, (None,))[0] if isinstance(env, str) else type(env)
    return next((name for name in PAPER_ENVS
                 if env_class is not None and issubclass(env_class, ENVIRONMENTS[name][0])), None)


# ---- The unit of noise levels (Sec. V, Fig. 4): the median step of the demonstrations ------------
def median_step(episodes):
    """Median per-step joint displacement |q[t+1] - q[t]| over all steps and joints (Sec. V unit). Exact zeros
    (a joint pinned at a limit, an arm standing still) are ignored: a demo that waits does not shrink the unit."""
    steps = [np.abs(np.diff(np.asarray(ep["q"], dtype=np.float64), axis=0)).ravel() for ep in episodes]
    steps = np.concatenate(steps) if steps else np.zeros(0)
    steps = steps[steps > 0]
    assert len(steps), "median_step: the episodes contain no joint motion"
    return float(np.median(steps))


# The paper's own unit (docs/AUTHORS_SETUP.md §1): the median L2 norm over the joints of the authors' 30 Hz demo steps;
# ours (median_step) is per joint at the env's dt. In rad: sigma_ours * median_step = sigma_paper * this.
PAPER_MEDIAN_STEP = {"planar": 0.0176, "engine3d": 0.0166}  # rad, by the paper's env (paper_env)
PAPER_FRAME_DT = 1 / 30  # s: the authors' control period (30 Hz), the frame their velocities count per


def paper_median_step(env):
    """The paper's median step (rad) of env (a name of ENVIRONMENTS or an env object), or None where it has none."""
    return PAPER_MEDIAN_STEP.get(paper_env(env))


# ---- Fig. 5: the UR5's scene (the planar one: PlanarReacher.render, oracle.py) -------------------
def render_scene_image(env, path, q=None, width=640, height=480):
    """Save env.camera_image (the scene, arm at q) to path (.png) for figures; returns the image."""
    from matplotlib.image import imsave
    image = env.camera_image(q, width, height)
    imsave(path, image)
    return image


if __name__ == "__main__":
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env = make_env("planar")
    fig, axes = plt.subplots(1, 4, figsize=(16, 4))
    for ax, seed in zip(axes, env.eval_seeds()):
        env.reset(seed=seed)
        env.render(ax)
        ax.set_title(f"seed {seed}: {len(env.goal_configurations())} free goal configurations")
    fig.savefig("planar_scenes.png", dpi=80)
    print("wrote planar_scenes.png; obs_dim", env.obs_dim)
