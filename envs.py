"""The two environments of the paper's experiments (Sec. V; Tables I and II; Fig. 5).

Where the paper is implemented in this file:
    Sec. V, Table I    the planar 3-link reacher ............... PlanarConfig, PlanarReacher
    Sec. V, Table II   the UR5 reaching an engine lever ........ EngineConfig, EngineReach3D
    Sec. V             100 fixed evaluation scenarios .......... eval_seeds (train_seeds: disjoint)
    Sec. V, Fig. 4     the "median step" unit of noise levels .. median_step (the paper's own unit:
                                                                 PAPER_MEDIAN_STEP, paper_median_step)
    Fig. 5             the two scenes .......................... PlanarReacher.render, render_scene_image
The two envs share ArmEnv (state, the motion rule, the episode step, the end effector).

PlanarReacher: the planar 3-link reacher of Sec. V, built on the authors' setup (their code, read for
../shared/PAPER_SETUP.md §1): three box links (0.30 / 0.25 / 0.10 m) and an open gripper move in a
vertical plane among a 5 cm target block and two 7 cm obstacle blocks placed around the shoulder.
From its start the arm must reach the target within 6 cm without touching an obstacle or itself
(contact within 5 mm ends the episode); starts are often folded, so the arm must sometimes
untangle its links first (the paper's description). It runs at 10 Hz (dt = 1/30 gives the authors'
30 Hz) with their 0.5 rad/s joint speed limit and 33 s episodes.

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
    env.clip_action(q, action)                # step's motion rule: the next joint positions
    env.make_obs(q, q_prev)                   # batched observations for the current scenario
    env.make_obs_near(q, q_prev, recorded)    # ... of states drawn near recorded ones (relabel.py)
    env.obs_encoder, env.obs_encoder_args     # how a policy reads the observation ('flat', {}:
                                              # as numbers; diffusion.PolicyConfig.obs_encoder)
    env.plot_policy_view(episode, path)       # a figure of what the policy sees (none here)
    env.in_collision(q, margin=0.0)           # (B,) bool, True = in collision (vectorized numpy);
                                              # margin (m) inflates every pair's contact distance
    env.fk(q)                                 # (B, n_points, dim) joint points, base .. end effector
    env.ee(q)                                 # (B, dim) end effector
    env.ee_jacobian(q)                        # (B, dim, dof) d ee / d q, central differences
    env.goal_reached(q)                       # (B,) bool, True = end effector within tolerance
    env.goal                                  # (dim,) goal of the current scenario
    env.goal_configurations()                 # (M, dof) collision-free closed-form IK of the goal
    env.goal_is_pose                          # True: the goal includes an orientation, and
                                              # goal_configurations is its whole set (the oracle's goals)
    env.render(ax, q=None, alpha=1.0)         # matplotlib drawing of the scene (and arm at q)
    env.draw_noise_ellipses(ax, q, cov, color)   # joint covariances drawn at the end effector
    env.eval_seeds(), env.train_seeds(n, start=0), env.unseen_seeds()
PlanarReacher extras: set_scene(obstacles, goal) installs a hand-built scene; pymunk_in_collision(q)
is the simulator's (slow) version of in_collision.

EngineReach3D: the UR5 reaching an engine lever through a narrow, cluttered passage (Sec. V,
Table II), with pybullet (DIRECT mode) as the simulator and the same vectorized numpy check beside
it, in 3-D. Extras: set_scene(obstacles, goal, kinds), clearance(q) (signed distance),
pybullet_in_collision(q), camera_image(q) (an RGB image from pybullet's TinyRenderer),
render_scene_image(env, path). A research variant whose policy sees that camera image instead of the
obstacle list registers its own env, 'engine3d_image' (experiment/image_obs.py).

Step semantics: q_next = clip(q + clip(action - q, -max_step, max_step), lo, hi).
Targets beyond the joint limits are therefore clipped, not errors; NaN/inf/wrong shape raise
ValueError. An episode ends on success (goal reached, no collision), on collision (terminated),
or after max_steps steps (truncated).

Geometry (PlanarReacher): every body is an oriented box (centre, half extents, angle). The arm's six
boxes (three links, a palm, two fingers) are given in their links' frames by PlanarReacher.parts;
obstacles are one array (N, 5) of (centre x, y, half x, half y, angle). This one definition feeds both
  * the pymunk space (the simulator): kinematic link bodies carrying pymunk.Poly boxes, static
    obstacle boxes, every polygon rounded by half the contact margin, contacts from
    space.shape_query -- used by step();
  * the vectorized numpy check `in_collision` (exact box distances, `box_distance`) -- used by
    planners, relabeling and evaluation, which need millions of checks.
The two agree (tests/test_envs.py): on 12,000 random configurations in 4 scenes, and 1e-7 rad on
either side of contact-boundary points found by bisection. Known exception, of measure zero: a box
centred exactly across a link, for which pymunk reports a contact of depth 0 (counted as contact).

The file reads in that order: the planar env first (its config, the scenario seeds, ArmEnv, PlanarReacher,
make_env, the median step), which is all Table I needs; then, under a banner of its own, the UR5 env of
Table II (EngineConfig, EngineReach3D, its DH frames and closed-form IK, its figure). pybullet is imported
only when the first EngineReach3D is made: `import envs` and the planar env never load it. Beyond the paper
(after the last banner): the vectorized box geometry behind the planar in_collision, episode files
(save_episodes / load_episodes: one .npz, ragged arrays concatenated with offsets) and
straight_line_episode, a stand-in expert for tests and demos.
"""
import math
from dataclasses import dataclass

import numpy as np
import pymunk


# ----------------------------------------------------------------------------------------------
# The planar reacher's configuration (Table I)
# ----------------------------------------------------------------------------------------------
@dataclass
class PlanarConfig:
    # --- the arm: the authors' planar_3joint.urdf (PAPER_SETUP.md §1) ---
    link_lengths: tuple = (0.30, 0.25, 0.10)  # m, joint to joint (shoulder, elbow, wrist link)
    link_widths: tuple = (0.04, 0.035, 0.03)  # m, thickness of each box link
    gripper_reach: float = 0.15  # m, gripper base (end of the wrist link) to the end-effector point
    joint_lo: tuple = (-math.pi, -math.pi, -math.pi)  # rad, the URDF's limits on every joint
    joint_hi: tuple = (math.pi, math.pi, math.pi)  # rad
    # --- the task (PAPER_SETUP.md §1): success, contact, episode length, speed limit ---
    speed_limit: float = 0.5  # rad/s per joint; max_step = speed_limit * dt rad per step
    episode_seconds: float = 1000 / 30  # s (the authors' 1000 steps at 30 Hz); max_steps = it / dt
    goal_tolerance: float = 0.06  # m, success: end effector within this distance of the target centre
    contact_margin: float = 0.005  # m, bodies closer than this are in collision (the authors' 5 mm)
    # --- the scene (PAPER_SETUP.md §1): a target block and two obstacle blocks placed polar
    #     around the shoulder; a scene is re-drawn if blocks overlap, the start collides or the
    #     target cannot be reached collision-free ---
    target_size: float = 0.05  # m, the target cube (touching it is not a collision)
    obstacle_size: float = 0.07  # m, each obstacle cube
    n_obstacles: int = 2  # obstacle blocks per scene
    target_radius: tuple = (0.30, 0.55)  # m, distance of the target centre from the shoulder
    obstacle_radius: tuple = (0.20, 0.62)  # m, distance of each obstacle centre from the shoulder
    # The start: all joints uniform within their limits until the arm is collision-free (the authors' env
    # reset and evaluation config, q_start null; often folded: "the robot must untangle its links"). Their
    # fixed demonstration start gave BC more (62.7 % against 54.0 %) but left DAgger little to fix: measured,
    # not adopted (benchmarks/README.md, "Table I where DAgger has something to fix").

    # --- not in the paper ---
    # The gripper (a Robotiq 2F-85 held open, fixed to the wrist link) as three boxes in the wrist
    # link's frame: a palm and two fingers. The sizes are this project's approximation of its
    # 85 mm-aperture outline (the URDF's meshes are not read here); the end-effector point lies
    # between the finger pads, gripper_reach beyond the gripper base (the authors' tool centre).
    palm_size: tuple = (0.07, 0.09)  # m, (length along the link, width across it)
    finger_size: tuple = (0.08, 0.015)  # m, each finger; the pair spans 0.07 .. 0.15 past the base
    finger_gap: float = 0.075  # m, clear width between the two fingers (fixed open)
    base: tuple = (0.0, 0.0)  # m, the shoulder pivot in the (x, z) plane of the arm
    # Timing. The authors run 30 Hz. We keep their speed limit and their seconds and run 10 Hz by
    # default: a third of the env steps and policy calls on a CPU, the same motion (dt = 1/30 s
    # gives the authors' rate).
    dt: float = 0.1  # s per step
    # States checked for contact within one step (the end state and evenly spaced ones before it).
    # At the speed limit the farthest arm point moves <= 0.05 rad x (0.81 + 0.52 + 0.27) m = 0.08 m
    # a step at 10 Hz, 0.02 m between checks: less than the thinnest band a part must cross to pass
    # through something (a 1.5 cm finger and the 3.5 cm link 2: 5 cm), so nothing tunnels.
    n_substeps: int = 4  # states per step
    block_clearance: float = 0.02  # m, blocks closer than this to each other overlap (re-draw)
    n_goal_angles: int = 180  # last-link orientations tried when searching goal configurations
    # A scene is kept only if at least this many of the 2 n_goal_angles closed-form IK candidates
    # of the target centre are collision-free (the solvability check; see goal_configurations).
    min_goal_configurations: int = 8  # configurations


# ----------------------------------------------------------------------------------------------
# Scenarios: seed ranges (Sec. V: 100 fixed evaluation scenarios, never seen in training)
# ----------------------------------------------------------------------------------------------
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


