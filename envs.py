"""The task of Table I: the planar 3-link reacher (Sec. V; Fig. 5), and what every env shares.

    Sec. V, Table I    the planar 3-link reacher ............... PlanarConfig, PlanarReacher
    Sec. V             100 fixed evaluation scenarios .......... eval_seeds (train_seeds, unseen_seeds: disjoint)
    Sec. V, Fig. 4     the "median step" unit of noise levels .. median_step (the paper's own: paper_median_step)
    Fig. 5             the planar scene ........................ PlanarReacher.render

Table II's UR5 env (EngineReach3D) is experiment/engine3d.py; it shares ArmEnv and one interface (gymnasium
conventions without the dependency):

    env = make_env('planar')                  # keywords: config fields (Table II's env: experiment/environments.py)
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


# ---- The planar reacher's configuration (Table I; the authors' setup: benchmarks/SETUP.md §1) ---------
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
def as_batch(q, dof):
    """(dof,) or (B, dof) array -> ((B, dof) float64, was_single)."""
    q = np.asarray(q, dtype=np.float64)
    single = q.ndim == 1
    if single:
        q = q[None]
    assert q.ndim == 2 and q.shape[1] == dof, f"q of shape {q.shape}, want ({dof},) or (B, {dof})"
    return q, single


class ArmEnv:
    """The part of the env interface (module docstring) that PlanarReacher and EngineReach3D share
    (experiment/engine3d.py). A subclass sets dof, dim, max_step, max_steps, obs_dim and supplies fk,
    _in_collision_chunk, simulator_in_collision (judges a step), make_obs, _draw_scenario, render; its config gives dt, goal_tolerance, joint_lo/hi and n_substeps."""

    # How a policy reads the observation: None, as numbers (diffusion.FlatObservation); a variant's env names its
    # encoder class and that class's keyword arguments (dagger.make_policy hands them to the policy)
    obs_encoder = None
    obs_encoder_args = {}
    paper_env = None  # the paper's env this one is or derives from ('planar': Table I; 'engine3d': Table II)
    paper_median_step = None  # rad: the paper's unit of noise levels for that env (Sec. V), None if it gives none
    max_parallel = None  # episodes of this env that may run in lockstep at once (None: any number)
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
        q, single = as_batch(q, self.dof)
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
        q, single = as_batch(q, self.dof)
        q_prev, _ = as_batch(q_prev, self.dof)
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
    observation.environment_state, benchmarks/SETUP.md §1):
        [0:3]    q        current joint positions (rad)
        [3:6]    q_prev   joint positions one step earlier (rad)
        [6:8]    target   centre of the target block (x, z) in m
        [8:10]   obstacle 1 centre (x, z) in m
        [10:12]  obstacle 2 centre (x, z) in m
        [12:14]  end effector (x, z) in m: forward kinematics of q (a noised state gets its own)
    The arm moves in the vertical (x, z) plane of the URDF; arrays call the second axis y.
    """

    dim, dof = 2, 3  # workspace dimension, joints
    paper_env, paper_median_step = "planar", 0.0176  # Table I; rad, the authors' median step (benchmarks/SETUP.md §1)
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
        q, single = as_batch(q, self.dof)
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
        q, single = as_batch(q, self.dof)
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
        placement (benchmarks/SETUP.md §1): each block at an angle uniform in [0, 2 pi) around the shoulder, at a
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


def make_env(name="planar", **config):
    """The env of a run by name, e.g. make_env('planar', max_steps=200) (keywords: config fields). This file holds
    Table I's planar reacher; Table II's UR5 and the variants' envs are made by experiment/environments.py."""
    if name != "planar":
        raise ValueError(f"unknown env {name!r}; envs.py makes 'planar' (Table II's 'engine3d' and its variants: "
                         "experiment.environments.make_env, which the harness hands the loop)")
    return PlanarReacher(PlanarConfig(**config))


# ---- The unit of noise levels (Sec. V, Fig. 4): the median step of the demonstrations ------------
def median_step(episodes):
    """Median per-step joint displacement |q[t+1] - q[t]| over all steps and joints (Sec. V unit). Exact zeros
    (a joint pinned at a limit, an arm standing still) are ignored: a demo that waits does not shrink the unit."""
    steps = [np.abs(np.diff(np.asarray(ep["q"], dtype=np.float64), axis=0)).ravel() for ep in episodes]
    steps = np.concatenate(steps) if steps else np.zeros(0)
    steps = steps[steps > 0]
    assert len(steps), "median_step: the episodes contain no joint motion"
    return float(np.median(steps))


# The authors' control period (30 Hz, benchmarks/SETUP.md §1): the frame their velocities count per. The paper's own
# unit of noise (an env's paper_median_step) is the median L2 norm over the joints of their 30 Hz demo steps; ours
# (median_step) is per joint at the env's dt. In rad: sigma_ours * median_step = sigma_paper * paper_median_step.
PAPER_FRAME_DT = 1 / 30  # s


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
