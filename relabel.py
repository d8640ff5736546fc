"""Corrective labels around expert interventions: paper Sec. IV-E ("Generating Corrective Labels"),
the augmented data D̂_k of Sec. IV-A steps 3-4. Top to bottom:
  demo_stats           Sec. IV-E: "the demonstration dataset's velocity and acceleration statistics";
                       the median step m (Sec. V) is the unit of every noise level
  perturb_states       Sec. IV-A step 3: q̃ ~ N(q_t, Σ) around the intervention states, Σ (`noise_factors`)
                       'isotropic' (σ m)² I (Table I's fixed-noise rows), 'pooled' Σ̄^α (Eqs. (15)-(16)) or
                       'per_step' Σ^α_t (Eq. (14)), both measured by calibrate.py
  monotone_projection  Sec. IV-E: "a monotone closest-point projection"                     (exercise 8)
  pd_return_chunk      Sec. IV-E: "a critically-damped PD controller, with accelerations clamped" (exercise 9)
  corrective_labels    projection -> return chunk for a batch of noised states; the default label is
                       the authors' servo (`servo_return_chunk`, beyond the banner, PAPER_SETUP.md §6)
  AugmentationSampler  Sec. IV-A steps 3-4: (observation, chunk, mask) triples made on the fly for
                       co-training (diffusion.train's `sampler` hook)
  plot_recovery        Fig. 1
Beyond the banner: the authors' servo, the measured-worse 'gap' lookahead, Fig. 1's axes and legend, the
sampler's table, draws, redraws, observations, pool and resume, `covariance_factor`, input checks.

Units: per control step: joints in rad, velocities rad/step, accelerations rad/step² (the env's
`max_step` is directly the velocity clamp, no dt appears); noise levels and most RelabelConfig knobs in
median steps m (the median per-step joint displacement of the demos), except velocity_noise: the
authors' number in their own median step per 30 Hz frame, converted by `velocity_noise_std` with the
env's units in DemoStats. The small Gaussian observation noise of Sec. V (last paragraph) is not
here: it is diffusion.TrainConfig.obs_noise, for every batch.

The env is passed in and used only through the env interface of envs.py: env.dof, env.joint_limits,
env.max_step, env.in_collision, env.make_obs_near, env.reset(seed=...), env.set_state, and for the figure
env.ee, env.ee_jacobian, env.draw_noise_ellipses, env.render. Which steps teach is the label rule in
diffusion.label_mask. Imports: numpy and that rule (matplotlib inside `plot_recovery`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from diffusion import chunk_dataset, expert_runs, label_mask  # the paper's label rule, one place


@dataclass
class RelabelConfig:
    # the paper (Sec. IV-E)
    horizon: int = 16  # steps: H, the length of a label chunk (the policy's action chunk)
    settle_steps: float = 8.0  # steps: the PD's unclamped error settles to 2 % in this many (H/2), label='pd'
    # not in the paper: the authors' label (their code, PAPER_SETUP.md §6), their 30 Hz frames converted to
    #   our 10 Hz steps; m = our median step, m' = theirs per frame. The servo's floors below take m' = m/3
    #   (the same joint speed, a third of our step per frame); it is not: their median step m' is 0.0176 rad
    #   (envs.PAPER_MEDIAN_STEP, L2 over the joints), while m/3 = 0.0079 rad on mid's D0 (m = 0.0237 rad), so
    #   m' ~2.2x m/3 (benchmarks/README.md, "The relabel servo's floors in the authors' unit")
    label: str = "servo"  # 'servo': `servo_return_chunk` (the authors'); 'pd': `pd_return_chunk` (the text's)
    velocity_noise: float = 0.3  # the paper's median steps per 30 Hz frame (theirs): std of a noised state's
    #   per-joint velocity noise, converted to rad per env step by `velocity_noise_std` (0.0158 rad/step planar)
    a_clamp_scale: float = 0.9  # unit-free: a_clamp = 0.9 · max(2√dof · acc_p95, accel_floor · m)
    # (accel_floor, gain_floor and speed_cap converted through the paper's m' instead -- 1.34, 2.97, 3.74 of our
    #  median steps on mid's D0 -- were probed on mid's round 1: fixed sigma = 8 -0.7, pooled -2.0 points over
    #  3 lineages, p >= 0.39, no gain; the m' = m/3 values below stay the defaults)
    accel_floor: float = 0.6  # median steps/step²: theirs 0.2 m'/frame², taken as 0.2 · (m/3) / (1/3 step)²
    gain_floor: float = 4.0 / 3.0  # median steps: Kp = a_clamp / max(d0, gain_floor · m); theirs 4 m', taken as 4/3 m
    jerk_slew: float = 1.5  # unit-free: |a_k - a_{k-1}| <= 1.5 a_clamp per step (theirs 0.5 per frame, 3 frames)
    speed_cap: float = 1.68  # median steps/step: |v| <= max(1.68 m, speed_cap_v0 · |v0|) (theirs 1.4 · 1.2 m'/frame,
    #   taken as 1.68 (m/3) per frame = 1.68 m per step)
    speed_cap_v0: float = 1.05  # unit-free: the 1.05 · |v0| part
    cursor_advance: int = 3  # steps (trajectory indices) per step: theirs 3 m' of arc per frame, 3 m per step if
    #   m' = m/3 (not probed through the paper's m')
    hold_tol: float = 0.02  # median steps/step: slower chunk steps at the segment end are "held" (out of the loss)
    min_moving_steps: int = 3  # steps: fewer unmasked steps and the state is redrawn (theirs 8 frames = 2.7 steps)
    near_end_steps: int = 3  # steps: a state projecting this near its segment's end is redrawn (theirs 8 frames)
    max_redraws: int = 6  # redraws (theirs 6), then the state is dropped
    pad_short: bool = False  # interventions shorter than H noised too (diffusion.expert_runs pad=True; their lever
    #   runs' teleop_pad_short_episodes): states are drawn at every intervention step, the labels end with the run
    # not in the paper: ours
    projection_window: int = 32  # steps: how far past t the projection looks, so a path that later passes
    #   near the same configuration cannot pull it far ahead (2H steps of path >> Table I's 16 median steps)
    lookahead: str = "time_matched"  # label='pd' target: trajectory[t_proj + k]; 'gap' (beyond the banner) is worse
    max_lookahead: int = 8  # steps: cap on the 'gap' lookahead (H/2)
    max_tries: int = 10  # draws: rejection rounds for a noised state in collision / off limits, then dropped
    pool_size: int = 4096  # pairs: AugmentationSampler's pool
    refresh_size: int = 512  # pairs: made per refresh, replacing the oldest
    reuse: float = 4.0  # unit-free: times a pair is served on average, for ~1 ms a call (bench_relabel.py)
    episodes_per_refresh: int = 16  # episodes: a refresh draws from this many, so env calls are batched


# ---- 1. Demonstration statistics (Sec. IV-E: "the demonstration dataset's velocity and acceleration statistics")

@dataclass(frozen=True)
class DemoStats:
    median_step: float  # rad: m, the median per-step joint displacement (envs.median_step); noise unit
    median_speed: float  # rad/step: median over moving steps of ‖q[t+1] - q[t]‖₂ ('gap' lookahead only)
    accel_max: np.ndarray  # (dof,) rad/step²: per-joint clamp on the PD's acceleration
    max_step: np.ndarray  # (dof,) rad/step: the env's speed limit, clamp on the velocity
    acc_p95: float  # rad/step²: 95th percentile of ‖q[t+1] - 2 q[t] + q[t-1]‖₂, sets the servo's a_clamp
    # the env's units, for knobs the authors set in their own (`velocity_noise_std`); None: not known
    paper_median_step: float | None = None  # rad: the paper's median step of the env (envs.paper_median_step)
    frames_per_step: float | None = None  # the authors' 30 Hz frames per env step: env.dt / envs.PAPER_FRAME_DT


def demo_stats(episodes: Sequence[dict], median_step: float, max_step, accel_percentile: float = 99.0,
               paper_median_step: float | None = None, frames_per_step: float | None = None) -> DemoStats:
    """Statistics of the base demonstrations D0 that shape the corrective labels.

    `median_step` is `envs.median_step(episodes)`; `max_step` the env's per-step joint speed limit
    (scalar or (dof,)); `paper_median_step` (envs.paper_median_step) and `frames_per_step` (env.dt /
    envs.PAPER_FRAME_DT, 3 at 10 Hz) convert the knobs the authors set in their unit (`velocity_noise_std`).
    The acceleration clamp is the `accel_percentile` of |q[t+1] - 2 q[t] + q[t-1]| per joint: a high
    percentile rather than the max, so one odd step does not set every label's clamp.
    """
    _check_demo_inputs(median_step, accel_percentile)
    steps, accels = [], []
    for ep in episodes:
        q = np.asarray(ep["q"], dtype=np.float64)  # (T, dof)
        if len(q) >= 2:
            steps.append(np.diff(q, axis=0))
        if len(q) >= 3:
            accels.append(np.abs(q[2:] - 2 * q[1:-1] + q[:-2]))  # second differences, rad/step²
    _check_demo_motion(steps, accels)  # an episode of >= 3 steps, and some motion
    speed = np.linalg.norm(np.concatenate(steps), axis=1)
    speed = speed[speed > 0]  # standing still is not a speed
    accels = np.concatenate(accels)  # (sum T-2, dof)
    accel_max = np.percentile(accels, accel_percentile, axis=0)  # (dof,)
    acc_p95 = float(np.percentile(np.linalg.norm(accels, axis=1), 95))  # the authors': norm over joints
    max_step = _check_clamps(accel_max, max_step)  # (dof,) rad/step
    return DemoStats(float(median_step), float(np.median(speed)), accel_max, max_step, acc_p95,
                     None if paper_median_step is None else float(paper_median_step),
                     None if frames_per_step is None else float(frames_per_step))


# ---- 2. Noised states around the intervention data (Sec. IV-A step 3; Σ^α from calibrate.py)

def label_steps(expert: np.ndarray, horizon: int, pad: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Steps t whose chunk is a valid label (diffusion.label_mask, the paper's label rule; pad: every run's
    every step), and seg_end (N,): the end (exclusive) of the expert run containing t -- the part of the
    trajectory labels may follow."""
    expert = np.asarray(expert, dtype=bool)
    seg_end = np.zeros(len(expert), dtype=np.int64)
    for start, end in expert_runs(expert, horizon, pad):
        seg_end[start:end] = end
    t = np.flatnonzero(label_mask(expert, horizon, pad))
    return t, seg_end[t]