# Not in the paper: under the authors' protocol HG-DAgger collects on the evaluation scenarios
# (dagger.collect_interventions), so those are not held out. These 100 scenarios are: no stage of
# any run collects, demonstrates or calibrates on them (dagger.py evaluates every policy on them too).
UNSEEN_SEED_START = 20_000
N_UNSEEN_SEEDS = 100


def unseen_seeds():
    """100 scenarios no policy ever trains on: seeds 20_000 .. 20_099 (disjoint from the training and
    evaluation seeds)."""
    return list(range(UNSEEN_SEED_START, UNSEEN_SEED_START + N_UNSEEN_SEEDS))


# ----------------------------------------------------------------------------------------------
# What every arm env shares: state, the motion rule, the episode step, the end effector
# ----------------------------------------------------------------------------------------------
def _as_batch(q, dof, name="q"):
    """(dof,) or (B, dof) finite array -> ((B, dof) float64, was_single)."""
    q = np.asarray(q, dtype=np.float64)
    single = q.ndim == 1
    if single:
        q = q[None]
    if q.ndim != 2 or q.shape[1] != dof:
        raise ValueError(f"{name} must have shape ({dof},) or (B, {dof}), got {np.shape(q)}")
    return q, single


class ArmEnv:
    """The part of the env interface (module docstring) that PlanarReacher and EngineReach3D share.

    A subclass sets dof, dim, max_step, max_steps, goal_tolerance, cfg.n_substeps and calls
    ArmEnv.__init__ with its joint limits, and supplies what differs: fk, in_collision,
    simulator_in_collision (the simulator's contacts that judge a step), make_obs, reset, render.
    """

    def __init__(self, joint_lo, joint_hi):
        self._lo = np.asarray(joint_lo, dtype=np.float64)
        self._hi = np.asarray(joint_hi, dtype=np.float64)
        # scenario state (set by reset)
        self.seed = None
        self._goal = np.zeros(self.dim)
        self._q = np.zeros(self.dof)
        self._q_prev = np.zeros(self.dof)
        self.step_count = 0
        self._has_state = False  # step() needs reset() or set_state() first

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

    @staticmethod
    def eval_seeds():
        """The 100 evaluation seeds (module function eval_seeds)."""
        return eval_seeds()

    @staticmethod
    def train_seeds(n, start=0):
        """n training seeds from start (module function train_seeds)."""
        return train_seeds(n, start)

    @staticmethod
    def unseen_seeds():
        """The 100 scenarios never trained on (module function unseen_seeds)."""
        return unseen_seeds()

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

    # ---- the motion rule and the episode step ------------------------------------------------
    def clip_action(self, q, action):
        """The next joint positions from `action` (absolute targets): speed limit, then limits."""
        return np.clip(q + np.clip(action - q, -self.max_step, self.max_step), self._lo, self._hi)

    def step(self, action):
        """Move toward the absolute joint target `action` (dof,) by at most max_step per joint.

        Collision is judged by the simulator's contacts (simulator_in_collision: pymunk for the
        planar env, pybullet for the 3-D one) at the end state and at n_substeps - 1 evenly spaced
        states before it (see PlanarConfig.n_substeps: nothing tunnels through an obstacle).
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
        collision = bool(any(self.simulator_in_collision(sweep)))
        self._q_prev, self._q = self._q, q_next
        self.step_count += 1
        success = (not collision) and bool(self.goal_reached(q_next))
        terminated = collision or success
        truncated = (not terminated) and self.step_count >= self.max_steps
        info = {"collision": collision, "success": success, "q": self.q, "step": self.step_count}
        return self.make_obs(self._q, self._q_prev), float(success), terminated, truncated, info

    # ---- what a policy reads: the plug-in points of an env variant (experiment/image_obs.py) ---
    # The observation is numbers throughout (the layouts in each env's docstring): a policy reads it flat
    # (diffusion.PolicyConfig.obs_encoder 'flat'). A variant whose observation ends in something else, a camera
    # image, names its encoder (diffusion.OBS_ENCODERS) and the encoder's keyword arguments here.
    obs_encoder = "flat"
    obs_encoder_args = {}  # read only: dagger.make_policy copies it into the policy's config

    def make_obs_near(self, q, q_prev, recorded):
        """Observations of states (q, q_prev) drawn near recorded states whose observations are `recorded`
        (relabel.py's noised states): here make_obs(q, q_prev), everything recomputed at the new state. A variant
        whose observation holds what only a render of the recorded state shows (a camera image) keeps that part
        of `recorded`, the paper's approximation for images (Sec. V)."""
        return self.make_obs(q, q_prev)

    def plot_policy_view(self, episode, path):
        """A figure of what the policy sees along `episode`, where that is more than the numbers of the
        observation (a variant's camera image); none here: returns False (nothing written)."""
        return False

    # ---- the end effector --------------------------------------------------------------------
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

    def square_view(self, axes, points, margin=0.0):
        """Square limits around workspace points (N, 2) in m, plus `margin` m and 10 %, on one axis or a list
        of them (square: the figures' equal aspect then fills the panel)."""
        lo, hi = np.min(points, axis=0), np.max(points, axis=0)
        center, half = (lo + hi) / 2, 1.1 * (0.5 * float(np.max(hi - lo)) + margin)
        for ax in (axes if isinstance(axes, (list, tuple, np.ndarray)) else [axes]):
            ax.set_xlim(center[0] - half, center[0] + half)
            ax.set_ylim(center[1] - half, center[1] + half)

    goal_is_pose = False  # the goal is a position (EngineReach3D: a pose with its orientation rule)

    def goal_reached(self, q):
        """True where the end effector is within goal_tolerance of the goal. (B,) bool."""
        return np.linalg.norm(self.ee(q) - self._goal, axis=-1) <= self.goal_tolerance

    def draw_noise_ellipses(self, ax, q, cov, color, n_std=2.0, alpha=0.3, plane=(0, 1)):
        """n_std ellipses of joint covariances cov (B, dof, dof) at q (B, dof), pushed to the end
        effector to first order, Sigma_ee = J Sigma J^T, and drawn in the given plane of the workspace."""
        from matplotlib.patches import Ellipse
        q = np.atleast_2d(q)
        J = self.ee_jacobian(q)[:, list(plane)]                                # (B, 2, dof)
        cov_ee = J @ np.asarray(cov) @ J.transpose(0, 2, 1)                   # (B, 2, 2)
        for c, S in zip(self.ee(q)[:, list(plane)], cov_ee):
            vals, vecs = np.linalg.eigh(S)
            vals = np.maximum(vals, 0.0)
            angle = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
            ax.add_patch(Ellipse(c, 2 * n_std * math.sqrt(vals[1]), 2 * n_std * math.sqrt(vals[0]), angle=angle,
                                 facecolor=color, edgecolor=color, alpha=alpha, lw=0.7))


# ----------------------------------------------------------------------------------------------
# The planar reacher (Sec. V, Table I)
# ----------------------------------------------------------------------------------------------
class PlanarReacher(ArmEnv):
    """3-link planar arm with a gripper among two box obstacles (paper Sec. V, Table I, Fig. 5).

    Observation layout (float32, obs_dim = 2 dof + 8 = 14; the authors' observation.state and
    observation.environment_state, PAPER_SETUP.md §1):
        [0:3]    q        current joint positions (rad)
        [3:6]    q_prev   joint positions one step earlier (rad)
        [6:8]    target   centre of the target block (x, z) in m
        [8:10]   obstacle 1 centre (x, z) in m
        [10:12]  obstacle 2 centre (x, z) in m
        [12:14]  end effector (x, z) in m: forward kinematics of q, so any state, noised ones
                 included, gets its own (relabel.py relies on this)
    The arm moves in the vertical (x, z) plane of the URDF; arrays call the second axis y.
    """

    dim = 2  # workspace dimension
    # Arm parts: (link, centre along the link from its joint, centre across it, half length, half
    # width) filled in by __init__ from the config; parts 3-5 (palm, fingers) ride on link 2.
    PART_NAMES = ("link1", "link2", "link3", "palm", "finger_left", "finger_right")
    # Self-collision pairs: parts whose links are not joined by a joint. Link 1 vs link 3 and the
    # gripper; link 2 vs the gripper (the gripper is a child of link 3, so link 2 and the palm are
    # not adjacent in the URDF's sense). Adjacent links share a joint and never count.
    SELF_PAIRS = ((0, 2), (0, 3), (0, 4), (0, 5), (1, 3), (1, 4), (1, 5))

    def __init__(self, config: PlanarConfig | None = None):
        self.cfg = cfg = config or PlanarConfig()
        if len(cfg.link_lengths) != 3 or len(cfg.link_widths) != 3:
            raise ValueError(f"PlanarReacher models a 3-link arm, got link_lengths={cfg.link_lengths}, "
                             f"link_widths={cfg.link_widths}")
        if not (cfg.dt > 0 and cfg.speed_limit > 0 and cfg.episode_seconds > 0):
            raise ValueError(f"PlanarConfig needs dt, speed_limit, episode_seconds > 0, got {cfg.dt}, "
                             f"{cfg.speed_limit}, {cfg.episode_seconds}")
        self.dof = 3
        self.link_lengths = np.asarray(cfg.link_lengths, dtype=np.float64)
        self.base = np.asarray(cfg.base, dtype=np.float64)
        self.dt = float(cfg.dt)
        self.max_step = float(cfg.speed_limit * cfg.dt)  # rad per step (0.05 at 10 Hz)
        self.max_steps = int(round(cfg.episode_seconds / cfg.dt))  # 333 at 10 Hz, 1000 at 30 Hz
        self.goal_tolerance = float(cfg.goal_tolerance)
        self.contact_margin = float(cfg.contact_margin)
        # Half the thinnest link's thickness: planners derive their check spacing from it (oracle.py).
        self.link_radius = 0.5 * float(min(cfg.link_widths))
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
        # R_j (dof,): no point of the arm is farther than this from joint j (the links beyond j
        # stretched straight, plus the farthest box corner of each part from its own joint), so a
        # joint step dq moves any point by at most sum_j R_j |dq_j| (oracle.py's check spacing).
        corner = np.hypot(np.abs(self.parts[:, 1]) + self.parts[:, 3], np.abs(self.parts[:, 2]) + self.parts[:, 4])
        link = self.parts[:, 0].astype(int)
        self.lever_arms = np.array([max(self.link_lengths[j:k].sum() + corner[p]
                                        for p, k in enumerate(link) if k >= j) for j in range(3)])
        self.obs_dim = 2 * self.dof + 2 * (2 + cfg.n_obstacles)
        super().__init__(cfg.joint_lo, cfg.joint_hi)
        self.obstacles = np.zeros((0, 5))  # (N, 5): centre x, y, half x, half y, angle
        self.set_scene(np.zeros((0, 5)))

    # ---- kinematics and geometry -------------------------------------------------------------
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

    def in_collision(self, q, margin=0.0):
        """True where configuration q touches an obstacle or itself. (B,) bool.

        A pair of boxes is in contact when their distance is below contact_margin (the authors'
        5 mm) + margin (planners pass margin > 0 to keep clear between their checks). Pairs: every
        arm part with every obstacle, and SELF_PAIRS. The target block is not an obstacle.
        Large batches run in chunks so the temporaries stay in cache.
        """
        q, single = _as_batch(q, self.dof)
        if not np.all(np.isfinite(q)):
            raise ValueError("in_collision: q contains NaN or inf")
        if not (np.isfinite(margin) and margin >= 0):
            raise ValueError(f"in_collision: margin must be a finite distance >= 0 m, got {margin}")
        chunk = 4096  # configurations per pass
        hit = np.concatenate([self._in_collision_chunk(q[i:i + chunk], self.contact_margin + margin)
                              for i in range(0, len(q), chunk)])
        return hit[0] if single else hit

    def _in_collision_chunk(self, q, margin):
        arm = self.part_boxes(q)  # 6 arrays (n_parts, B)
        B = len(q)
        i, j = np.array(self.SELF_PAIRS).T
        pairs_a = [x[i] for x in arm]  # self pairs: (n_pairs, B) each
        pairs_b = [x[j] for x in arm]
        if len(self.obstacles):  # and every part with every obstacle: (n_parts * N, B) each
            n_obs = len(self.obstacles)
            pairs_a = [np.concatenate([pa, np.repeat(x, n_obs, axis=0)]) for pa, x in zip(pairs_a, arm)]
            pairs_b = [np.concatenate([pb, np.broadcast_to(np.tile(g, len(self.parts))[:, None],
                                                           (len(self.parts) * n_obs, B))])
                       for pb, g in zip(pairs_b, self._obstacle_boxes)]
        # broad phase: bounding circles (centre, half diagonal) rule out most pairs cheaply
        cxa, cya, _, _, hxa, hya = pairs_a
        cxb, cyb, _, _, hxb, hyb = pairs_b
        reach = np.hypot(hxa, hya) + np.hypot(hxb, hyb) + margin
        near = (cxa - cxb) ** 2 + (cya - cyb) ** 2 < reach * reach  # (n_pairs, B)
        pair, b = np.nonzero(near)
        # narrow phase: exact box distances of the remaining pairs
        d = box_distance(tuple(x[pair, b] for x in pairs_a), tuple(x[pair, b] for x in pairs_b))
        hit = np.zeros(B, dtype=bool)
        hit[b[d < margin]] = True
        return hit

    def set_scene(self, obstacles, goal=None):
        """Install a scene: obstacles (N, 5) rows (centre x, y, half x, half y, angle), goal (2,).

        reset() calls this with a generated scene; tests and figures may call it with a built one.
        Derives everything both collision checks need from this one array.
        """
        obstacles = np.asarray(obstacles, dtype=np.float64).reshape(-1, 5)
        if not np.all(np.isfinite(obstacles)) or np.any(obstacles[:, 2:4] <= 0):
            raise ValueError("set_scene: obstacles must be finite with half extents > 0")
        if len(obstacles) > self.cfg.n_obstacles:
            raise ValueError(f"set_scene: {len(obstacles)} obstacles, the observation holds at most "
                             f"n_obstacles={self.cfg.n_obstacles}")
        self.obstacles = obstacles
        if goal is not None:
            self._goal = np.asarray(goal, dtype=np.float64).reshape(self.dim).copy()
        cx, cy, hx, hy, angle = obstacles.T
        self._obstacle_boxes = (cx, cy, np.cos(angle), np.sin(angle), hx, hy)
        centres = np.zeros(2 * self.cfg.n_obstacles)  # absent obstacles (hand-built scenes): zeros
        centres[:obstacles[:, :2].size] = obstacles[:, :2].ravel()
        self._scene_obs = np.concatenate([self._goal, centres]).astype(np.float32)
        self._build_space()

    # ---- pymunk mirror (the simulator) -------------------------------------------------------
    def _build_space(self):
        """pymunk space of the current scene: kinematic bodies carrying the arm's box parts,
        static obstacle boxes. Every pymunk polygon is rounded by half the contact margin, so two
        shapes touch in pymunk exactly when their boxes are closer than the margin."""
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
        self._obstacle_shapes = []
        for cx, cy, hx, hy, angle in self.obstacles:
            c, s = math.cos(angle), math.sin(angle)
            corners = [(cx + sx * hx * c - sy * hy * s, cy + sx * hx * s + sy * hy * c)
                       for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
            shape = pymunk.Poly(space.static_body, corners, radius=rounding)
            space.add(shape)
            self._obstacle_shapes.append(shape)
        space.reindex_static()  # compute the static shapes' world geometry once
        self._space = space
        self._pairs_that_count = {frozenset(p) for p in self.SELF_PAIRS}

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
        """True if a part penetrates an obstacle or a non-adjacent part in the posed space."""
        parts = self._part_shapes
        for i, shape in enumerate(parts):
            for hit in self._space.shape_query(shape):
                other = hit.shape
                if other in parts and frozenset((i, parts.index(other))) not in self._pairs_that_count:
                    continue  # the same link or adjacent links: not a collision
                # distance <= 0, not < 0: for a box centred exactly across a link (a tie between
                # two penetration directions) pymunk 7 reports a contact of distance 0.0
                if any(pt.distance <= 0.0 for pt in hit.contact_point_set.points):
                    return True
        return False

    # ---- scenarios ---------------------------------------------------------------------------
    def _draw_scene(self, rng):
        """One candidate scene: (obstacles (N, 5), goal (2,)), or None where blocks overlap.

        The authors' placement (PAPER_SETUP.md §1): the target and each obstacle at an angle uniform
        in [0, 2 pi) around the shoulder, at a distance uniform in target_radius / obstacle_radius.
        The obstacles may or may not block the way: nothing else constrains them.
        """
        cfg = self.cfg

        def polar(radius_range):
            angle, radius = rng.uniform(0.0, 2 * math.pi), rng.uniform(*radius_range)
            return self.base + radius * np.array([math.cos(angle), math.sin(angle)])

        goal = polar(cfg.target_radius)
        centres = np.array([polar(cfg.obstacle_radius) for _ in range(cfg.n_obstacles)])
        half = 0.5 * np.array([cfg.target_size] + [cfg.obstacle_size] * cfg.n_obstacles)
        blocks = np.concatenate([goal[None], centres])  # axis-aligned squares
        for i in range(len(blocks)):
            for j in range(i):
                # axis-aligned squares: the gap is the larger of the per-axis gaps
                gap = np.max(np.abs(blocks[i] - blocks[j]) - half[i] - half[j])
                if gap < cfg.block_clearance:
                    return None
        h = 0.5 * cfg.obstacle_size
        obstacles = np.c_[centres, np.full((cfg.n_obstacles, 2), h), np.zeros(cfg.n_obstacles)]
        return obstacles, goal

    def goal_configurations(self, goal=None, n_angles=None):
        """Collision-free joint configurations whose end effector is exactly at the goal. (M, 3).

        Closed-form IK of the 3-link chain (the last link reaches to the end effector): for each
        orientation phi of the last link the wrist is at goal - l3 (cos phi, sin phi), and the
        2-link IK of the wrist has two elbow solutions. Configurations outside the joint limits or
        in collision are dropped.
        """
        goal = self._goal if goal is None else np.asarray(goal, dtype=np.float64)
        n = n_angles or self.cfg.n_goal_angles
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
        """A necessary condition for a path from start to one of goal_qs: the shoulder can turn there.

        Joint 0 has hard limits at +-pi (no wrap-around), and an obstacle within link 1's reach
        blocks link 1 at some angles whatever the other joints do. The angles where link 1 alone is
        collision-free form intervals; the start's and at least one goal configuration's joint 0
        must lie in the same one. (Measured: this removes the scenes where the arm is walled in
        by its own joint limit, the main kind of unsolvable scene that the other checks keep.)
        """
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

    def reset(self, seed=None):
        """Draw the scenario of `seed` (target, obstacles, start) and put the arm at the start.

        Rejection sampling with one rng stream, so the scenario is a deterministic function of seed.
        A scene is re-drawn when blocks overlap, when its target has fewer than
        min_goal_configurations collision-free IK solutions, or when no start is found: the start
        is the first of 64 uniform draws within the joint limits that is collision-free and not
        already at the target.
        """
        if seed is None:
            seed = int(np.random.default_rng().integers(0, 2 ** 31))  # fresh entropy, recorded
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"reset: seed must be a non-negative int or None, got {seed!r}")
        rng = np.random.default_rng(int(seed))
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
                break
        self.seed = int(seed)
        self.set_state(start)
        return self.make_obs(self._q, self._q_prev), {"q": self.q, "goal": self.goal, "seed": self.seed}

    # ---- observations and the simulator's check used by step ---------------------------
    def make_obs(self, q, q_prev):
        """Observations (B, obs_dim) float32 for the current scenario; (dof,) -> (obs_dim,).

        The end effector is computed from q (forward kinematics)."""
        q, single = _as_batch(q, self.dof, "q")
        q_prev, _ = _as_batch(q_prev, self.dof, "q_prev")
        q_prev = np.broadcast_to(q_prev, q.shape)
        obs = np.empty((len(q), self.obs_dim), dtype=np.float32)
        d = self.dof
        obs[:, :d] = q
        obs[:, d:2 * d] = q_prev
        obs[:, 2 * d:-2] = self._scene_obs  # target, obstacle centres
        obs[:, -2:] = self.ee(q)
        return obs[0] if single else obs

    def simulator_in_collision(self, q):
        """The simulator's contact check used by step: pymunk."""
        return self.pymunk_in_collision(q)

    # ---- drawing -----------------------------------------------------------------------------
    def render(self, ax, q=None, alpha=1.0, color="tab:blue", show_scene=True):
        """Draw obstacles, the target and the arm at q (default: current state; (dof,) or (B, dof)).

        Boxes are drawn as polygons in data units, so sizes are to scale. The dashed circle is the
        success radius around the target. alpha / color style the arm; show_scene=False draws only
        the arm (for paths over a scene).
        """
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
            ax.set_xlim(self.base[0] - reach, self.base[0] + reach)
            ax.set_ylim(self.base[1] - reach, self.base[1] + reach)
            ax.set_aspect("equal")
            ax.set_xlabel("x [m]")
            ax.set_ylabel("z [m]")  # the arm's vertical plane (the URDF's x-z)
        q = self._q if q is None else q
        q = np.atleast_2d(q)
        cx, cy, c, s, hx, hy = self.part_boxes(q)  # (n_parts, B) each
        for b in range(len(q)):
            for p in range(len(self.parts)):
                xs, ys = box_corners(cx[p, b], cy[p, b], c[p, b], s[p, b], hx[p, b], hy[p, b])
                ax.add_patch(Polygon(np.c_[xs, ys], closed=True, color=color, alpha=alpha, lw=0))
            joints = self.fk(q[b])[:-1]
            ax.plot(joints[:, 0], joints[:, 1], "o", color="k", markersize=2, alpha=alpha)
        return ax


# ----------------------------------------------------------------------------------------------
# Environments by name
# ----------------------------------------------------------------------------------------------
# name -> (env class, its config); the UR5 env registers itself after its class ("engine3d"), a research variant
# on import of its module (experiment/image_obs.py: "engine3d_image", a subclass of EngineReach3D)
ENVIRONMENTS = {"planar": (PlanarReacher, PlanarConfig)}
PAPER_ENVS = ("planar", "engine3d")  # the paper's two envs: what is keyed by env (its unit, its table) names these


def make_env(name="planar", **config):
    """Environment by name, e.g. make_env('planar', max_steps=200) (keywords: config fields)."""
    if name not in ENVIRONMENTS:
        raise ValueError(f"make_env: unknown environment {name!r}; valid: {sorted(ENVIRONMENTS)}")
    env_class, config_class = ENVIRONMENTS[name]
    return env_class(config_class(**config))


def paper_env(env):
    """The paper's env (PAPER_ENVS) that env is or derives from -- a variant's env subclasses one, and is that
    env for the paper's unit, table and sizes -- or None. env: a name of ENVIRONMENTS or an env object."""
    env_class = ENVIRONMENTS.get(env, (None,))[0] if isinstance(env, str) else type(env)
    return next((name for name in PAPER_ENVS
                 if env_class is not None and issubclass(env_class, ENVIRONMENTS[name][0])), None)


# ----------------------------------------------------------------------------------------------
# The unit of noise levels (Sec. V, Fig. 4): the median step of the demonstrations
# ----------------------------------------------------------------------------------------------
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


# The paper's own unit, a fact of the authors' demos (PAPER_SETUP.md §1): the median over their
# demonstration steps of the L2 norm over the joints of one 30 Hz step, in rad (PCD
# paper/fig_noise_levels/plot.py: MED_PLANAR = 0.0176, MED_LEVER = 0.0166; the lever's is over the
# UR5's 6 arm joints, as paper/tables_repro/analysis/measure_w_lever.py measures it). Every sigma and W
# of the paper counts it. Ours (median_step above) is per joint at the env's dt: on a planar D0 at
# 10 Hz 0.0245 rad, 1.39x theirs. A per-joint sigma in rad is sigma_ours * median_step = sigma_paper * this.
PAPER_MEDIAN_STEP = {"planar": 0.0176, "engine3d": 0.0166}  # rad, by the paper's env (paper_env)
PAPER_FRAME_DT = 1 / 30  # s: the authors' control period (30 Hz), the frame their velocities count per


def paper_median_step(env):
    """The paper's median step (rad) of env (a name of ENVIRONMENTS or an env object), or None where the
    paper has none (then only radians and our median steps can be given)."""
    return PAPER_MEDIAN_STEP.get(paper_env(env))


# ==== The UR5 engine lever (Table II) =====================================================
# The second environment: the UR5 reaching an engine lever, simulated with pybullet. Table I's planar
# profiles never make it, and pybullet is imported only when they do (`_import_pybullet`).

pb = None  # the pybullet module, once the first EngineReach3D has imported it


def _import_pybullet():
    """pybullet, imported on first use into this module's `pb` (the planar env never needs it)."""
    global pb
    if pb is None:
        import pybullet
        pb = pybullet
    return pb


@dataclass
class EngineConfig:
    # --- the UR5 of Sec. V (radii from the UR5 datasheet's outer diameters: ~0.12 m shoulder and
    #     upper arm housings, ~0.10 m forearm, ~0.09 m wrists) ---
    link_radii: tuple = (0.06, 0.06, 0.05, 0.045, 0.045, 0.045, 0.025, 0.02)  # m, per ENGINE_LINK_NAMES
    # rad. The UR5 allows +-2 pi on every joint; one turn per joint is enough here and keeps the
    # planner from searching equivalent copies of each configuration. Shoulder in [-pi, 0] keeps
    # the upper arm above the shoulder (never into the table); the elbow stops at +-160 deg before
    # the forearm folds onto the upper arm (adjacent capsules, which the checks ignore).
    joint_lo: tuple = (-math.pi, -math.pi, -2.8, -math.pi, -math.pi, -math.pi)
    joint_hi: tuple = (math.pi, 0.0, 2.8, math.pi, math.pi, math.pi)  # rad
    # --- the task: "the robot moves at similar velocities as the 2D planar reacher" (Sec. V) ---
    max_step: float = 0.05  # rad/step, per-joint speed limit (0.5 rad/s at dt = 0.1 s), as planar
    dt: float = 0.1  # s per step (the authors run at 30 Hz; dt = 1/30 gives theirs)
    # m, TCP within this distance of the goal = reached. The authors' success rule: the EE within
    # 3 cm AND 10 deg of one fixed pose (SS sim_robot_pybullet_small_engine.py, TaskConfig); the
    # orientation part is the option below, off by default: with it BC at the table2 recipe reaches 88 %
    # (one end posture), without it 49 %, inside the paper's range (benchmarks/README.md, "The 10° rule").
    goal_tolerance: float = 0.03
    # deg or None. The orientation part of the authors' rule: with a value (theirs: 10), success also
    # needs the flange within this angle of goal_q's orientation, and goal_configurations (the oracle's
    # goal set) becomes the IK branches of goal_q's own pose -- one goal posture, as their demos have.
    # None (the default): position only, and the goal set spans every free tool orientation.
    goal_angle_tolerance: float | None = None
    # Episode step limit: the authors evaluate 1000 frames at 30 Hz (33 s; PCD
    # paper/tables_repro/lib_repro.sh, eval_lever --env.episode_length=1000); the same seconds here.
    max_steps: int = 333  # steps
    # The scene: the authors' small-engine cell (benchmarks/README.md, "The UR5 engine-lever task"): one
    # engine with its lever at a fixed place, a table, a wall behind the robot, two boxes drawn per seed on
    # the table. (This project's earlier generated bay of pipes, where BC stayed near 0 %, was replaced by it.)
    # Start of an episode (_draw_start): all six joints uniform within the joint limits
    # until the arm is clear of everything by start_clearance (theirs: SS splatsim/utils/
    # trajectory_generation.py, _get_random_collision_free_q, used when the config's q_start is null).
    # Starts near a home pose made BC 98 %: measured, not adopted (benchmarks/README.md, "BC at the earlier
    # mid recipe on the authors' cell: the start decided").

    # --- not in the paper ---
    tool_length: float = 0.10  # m, flange to tool centre point (TCP) along z6 (this project's tool)
    finger_half_width: float = 0.045  # m, the fingers are a bar along x6 across the probe's tip;
    #                                   they make joint 6 matter (all else is symmetric about z6)
    # States checked for contact per step (the end state and evenly spaced states before it). At
    # max_step on every joint a point of the arm moves at most 0.05 rad x sum_j R_j = 0.05 x 4.12 m
    # = 0.21 m per step (R_j: the fk chain length beyond joint j, 1.29 .. 0.18 m), i.e. 0.052 m
    # between checks -- less than the thinnest band a centre line must cross to pass through an
    # obstacle, 2 x (fingers 0.02 + lever shaft 0.015) = 0.07 m, so nothing tunnels.
    n_substeps: int = 4  # states per step
    n_max_obstacles: int = 16  # obstacle slots in the observation (absent = zeros); scenes have <= 15
    # --- the scene (EngineReach3D._draw_authors_scene). Their cell in our frame: the UR5's
    #     DH base frame is their URDF base frame turned 180 deg about z, (x, y) -> (-x, -y); the
    #     table top is our ground z = 0 ---
    # rad, the goal posture: the authors' q_goal_bias (the IK seed all their demos converge to); the
    # goal is its TCP, (0.151, -0.373, 0.206) m here, the tool pointing along +x at the engine.
    goal_q: tuple = (1.223, -1.587, 2.082, -0.925, -0.496, -1.124)
    # The small engine, fixed (theirs: randomize_pose=False at (-0.48, 0.36) m, a ~0.34 x 0.38 x
    # 0.34 m splat): a block capsule and a fuel-tank capsule on top, (x0, y0, z0, x1, y1, z1, radius) m.
    engine_parts: tuple = ((0.50, -0.46, 0.15, 0.50, -0.26, 0.15, 0.15),
                           (0.47, -0.45, 0.36, 0.47, -0.28, 0.36, 0.06))
    wall_y: float = 0.225  # m, a wall behind the robot: everything at y >= wall_y is solid (theirs:
    #                        a 3.0 x 0.05 x 1.5 m cuboid at y = -0.225 in their frame)
    # The two boxes on the table, drawn per seed (theirs: box1 x in [0.15, 0.5], y in [0.3, 0.5], turned
    # 90 deg; box2 x in [-0.4, 0.3], y in [0.6, 0.8]; each scaled 0.9-1.1; their sizes are splat
    # scans not in the public code). Each is a capsule lying on the table: centre x, y ranges (m),
    # its axis ('x' or 'y'), length (m) and radius (m, = half its height), scaled by box_scale.
    box_x: tuple = ((-0.50, -0.15), (-0.30, 0.40))  # m
    box_y: tuple = ((-0.50, -0.30), (-0.80, -0.60))  # m
    box_axis: tuple = ("y", "x")  # the two boxes stand at 90 deg to each other
    box_length: tuple = (0.30, 0.30)  # m, centre line (the box's long side minus its height)
    box_radius: tuple = (0.09, 0.09)  # m
    box_scale: tuple = (0.9, 1.1)  # uniform factor on length and radius
    # m, a start keeps this from everything: the authors' planning obstacle clearance
    # (SS configs/traj_configs/upright_robot_small_engine_curtain.json, obstacle_clearance)
    start_clearance: float = 0.02
    lever_offset: float = 0.08  # m, goal (TCP) to the lever handle's axis along the tool axis: the
    #                             probe tip (r 0.025) stops 0.035 m short of the handle (r 0.02)
    min_goal_configurations: int = 40  # a scene is kept only if at least this many of the
    #   goal_configurations candidates are free: a goal reachable from a sliver of joint space is
    #   a needle's eye that no planner (or IK from random seeds) finds reliably
    start_goal_min_dist: float = 0.5  # m, start TCP at least this far from the goal
    n_goal_directions: int = 48  # tool axes tried by goal_configurations (Fibonacci sphere) ...
    n_goal_rolls: int = 4  # ... times rotations of the fingers about it (0, 45, 90, 135 deg)


# ----------------------------------------------------------------------------------------------
# UR5 engine-lever reaching (Sec. V, Table II)
# ----------------------------------------------------------------------------------------------
# UR5 (CB3) standard Denavit-Hartenberg parameters, as published by Universal Robots
# ("DH parameters for calculations of kinematics and dynamics", universal-robots.com, UR5 row).
# Frame i follows frame i-1 by T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i); frame 6 is the flange.
UR5_D = np.array([0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823])  # m, offsets along z_{i-1}
UR5_A = np.array([0.0, -0.425, -0.39225, 0.0, 0.0, 0.0])  # m, lengths along x_i
UR5_ALPHA = np.array([math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0])  # rad, twists

# The arm as 8 capsules (EngineReach3D.link_segments): base column, upper arm, forearm, wrist 1,
# wrist 2, wrist 3 (centre to flange), tool probe (flange to TCP), finger bar.
ENGINE_LINK_NAMES = ("base", "upper_arm", "forearm", "wrist1", "wrist2", "wrist3", "probe", "fingers")
# The fixed camera of figures (and of the image variant's observations, experiment/image_obs.py): in
# front of the robot (the side away from the wall), above the table, looking at the engine and the goal
# (the authors' debug camera looks from the same side, SS sim_robot_pybullet_small_engine.py, PYBULLET_CAMERA_*)
ENGINE_CAMERA = dict(eye=(-0.35, -1.45, 1.0), target=(0.15, -0.3, 0.2), fov=60.0)
_CAPSULE_START = [0, 1, 2, 3, 4, 5, 6, 8]  # rows of EngineReach3D._capsule_points where each
_CAPSULE_END = [1, 2, 3, 4, 5, 6, 7, 9]  # capsule of ENGINE_LINK_NAMES starts / ends
# Self-collision pairs. Capsules that share a joint (consecutive in the chain) always overlap and
# never count. In the wrist, the DH offsets keep some non-consecutive capsules at a FIXED distance,
# whatever the joint angles: forearm-wrist 2 exactly d4 = 0.109 m apart (radii sum 0.095),
# wrist 1-wrist 3 exactly d5 = 0.0947 (0.09), wrist 2-probe d6 = 0.0823 (0.07), wrist 1-probe
# >= d5, wrist 2-fingers >= d6 + tool, wrist 3-fingers >= tool length. They can never touch, and
# with a planner's inflation margin of a few mm they would flag EVERY configuration, so they are
# left out too. The pairs that remain can meet when the arm folds (tests/test_engine3d.py checks
# that the left-out ones stay apart on random configurations):
ENGINE_SELF_PAIRS = np.array([(0, j) for j in range(2, 8)]  # base column vs forearm .. fingers
                             + [(1, j) for j in range(3, 8)]  # upper arm vs wrist 1 .. fingers
                             + [(2, 5), (2, 6), (2, 7), (3, 7)])  # forearm / wrist 1 vs the tool


class EngineReach3D(ArmEnv):
    """UR5 reaching an engine lever through a cluttered, narrow passage (Sec. V, Table II, Fig. 5).

    The paper renders its mockup with Gaussian splats; this project has no scan, so the scene is
    pybullet's own geometry, capsules: the authors' small-engine cell as their code sets it up
    (benchmarks/README.md, "The UR5 engine-lever task"): one engine with its lever at a fixed place,
    the goal the TCP of their goal posture (the witness), a wall behind the robot (a half-space, not
    an obstacle row), the table (the ground), and two boxes lying on the table, drawn per seed.
    Starts: uniform within the joint limits (theirs).

    One geometry definition (capsules: segment + radius, in `self.obstacles` and `link_segments`)
    feeds both
      * pybullet in DIRECT mode (the simulator): one body per arm capsule placed by our own FK,
        static obstacle bodies, a ground plane; contacts from pybullet -- used by step();
      * the vectorized numpy check `in_collision` (segment-segment distances) -- used by the
        planner, relabeling and evaluation.
    They agree on every random configuration tested, and 1e-6 rad on either side of points on the
    contact boundary (tests/test_engine3d.py): capsule-capsule distances are exact in both.

    Observation layout (float32, obs_dim = 2 dof + 3 + 7 n_max_obstacles = 127):
        [0:6]     q       current joint positions (rad)
        [6:12]    q_prev  joint positions one step earlier (rad)
        [12:15]   goal    TCP goal (x, y, z) in m
        [15:127]  obstacles, n_max_obstacles slots of (x0, y0, z0, x1, y1, z1, radius) in m
    The paper's policy sees images instead of the obstacles (Sec. V): that layout is a research variant's
    env, 'engine3d_image' (experiment/image_obs.py), a subclass that replaces [15:] by a camera image.
    """

    dim = 3  # workspace dimension

    def __init__(self, config: EngineConfig | None = None):
        _import_pybullet()  # the simulator, loaded with the first UR5 env
        self.cfg = cfg = config or EngineConfig()
        self.dof = 6
        if cfg.goal_angle_tolerance is not None and not 0.0 < cfg.goal_angle_tolerance <= 180.0:
            raise ValueError(f"EngineConfig.goal_angle_tolerance must be None (position only) or degrees in "
                             f"(0, 180] about the goal posture goal_q (the authors' 10); "
                             f"got {cfg.goal_angle_tolerance!r}")
        self._wall_y = float(cfg.wall_y)  # the wall of the authors' cell: a half-space y >= wall_y
        self.goal_is_pose = cfg.goal_angle_tolerance is not None
        self._goal_frame = ur5_frames(np.asarray(cfg.goal_q, dtype=np.float64)[None])[0, 6]  # (4, 4) flange
        self.link_radii = np.asarray(cfg.link_radii, dtype=np.float64)
        if self.link_radii.shape != (len(ENGINE_LINK_NAMES),) or np.any(self.link_radii <= 0):
            raise ValueError(f"link_radii must be {len(ENGINE_LINK_NAMES)} positive radii "
                             f"({', '.join(ENGINE_LINK_NAMES)}), got {cfg.link_radii}")
        # the thinnest arm capsule: planners derive their edge-check spacing from it (oracle.py)
        self.link_radius = float(self.link_radii.min())
        self.max_step = float(cfg.max_step)
        self.max_steps = int(cfg.max_steps)
        self.dt = float(cfg.dt)
        self.goal_tolerance = float(cfg.goal_tolerance)
        self.obs_dim = 2 * self.dof + self.dim + 7 * cfg.n_max_obstacles
        super().__init__(cfg.joint_lo, cfg.joint_hi)
        self.obstacles = np.zeros((0, 7))  # (N, 7): x0, y0, z0, x1, y1, z1, radius
        self.obstacle_kinds = []  # 'engine' | 'lever' | 'pipe' | 'box', for drawing
        self.witness = None  # (6,) the collision-free goal posture the scene was built around
        self._client = None  # pybullet DIRECT client, created by the first set_scene
        seg = self.link_segments(np.zeros(self.dof))[0]
        self.link_lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)  # (8,) rigid: same at every q
        i, j = ENGINE_SELF_PAIRS.T
        self._self_contact = self.link_radii[i] + self.link_radii[j]  # (P,) radii sums
        self.set_scene(np.zeros((0, 7)))

    # ---- kinematics and geometry -------------------------------------------------------------
    def _capsule_points(self, q):
        """(B, 10, 3): base, shoulder, elbow, wrist 1-3 centres, flange, TCP, the two finger ends.

        The DH chain of ur5_frames written out point by point, 4x faster than the 4x4 products
        (tests check the two agree). Joints 2-4 are parallel (alpha2 = alpha3 = 0), so the shoulder,
        elbow and wrist 1 move in the vertical plane at angle q1, with in-plane angles q2,
        q2 + q3 and q2 + q3 + q4; the lateral axis z1 = (sin q1, -cos q1, 0) carries d4.
        """
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
        # The finger bar crosses the probe just behind the TCP, where its tips are exactly as far
        # from the wrist-3 centre as the TCP is: no point of the arm is farther from joint j than
        # the fk chain beyond joint j is long, the lever-arm bound planners derive from fk.
        reach = UR5_D[5] + self.cfg.tool_length  # wrist-3 centre to TCP
        w = self.cfg.finger_half_width
        centre = p[:, 5] + math.sqrt(reach * reach - w * w) * z6
        p[:, 8], p[:, 9] = centre - w * x6, centre + w * x6
        return p

    def fk(self, q):
        """Joint points (B, 7, 3): base, shoulder, elbow, wrist 1-3, TCP. (dof,) -> (7, 3).

        One point on the axis of each joint (the origins of the UR5's DH frames 0..5; the DH model
        puts the shoulder and elbow offsets of the real arm into d4) plus the tool centre point,
        the end effector. The flange lies on the line from wrist 3 to the TCP.
        """
        q, single = _as_batch(q, self.dof)
        points = self._capsule_points(q)[:, [0, 1, 2, 3, 4, 5, 7]]
        return points[0] if single else points

    def link_segments(self, q):
        """Arm capsules (B, 8, 2, 3): end points in ENGINE_LINK_NAMES order (radii: link_radii)."""
        q, _ = _as_batch(q, self.dof)
        p = self._capsule_points(q)  # (B, 10, 3)
        return np.stack([p[:, _CAPSULE_START], p[:, _CAPSULE_END]], axis=2)

    def clearance(self, q):
        """Signed distance (B,) from the arm at q to everything it may not touch, in m.

        The minimum over: every arm capsule vs every obstacle capsule (segment distance minus the
        two radii), the self-collision pairs ENGINE_SELF_PAIRS, the forearm .. fingers vs the
        ground plane z = 0, and every arm capsule vs the wall y = wall_y.
        Negative = penetration.
        """
        q, single = _as_batch(q, self.dof)
        if not np.all(np.isfinite(q)):
            raise ValueError("clearance/in_collision: q contains NaN or inf")
        # chunks of 256 configurations keep the (chunk, 8, N) temporaries in cache: 2x faster
        d = np.concatenate([self._clearance(q[k:k + 256]) for k in range(0, len(q), 256)])
        return d[0] if single else d

    def _arm_components(self, q):
        """Arm capsule end points, components first: a0, a1 (3, B, 8) (contiguous, for speed)."""
        p = self._capsule_points(q).transpose(2, 0, 1)  # (3, B, 10)
        return np.ascontiguousarray(p[:, :, _CAPSULE_START]), np.ascontiguousarray(p[:, :, _CAPSULE_END])

    def _ground_clearance(self, a0, a1):
        """(B,) lowest point of the forearm .. fingers above the ground plane z = 0.

        The base column stands on the ground, and the upper arm cannot reach it: with the shoulder
        in [-pi, 0] it points upward, its lowest point is always 0.089 - 0.06 m up.
        """
        return (np.minimum(a0[2, :, 2:], a1[2, :, 2:]) - self.link_radii[2:]).min(axis=1)

    def _wall_clearance(self, a0, a1):
        """(B,) distance from the arm's capsules to the wall's face y = wall_y.

        A capsule's distance to a plane is smallest at one of its two end points."""
        return (self._wall_y - np.maximum(a0[1], a1[1]) - self.link_radii).min(axis=1)

    def _clearance(self, q):
        """clearance for a (B, dof) batch: every pair, no broad phase."""
        a0, a1 = self._arm_components(q)
        r, (i, j) = self.link_radii, ENGINE_SELF_PAIRS.T
        d = (segment_distance_3d(a0[:, :, i], a1[:, :, i], a0[:, :, j], a1[:, :, j])
             - r[i] - r[j]).min(axis=1)  # (B,) self-collision pairs
        d = np.minimum(d, self._ground_clearance(a0, a1))
        d = np.minimum(d, self._wall_clearance(a0, a1))
        if len(self.obstacles):
            g = self._geom
            dist = segment_distance_3d(a0[..., None], a1[..., None], g["start"][:, None, None],
                                       g["end"][:, None, None])  # (B, 8, N)
            d = np.minimum(d, (dist - g["contact"]).min(axis=(1, 2)))
        return d

    def in_collision(self, q, margin=0.0):
        """True where the arm at q penetrates an obstacle, the ground or itself. (B,) bool.

        With margin > 0 (m), True also where anything is closer than margin: the inflated check
        planners use to keep clear between their collision checks. The same predicate as
        clearance(q) < margin (a test checks it), computed in two phases for speed:
          broad phase: axis-aligned bounding boxes of every (config, arm capsule, obstacle or
            other arm capsule) pair -- a cheap test that rules out ~98% of the obstacle pairs;
          narrow phase: exact segment-segment distances of the remaining pairs, in one call.
        The base column never moves (joint 1 turns it about its own axis): its clearance is a
        constant of the scene, computed once by set_scene.
        """
        q, single = _as_batch(q, self.dof)
        if not np.all(np.isfinite(q)):
            raise ValueError("in_collision: q contains NaN or inf")
        if not (np.isfinite(margin) and margin >= 0):
            raise ValueError(f"in_collision: margin must be a finite distance >= 0 m, got {margin}")
        chunk = 1024  # configurations per pass: temporaries stay in cache
        hit = np.concatenate([self._in_collision_chunk(q[k:k + chunk], float(margin))
                              for k in range(0, len(q), chunk)])
        return hit[0] if single else hit

    def _in_collision_chunk(self, q, margin):
        a0, a1 = self._arm_components(q)  # (3, B, 8) each
        hit = (self._ground_clearance(a0, a1) < margin) | (self._base_clearance < margin)  # (B,)
        hit |= self._wall_clearance(a0, a1) < margin
        # broad phase: axis-aligned boxes around the capsules, grown by the margin; two capsules
        # whose boxes do not overlap cannot be closer than the margin
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
        # narrow phase on all candidates: segment A = an arm capsule, segment B = obstacle / capsule;
        # arm capsules are picked by flat index config * 8 + capsule from the raveled (3, B * 8)
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
        """Install a scene: obstacles (N, 7) rows (x0, y0, z0, x1, y1, z1, radius), goal (3,).

        reset() calls this with a generated scene; tests and figures may call it with a built one.
        kinds: one of 'engine', 'lever', 'pipe', 'box' per obstacle (colours only; default pipe).
        The wall is not an obstacle row: it belongs to the scene.
        Derives everything both collision checks need from this one array.
        """
        self._set_obstacles(obstacles, kinds)
        if goal is not None:
            goal = np.asarray(goal, dtype=np.float64)
            if goal.shape != (self.dim,) or not np.all(np.isfinite(goal)):
                raise ValueError(f"set_scene: goal must be a finite ({self.dim},) array, got {goal}")
            self._goal = goal.copy()
        self._obstacle_obs = np.zeros(7 * self.cfg.n_max_obstacles, dtype=np.float32)
        self._obstacle_obs[: self.obstacles.size] = self.obstacles.ravel()
        self._build_bullet()

    def _set_obstacles(self, obstacles, kinds=None):
        """Obstacle array and the broad-phase geometry of in_collision (no pybullet rebuild)."""
        obstacles = np.asarray(obstacles, dtype=np.float64).reshape(-1, 7)
        if len(obstacles) > self.cfg.n_max_obstacles:
            raise ValueError(f"set_scene: {len(obstacles)} obstacles, the observation holds at "
                             f"most n_max_obstacles={self.cfg.n_max_obstacles}")
        if not np.all(np.isfinite(obstacles)) or np.any(obstacles[:, 6] <= 0):
            raise ValueError("set_scene: obstacles must be finite with radius > 0")
        kinds = ["pipe"] * len(obstacles) if kinds is None else list(kinds)
        valid = ("engine", "lever", "pipe", "box")
        if len(kinds) != len(obstacles) or any(k not in valid for k in kinds):
            raise ValueError(f"set_scene: kinds must give one of {valid} per obstacle, got {kinds}")
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
        """pybullet DIRECT world of the current scene: arm capsule bodies, obstacles, ground."""
        if self._client is None:
            self._client = pb.connect(pb.DIRECT)
        cid = self._client
        pb.resetSimulation(physicsClientId=cid)
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=cid)
        floor_visual = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[1.5, 1.5, 0.005],
                                            visualFramePosition=[0, 0, -0.005],
                                            rgbaColor=[0.85, 0.85, 0.82, 1], physicsClientId=cid)
        self._ground = pb.createMultiBody(0, plane, floor_visual, physicsClientId=cid)
        # arm: one capsule body per link, placed by our FK. Mass > 0 makes them dynamic bodies,
        # which pybullet tests against the static obstacles (static-static pairs are skipped);
        # we never call stepSimulation, so nothing moves by itself.
        self._link_bodies = []
        for name, length, radius in zip(ENGINE_LINK_NAMES, self.link_lengths, self.link_radii):
            color = [0.2, 0.5, 0.85, 1] if name in ("probe", "fingers") else [0.75, 0.78, 0.82, 1]
            self._link_bodies.append(self._capsule_body(float(length), float(radius), color, mass=1.0))
        checked = {tuple(pair) for pair in ENGINE_SELF_PAIRS.tolist()}
        for i in range(len(self._link_bodies)):  # arm pairs outside ENGINE_SELF_PAIRS: no contacts
            for j in range(i + 1, len(self._link_bodies)):
                if (i, j) not in checked:
                    pb.setCollisionFilterPair(self._link_bodies[i], self._link_bodies[j], -1, -1, 0,
                                              physicsClientId=cid)
        for body in self._link_bodies[:2]:  # base, upper arm never reach the ground (_ground_clearance)
            pb.setCollisionFilterPair(body, self._ground, -1, -1, 0, physicsClientId=cid)
        colors = {"engine": [0.25, 0.25, 0.28, 1],
                  "lever": [0.85, 0.15, 0.1, 1], "pipe": [0.9, 0.55, 0.1, 1], "box": [0.62, 0.45, 0.3, 1]}
        half = [1.5, 0.25, 0.75]  # the wall: a 0.5 m thick slab whose face is the plane y = wall_y
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=cid)
        visual = pb.createVisualShape(pb.GEOM_BOX, halfExtents=half, rgbaColor=[0.87, 0.8, 0.75, 1],
                                      physicsClientId=cid)
        pb.createMultiBody(0, shape, visual, basePosition=[0.0, self._wall_y + half[1], half[2]],
                           physicsClientId=cid)
        for (x0, y0, z0, x1, y1, z1, radius), kind in zip(self.obstacles, self.obstacle_kinds):
            a, b = np.array([x0, y0, z0]), np.array([x1, y1, z1])
            body = self._capsule_body(float(np.linalg.norm(b - a)), float(radius), colors[kind], mass=0.0)
            self._place(body, a, b)
        goal_visual = pb.createVisualShape(pb.GEOM_SPHERE, radius=self.goal_tolerance / 2,
                                           rgbaColor=[0.1, 0.8, 0.2, 1], physicsClientId=cid)
        pb.createMultiBody(0, -1, goal_visual, basePosition=self._goal.tolist(), physicsClientId=cid)

    def _capsule_body(self, length, radius, color, mass):
        cid = self._client
        shape = pb.createCollisionShape(pb.GEOM_CAPSULE, radius=radius, height=length,
                                        physicsClientId=cid)
        visual = pb.createVisualShape(pb.GEOM_CAPSULE, radius=radius, length=length, rgbaColor=color,
                                      physicsClientId=cid)
        return pb.createMultiBody(mass, shape, visual, physicsClientId=cid)

    def _place(self, body, a, b):
        """Put a capsule body (axis = its local z) on the segment a -> b."""
        direction = (b - a) / max(np.linalg.norm(b - a), 1e-12)
        quat = _quaternion_z_to(direction[None])[0]
        pb.resetBasePositionAndOrientation(body, ((a + b) / 2).tolist(), quat.tolist(),
                                           physicsClientId=self._client)

    def _pose_arm(self, q):
        """Place the arm's capsule bodies at configuration q (dof,)."""
        seg = self.link_segments(q)[0]  # (8, 2, 3)
        centres = seg.mean(axis=1)
        directions = seg[:, 1] - seg[:, 0]
        quats = _quaternion_z_to(directions / np.linalg.norm(directions, axis=1, keepdims=True))
        for body, c, quat in zip(self._link_bodies, centres, quats):
            pb.resetBasePositionAndOrientation(body, c.tolist(), quat.tolist(),
                                               physicsClientId=self._client)

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
    def goal_configurations(self, goal=None, n_directions=None, n_rolls=None):
        """Collision-free joint configurations that reach the goal. (M, 6).

        Position-only success (goal_angle_tolerance None): every tool orientation
        (tcp_goal_configurations); with the orientation rule: goal_q's own pose and that pose tilted
        by half the tolerance about +-x, y, z of the flange (goal_pose_configurations).
        """
        if not self.goal_is_pose:
            return self.tcp_goal_configurations(goal, n_directions, n_rolls)
        return self.goal_pose_configurations()

    def goal_pose_configurations(self):
        """The closed-form IK branches of goal_q's flange pose and of 6 tilts of it by half the angle
        tolerance, TCP on the goal; within the limits, collision-free and goal_reached. (M, 6)."""
        frame = self._goal_frame
        tilt = math.radians(self.cfg.goal_angle_tolerance) / 2
        turns = [np.eye(3)] + [axis_rotation(a, tilt) for a in np.vstack([np.eye(3), -np.eye(3)])]
        flange = np.tile(np.eye(4), (len(turns), 1, 1))
        flange[:, :3, :3] = frame[:3, :3] @ np.array(turns)
        flange[:, :3, 3] = self._goal - self.cfg.tool_length * flange[:, :3, 2]  # TCP on the goal
        q = ur5_ik(flange).reshape(-1, self.dof)
        q = q[~np.isnan(q).any(axis=1)]
        q = q[np.all((q >= self._lo) & (q <= self._hi), axis=1)]
        q = q[~self.in_collision(q)] if len(q) else q
        return q[self.goal_reached(q)] if len(q) else q

    def tool_angle(self, q):
        """Degrees between the flange's orientation at q and at the goal posture goal_q. (B,) or float."""
        q = np.asarray(q, dtype=np.float64)
        R = ur5_frames(q.reshape(-1, self.dof))[:, 6, :3, :3]
        cos = (np.einsum("bij,ij->b", R, self._goal_frame[:3, :3]) - 1) / 2  # (trace(R^T R_goal) - 1) / 2
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        return angle.reshape(q.shape[:-1]) if q.ndim > 1 else float(angle[0])

    def goal_reached(self, q):
        """True where the TCP is within goal_tolerance of the goal and, with goal_angle_tolerance, the
        flange within that angle of the goal posture's orientation (the authors' 3 cm and 10 deg). (B,)"""
        near = super().goal_reached(q)
        if not self.goal_is_pose:
            return near
        return near & (self.tool_angle(q) <= self.cfg.goal_angle_tolerance)

    def tcp_goal_configurations(self, goal=None, n_directions=None, n_rolls=None):
        """Collision-free joint configurations with the TCP exactly at the goal. (M, 6).

        Closed-form IK (ur5_ik) for a fixed set of tool orientations: n_directions tool axes z6
        spread over the sphere, each with n_rolls rotations of the fingers about it, and up to 8
        arm branches per orientation. Solutions outside the joint limits or in collision are dropped.
        """
        goal = self._goal if goal is None else np.asarray(goal, dtype=np.float64)
        n_dir = n_directions or self.cfg.n_goal_directions
        n_roll = n_rolls or self.cfg.n_goal_rolls
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
        """One candidate scene of the authors' cell: (obstacles (N, 7), kinds, goal (3,), witness (6,)).

        Fixed: the engine (cfg.engine_parts), the goal posture cfg.goal_q and its TCP (the goal),
        a T-handle lever just beyond the TCP along the tool axis with its shaft running on into
        the engine, and the wall (not a row: EngineReach3D._wall_y).
        Drawn: the two boxes, each a capsule lying on the table, centre uniform in its box_x x box_y
        range, length and radius scaled by one factor from box_scale. The scene is re-drawn by reset
        if the goal posture collides.
        """
        cfg = self.cfg
        q_goal = np.asarray(cfg.goal_q, dtype=np.float64)
        frame6 = ur5_frames(q_goal[None])[0, 6]
        tool_axis, handle_axis = frame6[:3, 2], frame6[:3, 1]
        goal = self.ee(q_goal)
        obstacles, kinds = [], []
        for part in cfg.engine_parts:
            obstacles.append(list(part))
            kinds.append("engine")
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

    def reset(self, seed=None):
        """Draw the scenario of `seed` (the scene, then the start) and put the arm there.

        Rejection sampling with one rng stream, so the scene is a deterministic function of seed.
        The goal always has a collision-free configuration (the witness posture the scene is built
        around); scenes whose witness collides, or whose goal has fewer than
        min_goal_configurations free IK solutions, are re-drawn. Starts: see _draw_start.
        """
        if seed is None:
            seed = int(np.random.default_rng().integers(0, 2 ** 31))  # fresh entropy, recorded
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"reset: seed must be a non-negative int or None, got {seed!r}")
        rng = np.random.default_rng(int(seed))
        cfg = self.cfg
        while True:
            obstacles, kinds, goal, self.witness = self._draw_authors_scene(rng)
            self._set_obstacles(obstacles, kinds)
            self._goal = goal
            if self.in_collision(self.witness):
                continue
            if len(self.tcp_goal_configurations()) < cfg.min_goal_configurations:  # either success rule:
                continue  # the same scenes
            start = self._draw_start(rng)
            if start is not None:
                break
        self.seed = int(seed)
        self.set_scene(self.obstacles, self._goal, self.obstacle_kinds)
        self.set_state(start)
        return self.make_obs(self._q, self._q_prev), {"q": self.q, "goal": self.goal, "seed": self.seed}

    def _draw_start(self, rng, n=256):
        """A start: (6,) or None if none of n draws is acceptable.

        The authors': all joints uniform within the joint limits. The first draw that is clear of
        everything by start_clearance with its TCP at least start_goal_min_dist from the goal is taken.
        """
        cfg = self.cfg
        q = rng.uniform(self._lo, self._hi, size=(n, self.dof))
        far = np.linalg.norm(self.ee(q) - self._goal, axis=1) >= cfg.start_goal_min_dist
        ok = far & ~self.in_collision(q, margin=cfg.start_clearance)
        return q[np.argmax(ok)] if ok.any() else None

    # ---- observations, stepping --------------------------------------------------------------
    def make_obs(self, q, q_prev):
        """Observations (B, obs_dim) float32 for the current scenario; (dof,) -> (obs_dim,)."""
        obs, _, single = self._joint_goal_obs(q, q_prev)
        obs[:, 2 * self.dof + self.dim:] = self._obstacle_obs
        return obs[0] if single else obs

    def _joint_goal_obs(self, q, q_prev):
        """make_obs's first part: (obs (B, obs_dim) float32 with q, q_prev and the goal in [0:15], the rest
        for the caller to fill; q (B, dof) float64; single: q was (dof,))."""
        q, single = _as_batch(q, self.dof, "q")
        q_prev, _ = _as_batch(q_prev, self.dof, "q_prev")
        obs = np.empty((len(q), self.obs_dim), dtype=np.float32)
        d = self.dof
        obs[:, :d] = q
        obs[:, d:2 * d] = np.broadcast_to(q_prev, q.shape)
        obs[:, 2 * d:2 * d + self.dim] = self._goal
        return obs, q, single

    def simulator_in_collision(self, q):
        """The simulator's contact check used by step: pybullet."""
        return self.pybullet_in_collision(q)

    # ---- images and drawing ------------------------------------------------------------------
    def camera_image(self, q=None, width=640, height=480):
        """RGB image (height, width, 3) uint8 of the scene with the arm at q (default: current).

        pybullet's software renderer (ER_TINY_RENDERER: no display or GPU needed) from the fixed
        camera ENGINE_CAMERA, in front of the robot, looking at the engine.
        """
        q = self._check_q(self._q if q is None else q, "q")
        self._pose_arm(q)
        cam = ENGINE_CAMERA
        view = pb.computeViewMatrix(list(cam["eye"]), list(cam["target"]), [0, 0, 1])
        projection = pb.computeProjectionMatrixFOV(cam["fov"], width / height, 0.05, 5.0)
        _, _, rgba, _, _ = pb.getCameraImage(width, height, view, projection,
                                             renderer=pb.ER_TINY_RENDERER,
                                             lightDirection=[0.6, -0.5, 1.0], shadow=0,
                                             physicsClientId=self._client)
        return np.reshape(np.asarray(rgba, dtype=np.uint8), (height, width, 4))[..., :3]

    def render(self, ax, q=None, alpha=1.0, color="tab:blue", show_scene=True):
        """Draw the scene and the arm at q (default: current state; (dof,) or (B, dof)).

        On a 3-D axis (projection='3d') capsules are drawn as thick lines; on a 2-D axis the
        pybullet camera image of the scene (arm at the first q) is shown with imshow.
        """
        q = self._q if q is None else np.asarray(q, dtype=np.float64)
        if not hasattr(ax, "get_zlim"):
            ax.imshow(self.camera_image(np.atleast_2d(q)[0], 480, 360))
            ax.set_axis_off()
            return ax
        widths = {"engine": 14, "lever": 2, "pipe": 4, "box": 10}
        colors = {"engine": "0.2", "lever": "tab:red", "pipe": "tab:orange", "box": "tab:brown"}
        if show_scene:
            for (x0, y0, z0, x1, y1, z1, _), kind in zip(self.obstacles, self.obstacle_kinds):
                ax.plot([x0, x1], [y0, y1], [z0, z1], color=colors[kind], linewidth=widths[kind])
            ax.scatter(*self._goal, color="tab:green", s=40)
            x, z = [-0.7, 0.7, 0.7, -0.7, -0.7], [0, 0, 1.0, 1.0, 0]  # the wall's outline
            ax.plot(x, [self._wall_y] * 5, z, color="0.6")
            ax.set_xlim(-0.7, 0.6)  # the cell lies toward +x (the engine) and -y (the boxes)
            ax.set_ylim(-1.0, 0.3)
            ax.set_zlim(0.0, 1.0)
            ax.set_box_aspect((1.3, 1.3, 1.0))
        for seg in self.link_segments(np.atleast_2d(q)):
            for (a, b), radius in zip(seg, self.link_radii):
                ax.plot(*np.stack([a, b], axis=1), color=color, alpha=alpha,
                        linewidth=max(1.0, 60 * radius), solid_capstyle="round")
        return ax

    def close(self):
        """Disconnect the pybullet client (reset() connects a new one)."""
        if self._client is not None:
            pb.disconnect(physicsClientId=self._client)
            self._client = None
            self._has_state = False

    def __del__(self):  # free the pybullet client when the env is garbage-collected
        try:
            self.close()
        except Exception:  # interpreter shutdown: pybullet may already be gone
            pass


