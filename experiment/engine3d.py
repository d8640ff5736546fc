"""Table II's environment: the UR5 reaching an engine lever through a cluttered passage (Sec. V, Table II, Fig. 5),
pybullet's contacts beside a vectorized capsule check, and the UR5's kinematics. `python dagger.py --profile
table2` runs it; Table I's path (the default run) never does.

    EngineConfig, EngineReach3D ........ the env (envs.ArmEnv's interface: envs.py's docstring)
    ur5_frames, ur5_ik ................. the UR5's forward kinematics (Denavit-Hartenberg) and closed-form IK
    segment_distance_3d ................ the capsule check's geometry
    render_scene_image ................. Fig. 5's UR5 scene

The harness makes it by name (experiment/environments.py, 'engine3d') and hands that factory to the loop.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from envs import ArmEnv, as_batch

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
    paper_env, paper_median_step = "engine3d", 0.0166  # Table II; rad, the authors' median step (SETUP.md §1)
    max_parallel = 100  # each env holds a pybullet client: 300 at once would take ~9 GB
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
        q, single = as_batch(q, self.dof)
        points = self._capsule_points(q)[:, [0, 1, 2, 3, 4, 5, 7]]
        return points[0] if single else points

    def link_segments(self, q):
        """Arm capsules (B, 8, 2, 3): end points in ENGINE_LINK_NAMES order (radii: link_radii)."""
        q, _ = as_batch(q, self.dof)
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
        q, single = as_batch(q, self.dof)
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


# ---- Fig. 5: the UR5's scene (the planar one: PlanarReacher.render, oracle.py) -------------------
def render_scene_image(env, path, q=None, width=640, height=480):
    """Save env.camera_image (the scene, arm at q) to path (.png) for figures; returns the image."""
    from matplotlib.image import imsave
    image = env.camera_image(q, width, height)
    imsave(path, image)
    return image