def noise_factors(sigma, steps: np.ndarray, dof: int, median_step: float | None = None, n_steps: int | None = None) -> np.ndarray:
    """Noise factors L_t (len(steps), dof, dof), L Lᵀ = Σ_t (`covariance_factor`), for the timesteps
    `steps` of one episode.

    The three noise models, told apart by the form of `sigma`:
      - isotropic: a scalar σ >= 0 in median steps -> Σ = (σ · median_step)² I  (needs median_step, rad)
      - pooled:    an array (dof, dof), rad²       -> Σ̄^α at every step                (Eqs. (15)-(16))
      - per_step:  a pair (timesteps (M,), covs (M, dof, dof)) -> Σ^α_t of the nearest measured
                   timestep (calibrate.py measures every other step); or an array (n_steps, dof, dof)
                   aligned with the episode's steps                                     (Eq. (14))
    """
    steps = np.asarray(steps, dtype=np.int64)
    if isinstance(sigma, tuple):  # per_step with explicit timesteps
        covs, nearest = _nearest_measured(sigma, steps, dof)  # (M, dof, dof), (len(steps),) index into covs
        return covariance_factor(covs)[nearest]
    s = np.asarray(sigma, dtype=np.float64)
    if s.ndim == 0:  # isotropic baseline: L = σ m I
        _check_isotropic(sigma, s, median_step)
        return np.broadcast_to(float(s) * median_step * np.eye(dof), (len(steps), dof, dof))
    if s.shape == (dof, dof):  # pooled
        return np.broadcast_to(covariance_factor(s), (len(steps), dof, dof))
    if s.ndim == 3 and s.shape[1:] == (dof, dof):  # per_step, aligned with the episode
        _check_aligned(s, n_steps)
        return covariance_factor(s)[steps]
    raise _sigma_shape_error(s, dof, n_steps)


def _draw_valid(center: np.ndarray, factors: np.ndarray, rng: np.random.Generator, env, max_tries: int) -> tuple[np.ndarray, np.ndarray]:
    """q̃ = q_t + L z, z ~ N(0, I), so q̃ ~ N(q_t, L Lᵀ), per row; rows in collision or off the joint
    limits are redrawn up to `max_tries` rounds (rejecting, not clipping, keeps the states Gaussian-
    shaped instead of piling mass onto the limit). Returns (q̃ (m, dof), kept (m,) bool)."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in env.joint_limits)
    q = center.copy()
    kept = np.zeros(len(center), dtype=bool)
    todo = np.arange(len(center))
    for _ in range(max_tries):
        if todo.size == 0:
            break
        z = rng.standard_normal((todo.size, center.shape[1]))
        cand = center[todo] + np.einsum("mij,mj->mi", factors[todo], z)  # (m, dof)
        ok = np.all((cand >= lo) & (cand <= hi), axis=-1)  # inside the joint limits
        if ok.any():
            ok[ok] = ~np.asarray(env.in_collision(cand[ok]), dtype=bool)
        q[todo[ok]] = cand[ok]
        kept[todo[ok]] = True
        todo = todo[~ok]
    return q, kept


def perturb_states(episode: dict, sigma, rng: np.random.Generator, n: int, env, t_index=None,
                   median_step: float | None = None, horizon: int = 16, max_tries: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Draw n noised joint states q̃ ~ N(q_t, Σ_t) around the intervention states of `episode`.

    sigma: see `noise_factors` (isotropic scalar in median steps / pooled (dof, dof) / per-step).
    t_index: None -> t uniform over the steps with a valid label (`label_steps`); an int -> all n
      around that step; an array (n,) -> one state around each given step.
    env: reset to the episode's scenario (`env.reset(seed=episode['seed'])`) for collision checks.
    Returns (q̃ (m, dof), t (m,)) with m <= n: states still in collision or outside the joint limits
    after `max_tries` draws are dropped.
    """
    q, expert = _check_episode(episode)
    _check_count(n)
    if t_index is None:
        valid_t, _ = label_steps(expert, horizon)
        _check_has_labels(valid_t, horizon)
        t = rng.choice(valid_t, size=n)
    else:
        t = _check_t_index(np.broadcast_to(np.asarray(t_index, dtype=np.int64), (n,)).copy(), len(q))
    factors = noise_factors(sigma, t, q.shape[1], median_step=median_step, n_steps=len(q))
    env.reset(seed=int(episode["seed"]))
    q_tilde, kept = _draw_valid(q[t], np.asarray(factors), rng, env, max_tries)
    return q_tilde[kept], t[kept]


# ---- 3. Monotone closest-point projection (Sec. IV-E)

def monotone_projection(q: np.ndarray, trajectory: np.ndarray, t_start, window: int | None = None, t_end=None):
    """Index of the trajectory point closest to q among t_start <= t < min(t_start + window, t_end).

    "Monotone": the search never looks before t_start, so a noised copy of the state at step t is
    associated with step t or later even when an earlier point of the path is closer -- the label
    never tells the robot to go back in time. Ties go to the earliest index.
    q: (B, dof) or (dof,); trajectory (T, dof); t_start, t_end: int or (B,) (t_end exclusive,
    default T); window: steps, None = no bound. Returns (B,) int64 (or an int for a single q).
    """
    # checked arrays: q (B, dof), trajectory (T, dof), t_start (B,), t_end (B,); single: q was (dof,)
    q, trajectory, t_start, t_end, single = _projection_inputs(q, trajectory, t_start, window, t_end)
    # >>> exercise 8: the monotone closest-point projection (Sec. IV-E)
    width = int((t_end - t_start).max(initial=1))
    if window is not None:
        width = min(width, int(window))
    # candidates t_start .. t_start + W - 1; those past the segment end repeat its last point, which
    # cannot win: argmin returns the first of equal distances
    idx = np.minimum(t_start[:, None] + np.arange(width)[None, :], t_end[:, None] - 1)  # (B, W)
    diff = trajectory[idx] - q[:, None, :]  # (B, W, dof)
    best = t_start + np.argmin(np.einsum("bwd,bwd->bw", diff, diff), axis=1)  # squared distances
    return int(best[0]) if single else best
    # <<< exercise 8


# ---- 4. The return chunk: the critically damped PD of Sec. IV-E (the default servo: beyond the banner)

def critically_damped_gains(settle_steps: float) -> tuple[float, float]:
    """(Kp, Kd) per step for a critically damped PD on the discrete double integrator v ← v + a, q ← q + v
    (one control step, dt = 1). Continuous time: e'' + Kd e' + Kp e = 0 is critically damped for
    Kd = 2 √Kp (double pole -ω), and e(t) = (1 + ωt) e0 e^{-ωt} falls below 2 % at ωt ≈ 5.83. At dt = 1
    an Euler step of those gains overshoots, so the discrete double pole is placed at p = e^{-ω}: the
    error map [[1-Kp, 1-Kd], [-Kp, 1-Kd]] has trace 2 - Kp - Kd = 2p and determinant 1 - Kd = p²,
    i.e. Kp = (1-p)², Kd = 1 - p² (-> Kd = 2 √Kp as ω -> 0)."""
    _check_settle_steps(settle_steps)
    # >>> exercise 9: the critically damped PD return chunk, accelerations clamped (Sec. IV-E)
    p = np.exp(-5.83 / settle_steps)  # 5.83: (1 + x) e^{-x} = 0.02 at x = 5.83 (2 % settling)
    return float((1 - p) ** 2), float(1 - p ** 2)
    # <<< exercise 9