ENVIRONMENTS["engine3d"] = (EngineReach3D, EngineConfig)


# ----------------------------------------------------------------------------------------------
# Figures (Fig. 5): the scenes
# ----------------------------------------------------------------------------------------------
def render_scene_image(env, path, q=None, width=640, height=480):
    """Save env.camera_image (the scene, arm at q) to path (.png) for figures; returns the image."""
    from matplotlib.image import imsave

    image = env.camera_image(q, width, height)
    imsave(path, image)
    return image


# ----------------------------------------------------------------------------------------------
# Capsule geometry and UR5 kinematics (EngineReach3D)
# ----------------------------------------------------------------------------------------------
def segment_distance_3d(a0, a1, b0, b1):
    """Distance between segments [a0, a1] and [b0, b1], broadcasting; COMPONENTS FIRST: (3, ...).

    Closest points of two segments (Ericson, Real-Time Collision Detection, Sec. 5.1.9): the
    closest points of the infinite lines, clamped to the segments, re-projected once. A zero-length
    segment (a sphere) goes through the same formulas with its squared length floored at 1e-18.
    Coordinates come as separate x, y, z arrays (first axis) because every operation below then
    runs on contiguous memory: 4-5x faster than reducing a trailing axis of size 3.
    """
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


def axis_rotation(axis, angle):
    """The 3 x 3 rotation by `angle` rad about the unit vector `axis` (Rodrigues' formula)."""
    x, y, z = axis
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


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


# ==== Beyond the paper (safe to skip) ====================================================
# The vectorized numpy geometry behind the planar in_collision (the simulator's contact checks, fast
# enough for the millions of checks of planning and relabeling), episode files and a stand-in expert for
# tests and demos.

# ----------------------------------------------------------------------------------------------
# Vectorized box geometry (numpy). Every body is an oriented box: centre (x, y), half extents
# (hx, hy) along its own axes, and angle. Arrays broadcast over any leading shape.
# ----------------------------------------------------------------------------------------------
def point_box_distance(px, py, cx, cy, cos, sin, hx, hy):
    """Distance from point p to the box (0 inside): in the box's frame, |max(|p_local| - h, 0)|."""
    dx, dy = px - cx, py - cy
    lx = np.maximum(np.abs(dx * cos + dy * sin) - hx, 0.0)  # local x = p . u
    ly = np.maximum(np.abs(-dx * sin + dy * cos) - hy, 0.0)  # local y = p . n
    return np.sqrt(lx * lx + ly * ly)


def box_corners(cx, cy, cos, sin, hx, hy):
    """The four corners of each box: (xs, ys), each a list of 4 arrays shaped like cx."""
    xs, ys = [], []
    for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        xs.append(cx + sx * hx * cos - sy * hy * sin)
        ys.append(cy + sx * hx * sin + sy * hy * cos)
    return xs, ys