def pd_return_chunk(q0: np.ndarray, v0: np.ndarray, trajectory: np.ndarray, t_proj, H: int, lookahead,
                    accel_max, max_step, settle_steps: float | None = None, t_end=None, limits=None) -> np.ndarray:
    """Roll out a critically damped PD controller from (q0, v0) back onto the expert trajectory.

    The reference at step k is r_k = trajectory[t_proj + lookahead + k], held at the segment's last
    point (index t_end - 1): the chunk REJOINS the trajectory, then follows it. With e_k = q_k - r_k
    and u_k = r_k - r_{k-1}, the control is PD plus the reference's acceleration as feed-forward,
        a_k = -Kp e_k - Kd (v_k - u_k) + (u_{k+1} - u_k),
    so e obeys the map of `critically_damped_gains` exactly (settling in ~settle_steps, default H/2)
    while |a| <= accel_max (per joint, the demos') and |v| <= max_step (the env's) are inactive. In
    cascade form, a = Kd (w* - (v - u)) with closing speed w* = -(Kp/Kd) e, capped at √(2 accel_max |e|)
    so the clamped deceleration can still stop at the path. Sec. IV-E's target "a state a few timesteps
    further" is lookahead 0 here: the feed-forward removes the lag a lookahead makes up for (the literal
    reading is `lookahead_steps`, beyond the banner).

    q0, v0: (B, dof) or (dof,) rad, rad/step; trajectory (T, dof); t_proj, lookahead, t_end: int or
    (B,) steps; accel_max rad/step², max_step rad/step; limits: optional (lo, hi) joint limits.
    Returns the absolute joint targets q_1 .. q_H: (B, H, dof) (or (H, dof) for a single q0).
    """
    trajectory, q, v, single = _return_chunk_inputs(q0, v0, trajectory, H)
    B, dof = q.shape
    # checked: accel_max, max_step (dof,); start = t_proj + lookahead (B,); t_end (B,), default T
    accel_max, max_step, start, t_end = _pd_inputs(accel_max, max_step, t_proj, lookahead, t_end, B, dof, len(trajectory))
    # >>> exercise 9: the critically damped PD return chunk, accelerations clamped (Sec. IV-E)
    kp, kd = critically_damped_gains(H / 2 if settle_steps is None else settle_steps)
    # reference r_{-1} .. r_H, held at the segment's last point
    idx = np.minimum(start[:, None] + np.arange(-1, H + 1)[None, :], t_end[:, None] - 1)  # (B, H+2)
    idx = np.maximum(idx, 0)
    ref = trajectory[idx]  # (B, H+2, dof)
    u = np.diff(ref, axis=1)  # (B, H+1, dof): u[:, k] = r_k - r_{k-1}
    feedforward = np.diff(u, axis=1)  # (B, H, dof): the reference's own acceleration u_{k+1} - u_k
    clamp = lambda x, limit: np.minimum(np.maximum(x, -limit), limit)  # per joint (np.clip is slower)
    v = clamp(v, max_step)
    chunk = np.empty((B, H, dof))
    for k in range(H):
        e = q - ref[:, k + 1]  # tracking error e_k = q_k - r_k
        w_des = -(kp / kd) * e  # closing speed the linear PD asks for ...
        w_des = clamp(w_des, np.sqrt(2 * accel_max * np.abs(e)))  # ... capped so the clamped decel can still stop
        a = kd * (w_des - (v - u[:, k])) + feedforward[:, k]  # PD (cascade form) + feed-forward
        a = clamp(a, accel_max)  # accelerations seen in the demonstrations
        v = clamp(v + a, max_step)  # the env's speed limit
        q_next = q + v
        if limits is not None:
            q_next = np.minimum(np.maximum(q_next, limits[0]), limits[1])
            v = q_next - q  # a joint stopped by its limit has stopped moving
        q = q_next
        chunk[:, k] = q
    return chunk[0] if single else chunk
    # <<< exercise 9


def corrective_labels(q_tilde: np.ndarray, v: np.ndarray, trajectory: np.ndarray, t: np.ndarray, t_end: np.ndarray,
                      stats: DemoStats, cfg: RelabelConfig, limits=None, t_proj=None) -> tuple[np.ndarray, np.ndarray]:
    """The labelling of Sec. IV-E for noised states q̃ (m, dof) with velocities v (m, dof) that came
    from steps t (m,): monotone projection -> return chunk, by `cfg.label`: 'servo' (default, the
    authors', `servo_return_chunk`) or 'pd' (`pd_return_chunk`). `t_end` (m,) is the (exclusive) end
    of each state's expert segment in `trajectory`; `t_proj` (m,) may pass projections already computed.
    Returns (chunks (m, H, dof), mask (m, H) bool, True = in the loss; all True for 'pd')."""
    if t_proj is None:
        t_proj = monotone_projection(q_tilde, trajectory, t, window=cfg.projection_window, t_end=t_end)
    _check_label(cfg)
    if cfg.label == "servo":
        return servo_return_chunk(q_tilde, v, trajectory, t_proj, cfg.horizon, stats.median_step, stats.acc_p95,
                                  stats.max_step, t_end=t_end, limits=limits, cfg=cfg)
    ahead = _pd_lookahead(q_tilde, trajectory, t_proj, stats, cfg)  # 0 (time-matched) unless lookahead='gap'
    chunks = pd_return_chunk(q_tilde, v, trajectory, t_proj, cfg.horizon, ahead, stats.accel_max, stats.max_step,
                             settle_steps=cfg.settle_steps, t_end=t_end, limits=limits)
    return chunks, np.ones(chunks.shape[:2], dtype=bool)


# ---- 5. On-the-fly augmentation for co-training (Sec. IV-A steps 3-4)

NOISE_KINDS = ("isotropic", "pooled", "per_step")


def velocity_noise_std(cfg: RelabelConfig, stats: DemoStats) -> float:
    """rad per env step: the std of a noised state's per-joint velocity noise (PAPER_SETUP.md §6).

    The authors add N(0, (0.3 m_p)²) per joint to the velocity per 30 Hz frame, m_p their median step:
    0.3 · 0.0176 = 0.00528 rad/frame = 0.158 rad/s on the planar arm. The same rate over one of our
    steps, which spans frames_per_step = dt / (1/30 s) of their frames, is
        velocity_noise · m_p · frames_per_step  = 0.3 · 0.0176 · 3 = 0.0158 rad per 0.1 s step
    (0.65 of our median step 0.0245; 0.3 of ours per step, 0.0074 rad, was 2.15x too little).
    Without the env's units (stats.paper_median_step or frames_per_step None): velocity_noise of our
    median step per step.
    """
    if stats.paper_median_step is None or stats.frames_per_step is None:
        return cfg.velocity_noise * stats.median_step
    return cfg.velocity_noise * stats.paper_median_step * stats.frames_per_step