def box_distance(a, b):
    """Distance between boxes a and b (0 if they overlap). a, b: tuples (cx, cy, cos, sin, hx, hy).

    Two facts of 2-D convex geometry make this short and exact:
      * overlap <=> no separating axis among the four edge normals (the separating axis theorem);
      * two disjoint convex polygons are closest at a vertex of one of them, so the distance is the
        smallest of the 8 corner-to-box distances.
    """
    acx, acy, ac, as_, ahx, ahy = a
    bcx, bcy, bc, bs, bhx, bhy = b
    dx, dy = bcx - acx, bcy - acy
    overlap = np.ones(np.broadcast(acx, bcx).shape, dtype=bool)
    for ex, ey in ((ac, as_), (-as_, ac), (bc, bs), (-bs, bc)):  # the 4 axes: u_a, n_a, u_b, n_b
        ra = ahx * np.abs(ac * ex + as_ * ey) + ahy * np.abs(-as_ * ex + ac * ey)  # a's half shadow
        rb = bhx * np.abs(bc * ex + bs * ey) + bhy * np.abs(-bs * ex + bc * ey)
        overlap &= np.abs(dx * ex + dy * ey) <= ra + rb
    d = np.full(overlap.shape, np.inf)
    for (xs, ys), box in ((box_corners(*a), b), (box_corners(*b), a)):
        for x, y in zip(xs, ys):
            d = np.minimum(d, point_box_distance(x, y, *box))
    return np.where(overlap, 0.0, d)


# ----------------------------------------------------------------------------------------------
# Episode files and a stand-in expert
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


def straight_line_episode(env, seed, peak=0.04, expert_from=5):
    """Stand-in expert data for module demos, tests and benchmarks (no oracle needed).

    In scenario `seed` the arm moves in a straight joint-space line from its start toward the goal
    configuration nearest to it, stopped at 90 % of the way to the first contact, timed with a
    smoothstep (rest to rest, peak speed `peak` rad/step). Steps from `expert_from` on are marked
    as expert-driven (an "intervention" that runs to the end of the episode).
    """
    env.reset(seed=int(seed))
    q0 = env.q
    goals = env.goal_configurations()
    target = goals[np.argmin(np.abs(goals - q0).sum(1))]
    f = np.linspace(0, 1, 401)
    hit = env.in_collision(q0 + f[:, None] * (target - q0))
    d = (0.9 * f[np.argmax(hit)] if hit.any() else 1.0) * (target - q0)
    tau = np.linspace(0, 1, int(np.ceil(1.5 * np.abs(d).max() / peak)) + 1)
    q = q0 + (3 * tau ** 2 - 2 * tau ** 3)[:, None] * d  # (T, dof), smoothstep
    prev = np.concatenate([q[:1], q[:-1]])
    return {"obs": env.make_obs(q, prev), "q": q, "action": np.concatenate([q[1:], q[-1:]]),
            "expert": np.arange(len(q)) >= expert_from, "seed": int(seed)}


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