class AugmentationSampler:
    """sampler(n, rng) -> (obs (n, obs_dim) float32, chunks (n, H, dof) float32, mask (n, H) bool):
    noised intervention states with corrective labels, the D̂_1 ∪ ... ∪ D̂_k of Sec. IV-A, made on the fly.

    noise / sigma: 'isotropic' a scalar σ in median steps (Table I baselines); 'pooled' Σ̄^α (dof, dof)
      rad² (Eqs. (15)-(16)); 'per_step' (Eq. (14)) sigma[e] for episode index e is a pair (timesteps
      (M,), covs (M, dof, dof)), in a list aligned with `episodes` or a dict {episode index: pair}.
    make_env: a no-argument factory (e.g. `lambda: envs.make_env('planar')`); one env per scenario seed.

    A pair: (episode, t) uniform among the labelable intervention steps; q̃ ~ N(q_t, Σ_t) (collision-free,
    within limits); v = (q_t - q_{t-1}) + N(0, `velocity_noise_std`²); obs = env.make_obs(q̃, q̃ - v) in the
    episode's scenario (PAPER_SETUP.md §6), given the recorded observation of state t (env.make_obs_near: an env
    whose observation is a camera image keeps the recorded image, the paper's Sec. V); chunk, mask =
    `corrective_labels`.
    Pairs are made in batches into a pool that each call draws from (`_refresh_pool`, beyond the banner);
    all randomness comes from each call's rng: the same seed and calls give the same pairs."""

    def __init__(self, episodes: Sequence[dict], make_env: Callable[[], object], stats: DemoStats,
                 noise: str, sigma, cfg: RelabelConfig | None = None):
        self.cfg = cfg or RelabelConfig()
        _check_sampler_config(noise, self.cfg)
        self.noise, self.stats, self._make_env, self._envs = noise, stats, make_env, {}
        # One flat table of every labelable intervention step (`label_steps`), the episodes concatenated
        # so projection and labels run once per batch (`_build_table`): trajectory (sum T, dof); per row:
        # center q_t, velocity q_t - q_{t-1}, factors L_t (`noise_factors`), t_glob / end_glob (q_t / its
        # segment's exclusive end in trajectory), seeds (scenario), episode_of / step_of (its recorded obs).
        _build_table(self, episodes, sigma)
        self._pool_obs = self._pool_chunks = self._pool_mask = None
        self._filled = self._write = self._served = 0  # pool fill, ring position, served since refresh
        self.n_drawn = self.n_kept = 0  # acceptance bookkeeping (collision / limit rejections)

    def generate(self, m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """m fresh pairs (fewer if states were dropped): obs (m', obs_dim) float32, chunks (m', H, dof)
        float32, mask (m', H) bool (True = in the loss). Rows are labelled by `_label_rows`, and those it
        rejects are redrawn up to `max_redraws` times (PAPER_SETUP.md §6; `_label_with_redraws`)."""
        _check_positive_count(m)
        rows = _draw_rows(self, m, rng)  # (m,) rows of the table, uniform over the labelable steps
        self.n_drawn += m
        r, q_tilde, v, chunks, mask = _label_with_redraws(self, rows, rng)
        self.n_kept += r.size
        if r.size == 0:
            return _no_pairs(self.cfg.horizon, self.center.shape[1])
        # obs = env.make_obs(q̃, q̃ - v) per scenario, near the recorded observation of state t (env.make_obs_near)
        return _observe(self, r, q_tilde, v), chunks.astype(np.float32), mask

    def _label_rows(self, rows: np.ndarray, rng: np.random.Generator, limits):
        """One pass of the pipeline over table rows (m,). Returns (r, q̃, v, chunks, mask) of the pairs
        made, and the rows to redraw: those projecting within `near_end_steps` of their segment's end, or
        whose label has fewer than `min_moving_steps` unmasked steps. Rows whose state stays in collision
        / off limits for `max_tries` draws are dropped."""
        cfg, dof = self.cfg, self.center.shape[1]
        q_tilde, kept = np.empty((len(rows), dof)), np.zeros(len(rows), dtype=bool)
        for seed in np.unique(self.seeds[rows]):  # q̃ ~ N(q_t, Σ_t): one batched collision check per scenario
            sel = self.seeds[rows] == seed
            q_tilde[sel], kept[sel] = _draw_valid(self.center[rows[sel]], self.factors[rows[sel]], rng,
                                                  self._env(int(seed)), cfg.max_tries)
        r, q_tilde = rows[kept], q_tilde[kept]  # states still invalid after max_tries are dropped
        # PAPER_SETUP.md §6: velocity = demo tangent + N(0, (0.3 of the paper's median step per frame)²) per joint
        v = self.velocity[r] + velocity_noise_std(cfg, self.stats) * rng.standard_normal(q_tilde.shape)
        t_proj = monotone_projection(q_tilde, self.trajectory, self.t_glob[r], window=cfg.projection_window,
                                     t_end=self.end_glob[r])
        ok = t_proj < self.end_glob[r] - cfg.near_end_steps  # not within near_end_steps of the end
        chunks, mask = corrective_labels(q_tilde[ok], v[ok], self.trajectory, self.t_glob[r[ok]],
                                         self.end_glob[r[ok]], self.stats, cfg, limits=limits, t_proj=t_proj[ok])
        moving = mask.sum(axis=1) >= cfg.min_moving_steps  # enough steps left in the loss
        ok[ok] = moving
        return (r[ok], q_tilde[ok], v[ok], chunks[moving], mask[moving]), r[~ok]

    def __call__(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """n pairs from the pool (diffusion.train's sampler hook): obs (n, obs_dim), chunks (n, H, dof),
        mask (n, H) bool (True = in the loss). Fills the pool on the first call."""
        _check_count(n)
        _fill_or_refresh_pool(self, rng)  # the first call fills it; then every reuse · refresh_size pairs served
        self._served += n
        pick = rng.integers(self._filled, size=n)
        return self._pool_obs[pick], self._pool_chunks[pick], self._pool_mask[pick]

    def _env(self, seed: int):  # the env of a scenario seed, made and reset once (`_scenario_env`)
        return _scenario_env(self, seed)

    def state_dict(self) -> dict:
        """The pool and its counters, for a resumed training run (the caller restores its rng)."""
        return _sampler_state(self)  # beyond the banner, as the loader

    def load_state_dict(self, state: dict) -> None:
        _load_sampler_state(self, state)


# ---- 6. Fig. 1: expert trajectory, policy-calibrated noise ellipses, sampled recovery trajectories

def plot_recovery(env, episode: dict, sigma, path: str, rng: np.random.Generator, stats: DemoStats,
                  cfg: RelabelConfig | None = None, n_recoveries: int = 6, n_ellipses: int = 6) -> str:
    """The paper's Fig. 1: the expert (intervention) end-effector path in blue, 2σ ellipses of the
    policy-calibrated noise pushed through the end-effector Jacobian (J Σ_t Jᵀ), and sampled recovery
    trajectories (end-effector paths of return chunks from noised states) in orange; left the scene,
    right a close-up of a fan of returns from one state. A 3-D env (env.dim == 3) is drawn in its top
    view (x, y in m). sigma as in `noise_factors`. Saves a PNG to `path` and returns it."""
    plt = _pyplot()  # matplotlib.pyplot on the Agg backend (files only)
    cfg = cfg or RelabelConfig()
    q, expert = _check_episode(episode)
    valid_t, seg_end = label_steps(expert, cfg.horizon)
    _check_has_labels(valid_t, cfg.horizon, figure=True)
    seg = valid_t[seg_end == seg_end[0]]  # labelable steps of the first intervention segment
    end = int(seg_end[0])
    env.reset(seed=int(episode["seed"]))
    xy = lambda qs: env.ee(qs)[:, :2]  # (B, 2) end effector in the drawn plane (x, y)

    def cov_at(ts):  # (n, dof, dof): the joint covariances Σ_t = L_t L_tᵀ at steps ts
        f = noise_factors(sigma, ts, q.shape[1], median_step=stats.median_step, n_steps=len(q))
        return f @ np.swapaxes(f, 1, 2)

    ell_t = seg[np.linspace(0, len(seg) - 1, min(n_ellipses, len(seg))).round().astype(int)]  # a handful
    # recovery trajectories from noised states at evenly spread steps of the segment, and a fan of them
    # from one state in the middle (the close-up)
    mid = int(seg[len(seg) // 2])
    steps = np.concatenate([seg[np.linspace(0, len(seg) - 1, n_recoveries).round().astype(int)],
                            np.full(n_recoveries, mid)])  # (2 n,)
    q_tilde, t = perturb_states(episode, sigma, rng, len(steps), env, t_index=steps,
                                median_step=stats.median_step, horizon=cfg.horizon, max_tries=cfg.max_tries)
    v = q[t] - q[np.maximum(t - 1, 0)]
    chunks, _ = corrective_labels(q_tilde, v, q, t, np.full(len(t), end), stats, cfg, limits=env.joint_limits)
    recoveries = [xy(np.concatenate([qt[None], ch])) for qt, ch in zip(q_tilde, chunks)]  # (H+1, 2) each

    env.set_state(q[seg[0]])  # the arm is drawn where the intervention starts
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.5))
    for ax in axes:
        _fig1_background(ax, env, q)  # planar: the arm, faded; 3-D top view: goal and base markers
        env.draw_noise_ellipses(ax, q[ell_t], cov_at(ell_t), "tab:blue", alpha=0.2)
        for rec in recoveries:
            ax.plot(rec[:, 0], rec[:, 1], color="tab:orange", lw=1.3)
            ax.plot(rec[0, 0], rec[0, 1], "o", color="tab:orange", ms=3)
        ax.plot(*xy(q[seg[0]:end]).T, color="tab:blue", lw=2.0)
        ax.set_aspect("equal")
    # close-up: the fan of returns from the middle state and its ellipse
    env.draw_noise_ellipses(axes[1], q[mid:mid + 1], cov_at(np.array([mid])), "tab:blue", alpha=0.2)
    fan = [rec for rec, ti in zip(recoveries, t) if ti == mid]
    _fig1_windows(axes, env, q, seg[0], end, mid, fan, cov_at(np.array([mid]))[0], cfg.horizon)
    _fig1_finish(fig, axes, env, path)  # legend, titles, layout; saves and closes
    return path


# ==== Beyond the paper (safe to skip) ====================================================

# ---- the authors' clamped servo: the label the loop uses by default ------------------------------
# From their code (PAPER_SETUP.md §6), not the paper's text. The paper's PD return is pd_return_chunk
# above (exercise 9); RelabelConfig(label='pd') uses it.

def servo_return_chunk(q0: np.ndarray, v0: np.ndarray, trajectory: np.ndarray, t_proj, H: int, median_step: float,
                       acc_p95: float, max_step, t_end=None, limits=None, cfg: RelabelConfig | None = None):
    """The label the training loop uses by default. It follows the authors' code (PAPER_SETUP.md §6),
    not the paper's text: a critically damped servo tracking the expert segment at its own cursor.

    Every step k the cursor c_k is the monotone projection of the label's own point x_k, at most
    `cursor_advance` indices past c_{k-1} (c starts at t_proj), and with m = median_step:
        a_k = Kp (r_c - x_k) + Kd (u_c - v_k),   r_c = trajectory[c], u_c = r_{c+1} - r_c (0 at the end),
        a_clamp = 0.9 · max(2√dof · acc_p95, accel_floor · m),  Kp = a_clamp / max(d0, gain_floor · m),
        Kd = 2 √Kp (critical damping),  d0 = ‖q0 - trajectory[t_proj]‖;
    then ‖a_k‖ <= a_clamp, ‖a_k - a_{k-1}‖ <= jerk_slew · a_clamp, ‖v‖ <= max(speed_cap · m,
    speed_cap_v0 · ‖v0‖) (the authors' norm clamps), |v| <= max_step per joint, x within `limits`.
    Held tail: once the cursor is at the segment's end and the arm has stopped (every joint moves
    < hold_tol · m) for the rest of the chunk, those steps repeat the end pose: mask False, out of the loss.
    (At hold_tol = 1e-3 the servo's k e^{-ωk} stop was not reached within H: measured.)

    q0, v0: (B, dof) or (dof,); trajectory (T, dof); t_proj, t_end: int or (B,) (t_end exclusive).
    Returns (chunk (B, H, dof) absolute joint targets x_1 .. x_H, mask (B, H) bool, True = in the
    loss); (H, dof) and (H,) for a single q0.
    """
    cfg = cfg or RelabelConfig()
    trajectory, x, v, single = _return_chunk_inputs(q0, v0, trajectory, H)
    B, dof = x.shape
    _check_servo_stats(median_step, acc_p95)
    max_step = np.broadcast_to(np.asarray(max_step, dtype=np.float64), (dof,))
    T = len(trajectory)
    t_end = np.broadcast_to(np.asarray(T if t_end is None else t_end, dtype=np.int64), (B,))
    cursor = np.broadcast_to(np.asarray(t_proj, dtype=np.int64), (B,)).copy()
    m = median_step
    norm = lambda a: np.linalg.norm(a, axis=-1, keepdims=True)  # (B, 1)
    cap = lambda a, limit: a * np.minimum(1.0, limit / np.maximum(norm(a), 1e-300))  # ‖a‖ <= limit
    a_clamp = cfg.a_clamp_scale * max(2 * np.sqrt(dof) * acc_p95, cfg.accel_floor * m)  # rad/step²
    d0 = norm(x - trajectory[cursor])  # (B, 1) distance to the projection
    omega = np.sqrt(a_clamp / np.maximum(d0, cfg.gain_floor * m))  # (B, 1): √Kp, Kp = a_clamp / max(d0, floor)
    # Kd = 2 √Kp is unstable under Euler at our ω ~ 1.1 per step (the label chattered; at the authors'
    # 30 Hz ω is 3x smaller): the double pole is placed at e^{-ω} as in `critically_damped_gains`.
    p = np.exp(-omega)
    kp, kd = (1 - p) ** 2, 1 - p ** 2  # (B, 1) per step², per step
    v_cap = np.maximum(cfg.speed_cap * m, cfg.speed_cap_v0 * norm(v))  # (B, 1) rad/step
    v = np.minimum(np.maximum(v, -max_step), max_step)
    a_prev = np.zeros((B, dof))
    chunk = np.empty((B, H, dof))
    held = np.zeros((B, H), dtype=bool)
    for k in range(H):
        # the servo's own monotone cursor: project x_k, never back, at most cursor_advance ahead
        cursor = monotone_projection(x, trajectory, cursor, window=cfg.cursor_advance + 1, t_end=t_end)
        at_end = cursor >= t_end - 1
        ref = trajectory[cursor]  # (B, dof)
        ref_vel = trajectory[np.minimum(cursor + 1, t_end - 1)] - ref  # (B, dof), 0 at the end
        a = kp * (ref - x) + kd * (ref_vel - v)  # PD on position and velocity error
        a = cap(a, a_clamp)  # accelerations of the demo envelope
        a = a_prev + cap(a - a_prev, cfg.jerk_slew * a_clamp)  # bounded jerk (slew)
        a_prev = a
        v = cap(v + a, v_cap)  # speed cap
        v = np.minimum(np.maximum(v, -max_step), max_step)  # the env's per-joint speed limit
        x_next = x + v
        if limits is not None:
            x_next = np.minimum(np.maximum(x_next, limits[0]), limits[1])
            v = x_next - x  # a joint stopped by its limit has stopped moving
        held[:, k] = at_end & (np.abs(x_next - x).max(axis=1) < cfg.hold_tol * m)
        x = x_next
        chunk[:, k] = x
    # the held tail: steps from which on every step is held; (B, H), True = in the loss
    tail = np.flip(np.logical_and.accumulate(np.flip(held, axis=1), axis=1), axis=1)
    mask = ~tail
    return (chunk[0], mask[0]) if single else (chunk, mask)


# ---- the literal lookahead of Sec. IV-E, measured worse than the time-matched target -------------

def lookahead_steps(q0: np.ndarray, q_proj: np.ndarray, median_speed: float, max_lookahead: int) -> np.ndarray:
    """The literal reading of Sec. IV-E's target, "a state a few timesteps further in the expert
    trajectory (computed with the median velocity in the dataset)": L = the steps the demos take at
    their median speed (rad/step) to cover the gap ‖q0 - q_proj‖ (rad), capped at max_lookahead
    steps (0 on the path).

    Why it is not the default (RelabelConfig.lookahead): a plain PD chasing a point that advances
    along the path settles Kd/Kp steps *behind* it, and a lookahead of a few steps is what puts
    such a PD back on the time-matched point. `pd_return_chunk` has velocity feed-forward and no
    lag, so its equivalent is lookahead 0 (reference trajectory[t_proj + k]). With L > 0 on top, the
    arm must gain L steps on an expert that already moves at the speed limit, which it cannot: on
    oracle demos at σ = 4 the chunk ends were 1.32 median steps from the path against 0.10
    time-matched (medians; benchmarks/bench_relabel.py).
    """
    gap = np.linalg.norm(np.asarray(q0) - np.asarray(q_proj), axis=-1)
    return np.minimum(np.ceil(gap / median_speed), max_lookahead).astype(np.int64)


def _pd_lookahead(q_tilde, trajectory, t_proj, stats: DemoStats, cfg: RelabelConfig):
    """The 'pd' label's lookahead in steps: 0 for 'time_matched', `lookahead_steps` for 'gap'."""
    if cfg.lookahead == "time_matched":
        return 0
    if cfg.lookahead == "gap":
        return lookahead_steps(q_tilde, trajectory[t_proj], stats.median_speed, cfg.max_lookahead)
    raise ValueError(f"RelabelConfig.lookahead must be 'time_matched' or 'gap', got {cfg.lookahead!r}")


# ---- Fig. 1's axes, windows, legend and titles ---------------------------------------------------

def _fig1_background(ax, env, q: np.ndarray) -> None:
    """Under Fig. 1's data: on a 3-D env (top view) the goal and the arm's base as markers and the axis
    labels; on a planar env the scene and the arm (`render(ax)` draws in the plane), faded: the path,
    noise and returns are the message."""
    if getattr(env, "dim", 2) == 3:
        ax.plot(*env.goal[:2], "*", color="tab:green", ms=14, zorder=3)
        ax.plot(*env.fk(q[:1])[0, 0, :2], "s", color="k", ms=6)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    else:
        env.render(ax, alpha=0.35)


def _fig1_windows(axes, env, q: np.ndarray, start: int, end: int, mid: int, fan: list, cov_mid: np.ndarray,
                  horizon: int) -> None:
    """Fig. 1's view windows: the close-up around the fan and the path a chunk either side of the middle
    state, with a margin of its ellipse's 2σ radius (m); on a 3-D env also the scene around the path, the
    goal and the base (a planar env's render sets its own window)."""
    xy = lambda qs: env.ee(qs)[:, :2]
    near = xy(q[max(mid - horizon // 2, start):min(mid + horizon + 1, end)])
    jac = env.ee_jacobian(q[mid:mid + 1])[0, :2]  # (2, dof)
    radius = 2 * np.sqrt(max(np.linalg.eigvalsh(jac @ cov_mid @ jac.T).max(), 0))  # 2σ, m
    pts = np.concatenate([near, *fan])
    span = float(np.max(pts.max(axis=0) - pts.min(axis=0)))
    # a close-up stays a close-up: a wide ellipse (a briefly trained policy's noise) is cut at the frame
    env.square_view(axes[1], pts, min(radius, max(span, 0.05)))
    if getattr(env, "dim", 2) == 3:
        env.square_view(axes[0], np.concatenate([xy(q[start:end]), env.goal[None, :2], env.fk(q[:1])[0, :1, :2]]), 0.05)


def _fig1_finish(fig, axes, env, path: str) -> None:
    """Fig. 1's legend, titles and layout; saves the PNG to `path`."""
    top_view = getattr(env, "dim", 2) == 3
    _fig1_legend(fig, top_view)
    axes[0].set_title("scene (top view)" if top_view else "scene")
    axes[1].set_title("close-up (top view)" if top_view else "close-up")
    fig.suptitle("Policy-calibrated noise around an intervention and the return labels (paper Fig. 1)")
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(path, dpi=120)
    _pyplot().close(fig)


def _pyplot():
    """matplotlib.pyplot on the Agg backend (plot_recovery only writes files; no display needed)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _fig1_legend(fig, goal_marker: bool) -> None:
    """Fig. 1's legend, below the panels (outside the data)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    handles = [Line2D([], [], color="tab:blue", lw=2, label="expert intervention (end effector)"),
               Patch(facecolor="tab:blue", alpha=0.2, label="policy-calibrated noise (2σ)"),
               Line2D([], [], color="tab:orange", label="sampled recovery trajectories")]
    if goal_marker:
        handles += [Line2D([], [], marker="*", color="tab:green", ls="", ms=10, label="goal"),
                    Line2D([], [], marker="s", color="k", ls="", ms=6, label="arm base")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)


# ---- the sampler's machinery: the table, episodes-first draws, redraws, observations, the pool (a ring
#      buffer), resume --------

def _build_table(sampler: AugmentationSampler, episodes: Sequence[dict], sigma) -> None:
    """The sampler's flat table of labelable intervention steps (see AugmentationSampler.__init__)."""
    H, noise, stats = sampler.cfg.horizon, sampler.noise, sampler.stats
    traj, center, vel, t_glob, end_glob, factors, seeds, ep_of, offset = [], [], [], [], [], [], [], [], 0
    sampler._episode_obs = [ep["obs"] for ep in episodes]  # recorded observations (references, no copy)
    for e, ep in enumerate(episodes):
        q, expert = _check_episode(ep)
        t, seg_end = label_steps(expert, H, sampler.cfg.pad_short)
        if t.size == 0:
            offset += len(q)
            traj.append(q)
            continue
        dof = q.shape[1]
        factors.append(noise_factors(_episode_sigma(noise, sigma, e, dof), t, dof, median_step=stats.median_step))
        prev = q[np.maximum(t - 1, 0)]  # at t = 0 the arm starts at rest (q_prev = q)
        traj.append(q)
        center.append(q[t])
        vel.append(q[t] - prev)
        t_glob.append(offset + t)
        end_glob.append(offset + seg_end)
        seeds.append(np.full(t.size, int(ep["seed"])))
        ep_of.append(np.full(t.size, e))
        offset += len(q)
    if not center:
        raise ValueError(f"no intervention step with a valid label (expert run >= H={H}) in {len(episodes)} episodes")
    sampler.trajectory = np.concatenate(traj)  # (sum T, dof)
    sampler.center = np.concatenate(center)  # (N, dof) q_t
    sampler.velocity = np.concatenate(vel)  # (N, dof) q_t - q_{t-1}
    sampler.t_glob = np.concatenate(t_glob)  # (N,) index of q_t in sampler.trajectory
    sampler.end_glob = np.concatenate(end_glob)  # (N,) exclusive end of its expert segment
    sampler.factors = np.ascontiguousarray(np.concatenate(factors))  # (N, dof, dof)
    sampler.seeds = np.concatenate(seeds)
    sampler.episode_of = np.concatenate(ep_of)
    sampler.step_of = sampler.t_glob - np.concatenate([[0], np.cumsum([len(q) for q in traj])])[sampler.episode_of]
    # contiguous block of rows per episode, for the "episodes first" draw
    sampler._ep_ids, sampler._ep_start, sampler._ep_count = np.unique(sampler.episode_of, return_index=True,
                                                                      return_counts=True)


def _draw_rows(sampler: AugmentationSampler, m: int, rng: np.random.Generator) -> np.ndarray:
    """m rows of the sampler's table, uniform over the labelable steps, drawn episodes first: k episodes
    with probability proportional to their labelable steps, then steps within them, so that a batch
    touches at most k = episodes_per_refresh scenarios (env calls are batched per scenario)."""
    k = min(sampler.cfg.episodes_per_refresh, m)
    draws = rng.choice(len(sampler._ep_ids), size=k, p=sampler._ep_count / sampler._ep_count.sum())
    per_draw = np.full(k, m // k)
    per_draw[: m % k] += 1
    return np.concatenate([sampler._ep_start[d] + rng.integers(sampler._ep_count[d], size=c)
                           for d, c in zip(draws, per_draw)])


def _label_with_redraws(sampler: AugmentationSampler, rows: np.ndarray, rng: np.random.Generator):
    """`_label_rows`, then again on the rows it asks to redraw, at most `max_redraws` times; the pairs
    of all passes concatenated: (r (m',), q̃ (m', dof), v (m', dof), chunks (m', H, dof), mask (m', H))."""
    limits = sampler._env(int(sampler.seeds[rows[0]])).joint_limits
    parts = []
    for _ in range(sampler.cfg.max_redraws + 1):
        if rows.size == 0:
            break
        part, rows = sampler._label_rows(rows, rng, limits)
        parts.append(part)
    return tuple(np.concatenate(x) for x in zip(*parts))


def _observe(sampler: AugmentationSampler, rows: np.ndarray, q_tilde: np.ndarray, v: np.ndarray) -> np.ndarray:
    """obs (m, obs_dim) float32 of noised states, one batched env call per scenario. The previous
    frame is rebuilt as q̃ - v (PAPER_SETUP.md §6); make_obs_near recomputes the end effector from q̃, given the
    recorded observations of the states the rows were drawn around."""
    obs = None
    for seed in np.unique(sampler.seeds[rows]):
        sel = sampler.seeds[rows] == seed
        env, r = sampler._env(int(seed)), rows[sel]
        recorded = np.stack([sampler._episode_obs[e][t] for e, t in zip(sampler.episode_of[r], sampler.step_of[r])])
        part = np.asarray(env.make_obs_near(q_tilde[sel], q_tilde[sel] - v[sel], recorded), dtype=np.float32)
        if obs is None:
            obs = np.empty((len(rows), part.shape[1]), np.float32)
        obs[sel] = part
    return obs


def _scenario_env(sampler: AugmentationSampler, seed: int):
    """One env per scenario seed, made by `make_env` and reset once, then reused (sampler._envs)."""
    if seed not in sampler._envs:
        env = sampler._make_env()
        env.reset(seed=seed)
        sampler._envs[seed] = env
    return sampler._envs[seed]


def _no_pairs(H: int, dof: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """generate's result when every state was dropped: empty obs, chunks (0, H, dof), mask (0, H)."""
    return np.empty((0, 0), np.float32), np.empty((0, H, dof), np.float32), np.empty((0, H), bool)


def _fill_or_refresh_pool(sampler: AugmentationSampler, rng: np.random.Generator) -> None:
    """The pool's schedule in `AugmentationSampler.__call__`: fill it on the first call; afterwards replace
    the oldest `refresh_size` pairs every `reuse * refresh_size` pairs served."""
    if sampler._filled == 0:  # first call
        _fill_pool(sampler, rng)
    elif sampler._served >= sampler.cfg.reuse * sampler.cfg.refresh_size:
        _refresh_pool(sampler, rng)
        sampler._served = 0


def _fill_pool(sampler: AugmentationSampler, rng: np.random.Generator) -> None:
    """The first call's fill of the pool (a bounded number of refreshes)."""
    cfg = sampler.cfg
    for _ in range(4 * cfg.pool_size // cfg.refresh_size):
        _refresh_pool(sampler, rng)
        if sampler._filled >= cfg.pool_size:
            break
    if sampler._filled == 0:
        raise ValueError(f"every perturbed state was in collision or outside the joint limits after "
                         f"{cfg.max_tries} tries, or too near its segment's end after "
                         f"{cfg.max_redraws} redraws; the noise ({sampler.noise}) is too large for these scenarios")


def _refresh_pool(sampler: AugmentationSampler, rng: np.random.Generator) -> int:
    """Replace the `refresh_size` oldest pairs of the pool by fresh ones; returns how many were made."""
    obs, chunks, mask = sampler.generate(sampler.cfg.refresh_size, rng)
    if sampler._pool_obs is None and len(obs):
        P = sampler.cfg.pool_size
        sampler._pool_obs = np.empty((P, obs.shape[1]), np.float32)
        sampler._pool_chunks = np.empty((P, *chunks.shape[1:]), np.float32)
        sampler._pool_mask = np.empty((P, chunks.shape[1]), bool)
    if len(obs):  # ring buffer: overwrite the oldest pairs
        slots = (sampler._write + np.arange(len(obs))) % sampler.cfg.pool_size
        sampler._pool_obs[slots], sampler._pool_chunks[slots], sampler._pool_mask[slots] = obs, chunks, mask
        sampler._write = int((sampler._write + len(obs)) % sampler.cfg.pool_size)
        sampler._filled = min(sampler.cfg.pool_size, sampler._filled + len(obs))
    return len(obs)


def _sampler_state(sampler: AugmentationSampler) -> dict:
    copy = lambda a: None if a is None else a.copy()
    return {"pool_obs": copy(sampler._pool_obs), "pool_chunks": copy(sampler._pool_chunks),
            "pool_mask": copy(sampler._pool_mask), "filled": int(sampler._filled),  # plain ints: a numpy scalar
            "write": int(sampler._write), "served": int(sampler._served),             # is refused by the
            "n_drawn": int(sampler.n_drawn), "n_kept": int(sampler.n_kept)}           # checkpoint's safe loader


def _load_sampler_state(sampler: AugmentationSampler, state: dict) -> None:
    copy = lambda a, dtype: None if a is None else np.array(a, dtype=dtype)
    sampler._pool_obs, sampler._pool_chunks = copy(state["pool_obs"], np.float32), copy(state["pool_chunks"], np.float32)
    sampler._pool_mask = copy(state.get("pool_mask"), bool)
    if sampler._pool_mask is None and sampler._pool_chunks is not None:  # a pool saved before masks existed
        sampler._pool_mask = np.ones(sampler._pool_chunks.shape[:2], dtype=bool)
    sampler._filled, sampler._write, sampler._served = int(state["filled"]), int(state["write"]), int(state["served"])
    sampler.n_drawn, sampler.n_kept = int(state["n_drawn"]), int(state["n_kept"])


# ---- the noise factor L (L Lᵀ = Σ) of a covariance, robust to singular Σ̂ ------------------------

def covariance_factor(cov: np.ndarray) -> np.ndarray:
    """L with L Lᵀ = Σ for a batch of covariances (..., dof, dof).

    An eigendecomposition rather than a Cholesky: Σ̂ from a handful of policy samples is often
    (near-)singular -- a flat ellipse -- where Cholesky fails. Eigenvalues negative only by round-off
    are set to 0; clearly negative ones mean the matrix is not a covariance (ValueError).
    """
    cov = _check_covariance(cov)  # (..., dof, dof) float64, finite and symmetric
    w, v = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    tol = 1e-9 * np.maximum(np.abs(w).max(axis=-1, keepdims=True), 1e-300)
    if np.any(w < -tol):
        raise ValueError(f"covariance is not positive semi-definite (smallest eigenvalue {w.min():.3g}); "
                         "valid covariances have eigenvalues >= 0")
    return v * np.sqrt(np.clip(w, 0.0, None))[..., None, :]  # (..., dof, dof): columns scaled


# ---- per-step Σ^α_t (calibrate.py measures every other step): the nearest measured timestep -----

def _nearest_measured(sigma: tuple, steps: np.ndarray, dof: int) -> tuple[np.ndarray, np.ndarray]:
    """A per-step sigma (timesteps (M,), covs (M, dof, dof)) sorted by timestep, and for each of `steps`
    the index of the nearest measured timestep (ties -> the earlier): (covs (M, dof, dof), nearest (len(steps),))."""
    measured_t, covs = _per_step_pair(sigma, dof)  # (M,), (M, dof, dof)
    order = np.argsort(measured_t, kind="stable")
    measured_t, covs = measured_t[order], covs[order]
    right = np.clip(np.searchsorted(measured_t, steps), 0, len(measured_t) - 1)
    left = np.clip(right - 1, 0, len(measured_t) - 1)
    nearest = np.where(np.abs(measured_t[left] - steps) <= np.abs(measured_t[right] - steps), left, right)
    return covs, nearest


# ---- input checks ---------------------------------------------------------------------------------

def _check_episode(episode: dict) -> tuple[np.ndarray, np.ndarray]:
    """(q (T, dof) float64, expert (T,) bool) of an episode, checked."""
    for key in ("q", "expert", "seed"):
        if key not in episode:
            raise ValueError(f"episode is missing '{key}'; an episode has 'obs', 'q', 'action', 'expert', 'seed'")
    q = np.asarray(episode["q"], dtype=np.float64)
    expert = np.asarray(episode["expert"], dtype=bool)
    if q.ndim != 2 or len(q) == 0:
        raise ValueError(f"episode['q'] must be (T, dof) with T >= 1, got shape {q.shape}")
    if expert.shape != (len(q),):
        raise ValueError(f"episode['expert'] must be ({len(q)},) like q, got shape {expert.shape}")
    return q, expert


def _check_clamps(accel_max: np.ndarray, max_step) -> np.ndarray:
    """demo_stats' clamps, checked > 0: the demos' accelerations (dof,) rad/step² and the env's speed
    limit (scalar or (dof,) rad/step), returned as a (dof,) array."""
    if np.any(accel_max <= 0):
        raise ValueError(f"the demonstrations show no acceleration on joints {np.flatnonzero(accel_max <= 0).tolist()}; "
                         "the PD return could never move them (accel clamp would be 0)")
    dof = accel_max.shape[0]
    max_step = np.broadcast_to(np.asarray(max_step, dtype=np.float64), (dof,)).copy()
    if np.any(~np.isfinite(max_step)) or np.any(max_step <= 0):
        raise ValueError(f"max_step must be positive and finite (rad/step), got {max_step}")
    return max_step


def _check_covariance(cov) -> np.ndarray:
    """cov as float64 (..., dof, dof), checked square, finite and symmetric (relative tolerance)."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.ndim < 2 or cov.shape[-1] != cov.shape[-2]:
        raise ValueError(f"a covariance must be (..., dof, dof), got shape {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise ValueError("covariance contains NaN or inf; valid covariances are finite")
    scale = float(np.abs(cov).max(initial=0.0))  # relative tolerances: covariances are ~1e-4 rad²
    if np.abs(cov - np.swapaxes(cov, -1, -2)).max(initial=0.0) > 1e-8 * scale:
        raise ValueError("covariance is not symmetric; valid covariances satisfy Σ = Σᵀ")
    return cov


def _sigma_shape_error(s: np.ndarray, dof: int, n_steps: int | None) -> ValueError:
    return ValueError(f"sigma must be a scalar (isotropic), ({dof}, {dof}) (pooled), ({n_steps}, {dof}, {dof}) or "
                      f"(timesteps, covs) (per-step); got shape {s.shape}")


def _per_step_pair(sigma: tuple, dof: int) -> tuple[np.ndarray, np.ndarray]:
    """A per-step sigma (timesteps (M,), covs (M, dof, dof)) as int64 / float64 arrays, checked."""
    if len(sigma) != 2:
        raise ValueError("per-step sigma must be a pair (timesteps (M,), covs (M, dof, dof))")
    measured_t = np.asarray(sigma[0], dtype=np.int64)
    covs = np.asarray(sigma[1], dtype=np.float64)
    if covs.ndim != 3 or covs.shape[1:] != (dof, dof) or measured_t.shape != (len(covs),) or len(covs) == 0:
        raise ValueError(f"per-step sigma must be timesteps (M,) with covs (M, {dof}, {dof}), M >= 1; "
                         f"got timesteps {measured_t.shape} and covs {covs.shape}")
    return measured_t, covs


def _check_isotropic(sigma, s: np.ndarray, median_step) -> None:
    if not np.isfinite(s) or s < 0:
        raise ValueError(f"isotropic sigma must be a finite number >= 0 (in median steps), got {sigma!r}")
    if median_step is None or not np.isfinite(median_step) or median_step <= 0:
        raise ValueError(f"isotropic sigma needs a finite positive median_step (rad), got {median_step!r}")


def _check_demo_inputs(median_step: float, accel_percentile: float) -> None:
    if not np.isfinite(median_step) or median_step <= 0:
        raise ValueError(f"median_step must be a finite positive number (rad), got {median_step!r}")
    if not 0 < accel_percentile <= 100:
        raise ValueError(f"accel_percentile must be in (0, 100], got {accel_percentile!r}")


def _check_demo_motion(steps: list, accels: list) -> None:
    """demo_stats' data: at least one episode of >= 3 steps (accelerations), and at least one moving step."""
    if not accels:
        raise ValueError("demo_stats needs at least one episode with >= 3 steps to measure accelerations")
    if not np.any(np.linalg.norm(np.concatenate(steps), axis=1) > 0):
        raise ValueError("the demonstrations never move; no median speed can be measured")


def _check_has_labels(valid_t: np.ndarray, horizon: int, figure: bool = False) -> None:
    if valid_t.size == 0 and figure:
        raise ValueError(f"episode has no intervention of at least H={horizon} expert steps to draw")
    if valid_t.size == 0:
        raise ValueError(f"episode has no intervention step with a valid label (expert runs >= H={horizon})")


def _check_settle_steps(settle_steps: float) -> None:
    if not np.isfinite(settle_steps) or settle_steps <= 0:
        raise ValueError(f"settle_steps must be a positive number of steps, got {settle_steps!r}")


def _check_positive_count(m) -> None:
    if not isinstance(m, (int, np.integer)) or m < 1:
        raise ValueError(f"m must be a positive integer, got {m!r}")


def _check_count(n) -> None:
    if not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n must be an integer >= 0, got {n!r}")


def _check_t_index(t: np.ndarray, T: int) -> np.ndarray:
    if t.size and (t.min() < 0 or t.max() >= T):
        raise ValueError(f"t_index must be in [0, {T}), got range [{t.min()}, {t.max()}]")
    return t


def _check_aligned(s: np.ndarray, n_steps: int | None) -> None:
    if n_steps is not None and len(s) != n_steps:
        raise ValueError(f"per-step sigma of shape {s.shape} is not aligned with the episode's {n_steps} steps; "
                         "pass (timesteps, covs) to say which steps the covariances belong to")


def _projection_inputs(q, trajectory, t_start, window, t_end):
    """monotone_projection's inputs as checked arrays: (q (B, dof), trajectory (T, dof), t_start (B,),
    t_end (B,) default T, single: True if q was one state)."""
    trajectory = np.asarray(trajectory, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    single = q.ndim == 1
    q = np.atleast_2d(q)
    if trajectory.ndim != 2 or len(trajectory) == 0 or q.shape[1] != trajectory.shape[1]:
        raise ValueError(f"trajectory must be (T>=1, dof) matching q (B, dof); got {trajectory.shape} and {q.shape}")
    B, T = len(q), len(trajectory)
    t_start = np.broadcast_to(np.asarray(t_start, dtype=np.int64), (B,))
    t_end = np.broadcast_to(np.asarray(T if t_end is None else t_end, dtype=np.int64), (B,))
    if B and (np.any(t_end > T) or np.any(t_start < 0) or np.any(t_start >= t_end)):
        raise ValueError(f"need 0 <= t_start < t_end <= T={T}; got t_start in [{t_start.min()}, {t_start.max()}], "
                         f"t_end in [{t_end.min()}, {t_end.max()}]")
    if window is not None and window < 1:
        raise ValueError(f"window must be >= 1 or None, got {window}")
    return q, trajectory, t_start, t_end, single


# pd_return_chunk's closing-speed cap √(2 accel_max |e|): without it a saturated PD overshot the path by
# 25 % of the initial error, with it 8 % (tests/test_relabel.py checks < 12 %).
def _pd_inputs(accel_max, max_step, t_proj, lookahead, t_end, B: int, dof: int, T: int):
    """pd_return_chunk's clamps and indices, checked: (accel_max (dof,) rad/step², max_step (dof,) rad/step,
    start = t_proj + lookahead (B,), t_end (B,) default T)."""
    accel_max = np.broadcast_to(np.asarray(accel_max, dtype=np.float64), (dof,))
    max_step = np.broadcast_to(np.asarray(max_step, dtype=np.float64), (dof,))
    if np.any(~(accel_max > 0)) or np.any(~(max_step > 0)):
        raise ValueError(f"accel_max and max_step must be > 0 per joint, got {accel_max} and {max_step}")
    t_end = np.broadcast_to(np.asarray(T if t_end is None else t_end, dtype=np.int64), (B,))
    start = np.broadcast_to(np.asarray(t_proj, dtype=np.int64), (B,)) + np.broadcast_to(np.asarray(lookahead, dtype=np.int64), (B,))
    if B and (np.any(start < 0) or np.any(t_end > T) or np.any(t_end < 1)):
        raise ValueError(f"need t_proj + lookahead >= 0 and 1 <= t_end <= T={T}")
    return accel_max, max_step, start, t_end


def _check_servo_stats(median_step: float, acc_p95: float) -> None:
    if not (median_step > 0 and np.isfinite(acc_p95) and acc_p95 >= 0):
        raise ValueError(f"need median_step > 0 and acc_p95 >= 0, got {median_step!r} and {acc_p95!r}")


def _return_chunk_inputs(q0, v0, trajectory, H):
    """Checked float arrays for a batched return chunk: (trajectory (T, dof), q (B, dof) copy, v (B, dof) copy,
    single: True if q0 was one state)."""
    trajectory = np.asarray(trajectory, dtype=np.float64)
    q = np.asarray(q0, dtype=np.float64)
    single = q.ndim == 1
    q = np.atleast_2d(q).copy()
    B, dof = q.shape
    v = np.broadcast_to(np.asarray(v0, dtype=np.float64), (B, dof)).copy()
    if trajectory.ndim != 2 or trajectory.shape[1] != dof or len(trajectory) == 0:
        raise ValueError(f"trajectory must be (T>=1, {dof}), got {trajectory.shape}")
    if not isinstance(H, (int, np.integer)) or H < 1:
        raise ValueError(f"H must be a positive integer, got {H!r}")
    return trajectory, q, v, single


def _check_label(cfg: RelabelConfig) -> None:
    if cfg.label not in ("servo", "pd"):
        raise ValueError(f"RelabelConfig.label must be 'servo' or 'pd', got {cfg.label!r}")


def _check_sampler_config(noise: str, cfg: RelabelConfig) -> None:
    if noise not in NOISE_KINDS:
        raise ValueError(f"noise must be one of {NOISE_KINDS}, got {noise!r}")
    _check_label(cfg)
    if cfg.lookahead not in ("time_matched", "gap"):
        raise ValueError(f"RelabelConfig.lookahead must be 'time_matched' or 'gap', got {cfg.lookahead!r}")
    if cfg.refresh_size < 1 or cfg.pool_size < cfg.refresh_size or not cfg.reuse > 0:
        raise ValueError("need 1 <= refresh_size <= pool_size and reuse > 0, got refresh_size="
                         f"{cfg.refresh_size}, pool_size={cfg.pool_size}, reuse={cfg.reuse}")


def _episode_sigma(noise: str, sigma, e: int, dof: int):
    """The sigma of episode e for AugmentationSampler, checked against the noise kind."""
    if noise == "isotropic" and np.ndim(sigma) != 0:
        raise ValueError(f"noise='isotropic' needs a scalar sigma (median steps), got shape {np.shape(sigma)}")
    if noise == "pooled" and np.shape(sigma) != (dof, dof):
        raise ValueError(f"noise='pooled' needs sigma of shape ({dof}, {dof}), got {np.shape(sigma)}")
    if noise != "per_step":
        return sigma
    try:
        per_ep = sigma[e]
    except (KeyError, IndexError, TypeError):
        raise ValueError(f"noise='per_step': no covariances for episode {e}; pass a list aligned with "
                         "episodes or a dict {episode index: (timesteps, covs)}") from None
    if not isinstance(per_ep, tuple):
        raise ValueError(f"noise='per_step': sigma[{e}] must be a pair (timesteps, covs)")
    return per_ep


# ---- samplers of a fine-tuning batch's intervention rows (dagger.intervention_sampler) -------------

class ChunkSampler:
    """Intervention frames as recorded: (obs, expert chunk) at every valid label start (HG-DAgger's data);
    pad=True: at every intervention step, with the loss mask of the chunk's padded steps (chunk_dataset)."""

    def __init__(self, episodes, H, pad=False):
        data = chunk_dataset(episodes, H, pad)
        self.obs, self.chunks = data[:2]
        self.mask = data[2] if pad else None  # (N, H) bool, False on the padded steps

    def __call__(self, n, rng):
        pick = rng.integers(len(self.obs), size=n)
        if self.mask is None:
            return self.obs[pick], self.chunks[pick]
        return self.obs[pick], self.chunks[pick], self.mask[pick]


class MixtureSampler:
    """Rows from several rounds' samplers in fixed proportions (the authors: equal). Samplers may return
    (obs, chunks) or (obs, chunks, mask); the mixture returns a mask (all True where a sampler gave none)
    as soon as one of them does."""

    def __init__(self, samplers, weights):
        self.samplers = samplers
        self.p = np.asarray(weights, float) / np.sum(weights)

    def __call__(self, n, rng):
        counts = rng.multinomial(n, self.p)
        parts = [s(c, rng) for s, c in zip(self.samplers, counts) if c > 0]
        obs = np.concatenate([p[0] for p in parts])
        chunks = np.concatenate([p[1] for p in parts])
        if not any(len(p) == 3 for p in parts):
            return obs, chunks
        masks = [p[2] if len(p) == 3 else np.ones(p[1].shape[:2], bool) for p in parts]
        return obs, chunks, np.concatenate(masks)

    def state_dict(self):
        return {str(i): s.state_dict() for i, s in enumerate(self.samplers) if hasattr(s, "state_dict")}

    def load_state_dict(self, state):
        for i, s in enumerate(self.samplers):
            if hasattr(s, "load_state_dict") and str(i) in state:
                s.load_state_dict(state[str(i)])


if __name__ == "__main__":
    # Demo on the planar env: one stand-in "intervention" (a straight joint-space path from the
    # scenario's start toward its nearest goal configuration, stopped before the first collision;
    # dagger.py uses the RRT oracle's interventions instead), noised with an anisotropic Σ of
    # 3-5 median steps per joint (the paper's calibrated range), labelled, timed and drawn.
    import time

    import envs  # the demo only; the module itself never imports the env

    env = envs.make_env("planar")
    rng = np.random.default_rng(0)
    episodes = [ep for ep in (envs.straight_line_episode(env, s) for s in range(40)) if len(ep["q"]) >= 40]
    stats = demo_stats(episodes, envs.median_step(episodes), env.max_step,
                       paper_median_step=envs.paper_median_step(env), frames_per_step=env.dt / envs.PAPER_FRAME_DT)
    print(f"{len(episodes)} episodes; median step {stats.median_step:.4f} rad, median speed "
          f"{stats.median_speed:.4f} rad/step, accel clamp {np.round(stats.accel_max, 4)} rad/step²")
    sigma = np.diag([5.0, 3.0, 4.0]) ** 2 * stats.median_step ** 2  # a pooled Σ̄^α stand-in
    sampler = AugmentationSampler(episodes, lambda: envs.make_env("planar"), stats, "pooled", sigma)
    sampler(128, rng)  # fills the pool
    t0 = time.perf_counter()
    for _ in range(200):
        obs, chunks, mask = sampler(128, rng)
    print(f"sampler: obs {obs.shape} {obs.dtype}, chunks {chunks.shape} {chunks.dtype}, {mask.mean():.0%} of steps in the loss; "
          f"{(time.perf_counter() - t0) / 200 * 1e3:.2f} ms per call of 128 pairs; "
          f"{sampler.n_kept / sampler.n_drawn:.1%} of noised states collision-free")
    print("wrote", plot_recovery(env, episodes[0], sigma, "fig1_recovery_demo.png", rng, stats))
