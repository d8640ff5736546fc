"""Corrective labels around expert interventions: paper Sec. IV-E ("Generating Corrective Labels") and the
augmented data D̂_k of Sec. IV-A steps 3-4. Top to bottom:
  demo_stats           the demonstrations' statistics; their median step m (Sec. V) is the unit of noise
  perturb_states       Sec. IV-A step 3: q̃ ~ N(q_t, Σ) around the intervention states, Σ (`noise_factors`)
                       'isotropic' (σ m)² I (Table I's fixed rows), 'pooled' Σ̄^α (Eqs. (15)-(16)) or
                       'per_step' Σ^α_t (Eq. (14)), both measured by calibrate.py
  monotone_projection  Sec. IV-E: "a monotone closest-point projection"                         (exercise 8)
  pd_return_chunk      Sec. IV-E: "a critically-damped PD controller, with accelerations clamped" (exercise 9):
                       the return label of every profile
  corrective_labels    projection -> PD return chunk, for a batch of noised states
  AugmentationSampler  Sec. IV-A steps 3-4: (observation, chunk, mask) made on the fly for co-training;
                       ChunkSampler, MixtureSampler: a fine-tuning batch's intervention rows, round by round
  plot_recovery        Fig. 1

Units per control step: joints rad, velocities rad/step, accelerations rad/step²; noise levels in median steps m.
The env is used only through envs.py's interface; which steps teach is the label rule diffusion.label_mask
(matplotlib only inside `plot_recovery`). The authors' own return label, in their units, is a research variant in
experiment/, not part of this file.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, ClassVar, Sequence

import numpy as np

from diffusion import chunk_dataset, expert_runs, label_mask  # the paper's label rule, one place


@dataclass
class RelabelConfig:
    horizon: int  # steps: H, the length of a label chunk (the policy's action chunk; dagger passes it)
    label: ClassVar[str] = "pd"  # the return label, as logs and run records name it: `pd_return_chunk` (Sec. IV-E)
    settle_steps: float = 8.0  # steps: the PD's unclamped error settles to 2 % in this many (Sec. IV-E's PD)
    velocity_noise: float = 0.3  # the authors' median steps per 30 Hz frame: std of the velocity noise
    # the authors' redraws (benchmarks/SETUP.md §6: 8 of their 30 Hz frames ~ 3 of our 10 Hz steps; 6 redraws)
    near_end_steps: int = 3  # steps: a state projecting this near its segment's end is redrawn
    max_redraws: int = 6  # redraws, then the state is dropped
    # ours
    projection_window: int = 32  # steps the projection looks past t (2H of path >> Table I's 16 median steps)
    max_tries: int = 10  # rejection rounds for a noised state in collision / off limits, then it is dropped
    pool_size: int = 4096  # pairs: AugmentationSampler's pool
    refresh_size: int = 512  # pairs made per refresh, replacing the oldest
    reuse: float = 4.0  # times a pair is served on average (bench_relabel.py)
    episodes_per_refresh: int = 16  # episodes a refresh draws from, so env calls are batched per scenario


# ---- 1. Demonstration statistics (Sec. IV-E: "the demonstration dataset's velocity and acceleration statistics")

@dataclass(frozen=True)
class DemoStats:
    median_step: float  # rad: m, the median per-step joint displacement (envs.median_step); noise unit
    accel_max: np.ndarray  # (dof,) rad/step²: per-joint clamp on the PD's acceleration
    max_step: np.ndarray  # (dof,) rad/step: the env's speed limit, clamp on the velocity
    # the env's units, for knobs the authors set in theirs (`velocity_noise_std`); None: not known
    paper_median_step: float | None = None  # rad: the paper's median step of the env (envs.paper_median_step)
    frames_per_step: float | None = None  # the authors' 30 Hz frames per env step: env.dt / envs.PAPER_FRAME_DT


def demo_stats(episodes: Sequence[dict], median_step: float, max_step,
               paper_median_step: float | None = None, frames_per_step: float | None = None) -> DemoStats:
    """Statistics of the base demonstrations D0 that shape the labels. `median_step` is `envs.median_step`;
    `max_step` the env's per-step joint speed limit (scalar or (dof,)). The acceleration clamp is the 99th
    percentile of |q[t+1] - 2 q[t] + q[t-1]| per joint (not the max: one odd step does not set every clamp)."""
    qs = [np.asarray(ep["q"], dtype=np.float64) for ep in episodes]  # (T, dof) each
    accels = np.concatenate([np.abs(q[2:] - 2 * q[1:-1] + q[:-2]) for q in qs if len(q) >= 3])  # (sum T-2, dof)
    accel_max = np.percentile(accels, 99.0, axis=0)  # (dof,) rad/step²
    max_step = np.broadcast_to(np.asarray(max_step, dtype=np.float64), accel_max.shape).copy()
    return DemoStats(float(median_step), accel_max, max_step,
                     None if paper_median_step is None else float(paper_median_step),
                     None if frames_per_step is None else float(frames_per_step))


# ---- 2. Noised states around the intervention data (Sec. IV-A step 3; Σ^α from calibrate.py)

def noise_factors(sigma, steps: np.ndarray, dof: int, median_step: float | None = None) -> np.ndarray:
    """Noise factors L_t (len(steps), dof, dof), L Lᵀ = Σ_t, at the timesteps `steps` of one episode. The
    form of `sigma` says the noise model:
      - isotropic: a scalar σ >= 0 in median steps -> Σ = (σ · median_step)² I  (needs median_step, rad)
      - pooled:    an array (dof, dof), rad²       -> Σ̄^α at every step                       (Eqs. (15)-(16))
      - per_step:  a pair (timesteps (M,), covs (M, dof, dof)) -> Σ^α_t of the nearest measured timestep,
                   ties to the earlier (calibrate.py measures every other step)               (Eq. (14))
    """
    steps = np.asarray(steps, dtype=np.int64)
    if isinstance(sigma, tuple):  # per_step
        measured_t, covs = np.asarray(sigma[0], dtype=np.int64), np.asarray(sigma[1], dtype=np.float64)
        order = np.argsort(measured_t, kind="stable")
        measured_t, covs = measured_t[order], covs[order]
        right = np.clip(np.searchsorted(measured_t, steps), 0, len(measured_t) - 1)
        left = np.clip(right - 1, 0, len(measured_t) - 1)
        nearest = np.where(np.abs(measured_t[left] - steps) <= np.abs(measured_t[right] - steps), left, right)
        return covariance_factor(covs)[nearest]
    s = np.asarray(sigma, dtype=np.float64)
    if s.ndim == 0:  # isotropic baseline: L = σ m I
        return np.broadcast_to(float(s) * median_step * np.eye(dof), (len(steps), dof, dof))
    assert s.shape == (dof, dof), f"pooled sigma: ({dof}, {dof}), not {s.shape}"
    return np.broadcast_to(covariance_factor(s), (len(steps), dof, dof))


def covariance_factor(cov: np.ndarray) -> np.ndarray:
    """L with L Lᵀ = Σ for covariances (..., dof, dof): an eigendecomposition, not a Cholesky, since Σ̂ from a
    handful of policy samples is often (near-)singular. Eigenvalues negative only by round-off are set to 0."""
    cov = np.asarray(cov, dtype=np.float64)
    w, v = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    return v * np.sqrt(np.clip(w, 0.0, None))[..., None, :]  # (..., dof, dof): columns scaled


def perturb_states(q_t: np.ndarray, factors: np.ndarray, rng: np.random.Generator, env,
                   max_tries: int = RelabelConfig.max_tries) -> tuple[np.ndarray, np.ndarray]:
    """Sec. IV-A step 3: noised states q̃ ~ N(q_t, Σ_t) around intervention states q_t (m, dof), drawn as
    q̃ = q_t + L_t z, z ~ N(0, I), with the factors L_t (m, dof, dof) of `noise_factors`. Rows in collision
    or off the joint limits of `env` (reset to the states' scenario) are redrawn up to `max_tries` rounds:
    rejecting, not clipping, keeps the states Gaussian-shaped instead of piling mass onto the limit.
    Returns (q̃ (m, dof), kept (m,) bool); a row not kept after `max_tries` rounds is to be dropped."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in env.joint_limits)
    q = q_t.copy()
    kept = np.zeros(len(q_t), dtype=bool)
    todo = np.arange(len(q_t))
    for _ in range(max_tries):
        if todo.size == 0:
            break
        z = rng.standard_normal((todo.size, q_t.shape[1]))
        cand = q_t[todo] + np.einsum("mij,mj->mi", factors[todo], z)  # (m, dof)
        ok = np.all((cand >= lo) & (cand <= hi), axis=-1)  # inside the joint limits
        if ok.any():
            ok[ok] = ~np.asarray(env.in_collision(cand[ok]), dtype=bool)
        q[todo[ok]] = cand[ok]
        kept[todo[ok]] = True
        todo = todo[~ok]
    return q, kept


# ---- 3. Monotone closest-point projection (Sec. IV-E)

def monotone_projection(q: np.ndarray, trajectory: np.ndarray, t_start, window: int | None = None, t_end=None):
    """Index of the trajectory point closest to q among t_start <= t < min(t_start + window, t_end) (Sec. IV-E).
    "Monotone": never before t_start, so a noised copy of the state at step t maps to step t or later even where
    an earlier point is closer (a label never goes back in time); ties go to the earliest index.
    q: (B, dof) or (dof,); trajectory (T, dof); t_start, t_end: int or (B,) (t_end exclusive, default T);
    window: steps, None = no bound. Returns (B,) int64 (or an int for a single q)."""
    trajectory = np.asarray(trajectory, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    single = q.ndim == 1
    q = np.atleast_2d(q)  # (B, dof)
    B, T = len(q), len(trajectory)
    t_start = np.broadcast_to(np.asarray(t_start, dtype=np.int64), (B,))
    t_end = np.broadcast_to(np.asarray(T if t_end is None else t_end, dtype=np.int64), (B,))
    if B and (np.any(t_end > T) or np.any(t_start < 0) or np.any(t_start >= t_end)):
        raise ValueError(f"need 0 <= t_start < t_end <= T={T}; got t_start in [{t_start.min()}, {t_start.max()}], "
                         f"t_end in [{t_end.min()}, {t_end.max()}]")
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


# ---- 4. The return chunk: the paper's critically damped PD (every profile's label)

def critically_damped_gains(settle_steps: float) -> tuple[float, float]:
    """(Kp, Kd) per step for a critically damped PD on the discrete double integrator v ← v + a, q ← q + v
    (dt = 1). In continuous time Kd = 2 √Kp gives the double pole -ω, and e(t) = (1 + ωt) e0 e^{-ωt} falls
    below 2 % at ωt ≈ 5.83; at dt = 1 an Euler step of those gains overshoots, so the discrete double pole
    is placed at p = e^{-ω}: the error map [[1-Kp, 1-Kd], [-Kp, 1-Kd]] has trace 2 - Kp - Kd = 2p and
    determinant 1 - Kd = p², i.e. Kp = (1-p)², Kd = 1 - p² (-> Kd = 2 √Kp as ω -> 0)."""
    if not np.isfinite(settle_steps) or settle_steps <= 0:
        raise ValueError(f"settle_steps must be a positive number of steps, got {settle_steps!r}")
    # >>> exercise 9: the critically damped PD return chunk, accelerations clamped (Sec. IV-E)
    p = np.exp(-5.83 / settle_steps)  # 5.83: (1 + x) e^{-x} = 0.02 at x = 5.83 (2 % settling)
    return float((1 - p) ** 2), float(1 - p ** 2)
    # <<< exercise 9


def pd_return_chunk(q0: np.ndarray, v0: np.ndarray, trajectory: np.ndarray, t_proj, H: int, lookahead,
                    accel_max, max_step, settle_steps: float | None = None, t_end=None, limits=None,
                    t_start=None) -> np.ndarray:
    """Roll out a critically damped PD controller from (q0, v0) back onto the expert trajectory (Sec. IV-E).

    The reference r_k = trajectory[t_proj + lookahead + k], held at the segment's last point (t_end - 1): the
    chunk REJOINS the trajectory, then follows it. With e_k = q_k - r_k and u_k = r_k - r_{k-1}, PD plus the
    reference's acceleration as feed-forward,
        a_k = -Kp e_k - Kd (v_k - u_k) + (u_{k+1} - u_k),
    makes e obey the map of `critically_damped_gains` (settling in ~settle_steps, default H/2) while
    |a| <= accel_max and |v| <= max_step are inactive. In cascade form the closing speed w* = -(Kp/Kd) e is capped at
    √(2 accel_max |e|), so the clamped deceleration can still stop at the path without overshooting.
    Sec. IV-E's "a few timesteps further" is lookahead 0 here: the feed-forward removes the lag.

    q0, v0: (B, dof) or (dof,) rad, rad/step; trajectory (T, dof); t_proj, lookahead, t_end: int or (B,) steps;
    t_start: int or (B,), the episode's first step in `trajectory` (episodes laid end to end: the reference never
    reaches before it, so at an episode's first step r_-1 = r_0, the arm at rest; default 0);
    limits: optional (lo, hi). Returns the joint targets q_1 .. q_H: (B, H, dof) (or (H, dof) for a single q0).
    """
    trajectory = np.asarray(trajectory, dtype=np.float64)
    q = np.asarray(q0, dtype=np.float64)
    single = q.ndim == 1
    q = np.atleast_2d(q).copy()
    B, dof = q.shape
    v = np.broadcast_to(np.asarray(v0, dtype=np.float64), (B, dof)).copy()
    accel_max = np.broadcast_to(np.asarray(accel_max, dtype=np.float64), (dof,))
    max_step = np.broadcast_to(np.asarray(max_step, dtype=np.float64), (dof,))
    if np.any(~(accel_max > 0)) or np.any(~(max_step > 0)):
        raise ValueError(f"accel_max and max_step must be > 0 per joint, got {accel_max} and {max_step}")
    T = len(trajectory)
    t_end = np.broadcast_to(np.asarray(T if t_end is None else t_end, dtype=np.int64), (B,))
    start = (np.broadcast_to(np.asarray(t_proj, dtype=np.int64), (B,))
             + np.broadcast_to(np.asarray(lookahead, dtype=np.int64), (B,)))
    if B and (np.any(start < 0) or np.any(t_end > T) or np.any(t_end < 1)):
        raise ValueError(f"need t_proj + lookahead >= 0 and 1 <= t_end <= T={T}")
    # >>> exercise 9: the critically damped PD return chunk, accelerations clamped (Sec. IV-E)
    kp, kd = critically_damped_gains(H / 2 if settle_steps is None else settle_steps)
    # reference r_{-1} .. r_H, held at the segment's last point
    idx = np.minimum(start[:, None] + np.arange(-1, H + 1)[None, :], t_end[:, None] - 1)  # (B, H+2)
    first = np.broadcast_to(np.asarray(0 if t_start is None else t_start, dtype=np.int64), (B,))
    idx = np.maximum(idx, first[:, None])  # never before the episode's first step
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
                      stats: DemoStats, cfg: RelabelConfig, limits=None, t_proj=None, t_start=None) -> np.ndarray:
    """Sec. IV-E for noised states q̃ (m, dof) with velocities v (m, dof) from steps t (m,): the monotone
    projection (or `t_proj` given), then the critically damped PD return chunk from there (lookahead 0), its
    accelerations clamped to the demonstrations' (stats.accel_max). t_end (m,): the exclusive end of each state's
    expert segment; t_start (m,): its episode's first step in `trajectory` (the PD reference's floor; default 0).
    Returns the chunks (m, H, dof) of joint targets."""
    if t_proj is None:
        t_proj = monotone_projection(q_tilde, trajectory, t, window=cfg.projection_window, t_end=t_end)
    return pd_return_chunk(q_tilde, v, trajectory, t_proj, cfg.horizon, 0, stats.accel_max, stats.max_step,
                           settle_steps=cfg.settle_steps, t_end=t_end, limits=limits, t_start=t_start)


# ---- 5. On-the-fly augmentation for co-training (Sec. IV-A steps 3-4)

def velocity_noise_std(cfg: RelabelConfig, stats: DemoStats) -> float:
    """rad per env step: the std of the per-joint velocity noise, the authors' N(0, (0.3 m_p)²) per 30 Hz frame
    (m_p their median step; benchmarks/SETUP.md §6) over frames_per_step frames. Without the env's units:
    velocity_noise · m."""
    if stats.paper_median_step is None or stats.frames_per_step is None:
        return cfg.velocity_noise * stats.median_step
    return cfg.velocity_noise * stats.paper_median_step * stats.frames_per_step


def paper_label_steps(expert: np.ndarray, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """The paper's label rule (diffusion.label_mask, expert_runs): the steps t (n,) whose chunk is a label, and
    seg_end (n,), the end (exclusive) of t's expert run."""
    seg_end = np.zeros(len(expert), dtype=np.int64)
    for start, end in expert_runs(expert, horizon):
        seg_end[start:end] = end
    t = np.flatnonzero(label_mask(expert, horizon))
    return t, seg_end[t]


class AugmentationSampler:
    """sampler(n, rng) -> (obs (n, obs_dim) float32, chunks (n, H, dof) float32, mask (n, H) bool): noised
    intervention states with corrective labels, the D̂_1 ∪ ... ∪ D̂_k of Sec. IV-A, made on the fly.

    A pair (benchmarks/SETUP.md §6): (episode, t) uniform over labelable steps; q̃ ~ N(q_t, Σ_t), collision-free;
    v = (q_t - q_{t-1}) + N(0, `velocity_noise_std`²); obs = env.make_obs_near(q̃, q̃ - v, recorded obs); chunk,
    mask = `return_chunks` (the PD's `corrective_labels`, every step in the loss). Pairs go in batches into a pool
    each call draws from (randomness: the call's rng).
    noise: 'isotropic', 'pooled' or 'per_step'; sigma: as in `noise_factors`, for 'per_step' a list or dict
    {episode index: pair}. make_env: an env factory. label_steps(expert, H): the steps states are drawn at (the
    paper's rule by default; a variant hands in its own)."""

    def __init__(self, episodes: Sequence[dict], make_env: Callable[[], object], stats: DemoStats,
                 noise: str, sigma, cfg: RelabelConfig, label_steps: Callable = None):
        self.cfg, self.noise, self.stats, self._make_env, self._envs = cfg, noise, stats, make_env, {}
        # one flat table of every labelable step, the episodes concatenated: projection and labels run once a batch
        arrays = [(np.asarray(ep["q"], dtype=np.float64), np.asarray(ep["expert"], dtype=bool)) for ep in episodes]
        steps = [(label_steps or paper_label_steps)(expert, cfg.horizon) for _, expert in arrays]  # (t, seg_end) each
        labelled = [e for e, (t, _) in enumerate(steps) if t.size]
        self._episode_obs = [ep["obs"] for ep in episodes]  # recorded observations (references, no copy)
        first = np.cumsum([0] + [len(q) for q, _ in arrays])  # each episode's first row in self.trajectory
        self.trajectory = np.concatenate([q for q, _ in arrays])  # (sum T, dof) the episodes' joints in turn
        self.episode_of = np.concatenate([np.full(steps[e][0].size, e) for e in labelled])  # (N,) episode ...
        self.step_of = np.concatenate([steps[e][0] for e in labelled])  # (N,) ... and step t
        self.start_glob = first[self.episode_of]  # (N,) index of the episode's first step in self.trajectory
        self.t_glob = self.start_glob + self.step_of  # (N,) index of q_t in self.trajectory
        self.end_glob = first[self.episode_of] + np.concatenate([steps[e][1] for e in labelled])  # (N,) its run's end
        self.center = self.trajectory[self.t_glob]  # (N, dof) q_t
        t_prev = np.where(self.step_of > 0, self.t_glob - 1, self.t_glob)  # at t = 0 the arm starts at rest
        self.velocity = self.center - self.trajectory[t_prev]  # (N, dof) q_t - q_{t-1}
        self.seeds = np.array([int(ep["seed"]) for ep in episodes])[self.episode_of]  # (N,) scenario seed
        dof = self.trajectory.shape[1]
        factors = [noise_factors(self._episode_sigma(sigma, e), steps[e][0], dof, median_step=stats.median_step)
                   for e in labelled]
        self.factors = np.concatenate(factors)  # (N, dof, dof) L_t, L Lᵀ = Σ_t
        # the contiguous block of rows of each episode, for the "episodes first" draw
        self._ep_ids, self._ep_start, self._ep_count = np.unique(self.episode_of, return_index=True, return_counts=True)
        self._pool_obs = self._pool_chunks = self._pool_mask = None
        self._filled = self._write = self._served = 0  # pool fill, ring position, served since refresh
        self.n_drawn = self.n_kept = 0  # acceptance bookkeeping (collision / limit rejections)

    def _episode_sigma(self, sigma, e: int):
        """Episode e's sigma: per_step's pair sigma[e]; the same sigma for every episode otherwise."""
        return sigma[e] if self.noise == "per_step" else sigma

    def __call__(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """n pairs from the pool (diffusion.train's sampler hook). The first call fills the pool; afterwards
        the oldest `refresh_size` pairs are replaced every `reuse * refresh_size` pairs served."""
        cfg = self.cfg
        if self._filled == 0:  # the first call: a bounded number of refreshes
            for _ in range(4 * cfg.pool_size // cfg.refresh_size):
                self._refresh_pool(rng)
                if self._filled >= cfg.pool_size:
                    break
            if self._filled == 0:
                raise ValueError(f"every perturbed state was in collision or off the joint limits after "
                                 f"{cfg.max_tries} tries, or too near its segment's end after {cfg.max_redraws} "
                                 f"redraws; the noise ({self.noise}) is too large for these scenarios")
        elif self._served >= cfg.reuse * cfg.refresh_size:
            self._refresh_pool(rng)
            self._served = 0
        self._served += n
        pick = rng.integers(self._filled, size=n)
        return self._pool_obs[pick], self._pool_chunks[pick], self._pool_mask[pick]

    def _refresh_pool(self, rng: np.random.Generator) -> None:
        """Replace the `refresh_size` oldest pairs of the pool (a ring buffer) by fresh ones."""
        obs, chunks, mask = self.generate(self.cfg.refresh_size, rng)
        P = self.cfg.pool_size
        if len(obs) == 0:
            return
        if self._pool_obs is None:
            self._pool_obs = np.empty((P, obs.shape[1]), np.float32)
            self._pool_chunks = np.empty((P, *chunks.shape[1:]), np.float32)
            self._pool_mask = np.empty((P, chunks.shape[1]), bool)
        slots = (self._write + np.arange(len(obs))) % P
        self._pool_obs[slots], self._pool_chunks[slots], self._pool_mask[slots] = obs, chunks, mask
        self._write = int((self._write + len(obs)) % P)
        self._filled = min(P, self._filled + len(obs))

    def generate(self, m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """m fresh pairs (fewer if states were dropped): obs (m', obs_dim) float32, chunks (m', H, dof)
        float32, mask (m', H) bool. Rows `_label_rows` rejects are redrawn up to `max_redraws` times."""
        rows = self._draw_rows(m, rng)  # (m,) rows of the table, uniform over the labelable steps
        self.n_drawn += m
        limits = self._env(int(self.seeds[rows[0]])).joint_limits
        parts = []
        for _ in range(self.cfg.max_redraws + 1):
            if rows.size == 0:
                break
            part, rows = self._label_rows(rows, rng, limits)
            parts.append(part)
        r, q_tilde, v, chunks, mask = (np.concatenate(x) for x in zip(*parts))
        self.n_kept += r.size
        if r.size == 0:
            H, dof = self.cfg.horizon, self.center.shape[1]
            return np.empty((0, 0), np.float32), np.empty((0, H, dof), np.float32), np.empty((0, H), bool)
        return self._observe(r, q_tilde, v), chunks.astype(np.float32), mask

    def _draw_rows(self, m: int, rng: np.random.Generator) -> np.ndarray:
        """m table rows, uniform over the labelable steps, drawn episodes first: k episodes with probability
        proportional to their labelable steps, then steps within them, so that a batch touches at most
        k = episodes_per_refresh scenarios (env calls are batched per scenario)."""
        k = min(self.cfg.episodes_per_refresh, m)
        draws = rng.choice(len(self._ep_ids), size=k, p=self._ep_count / self._ep_count.sum())
        per_draw = np.full(k, m // k)
        per_draw[: m % k] += 1
        return np.concatenate([self._ep_start[d] + rng.integers(self._ep_count[d], size=c)
                               for d, c in zip(draws, per_draw)])

    def _label_rows(self, rows: np.ndarray, rng: np.random.Generator, limits):
        """One pass over table rows (m,): (r, q̃, v, chunks, mask) of the pairs made, and the rows to redraw
        (projecting within `near_end_steps` of the segment's end, or a label with no step in the loss). States in
        collision / off limits after `max_tries` draws are dropped."""
        cfg, dof = self.cfg, self.center.shape[1]
        q_tilde, kept = np.empty((len(rows), dof)), np.zeros(len(rows), dtype=bool)
        for seed in np.unique(self.seeds[rows]):  # q̃ ~ N(q_t, Σ_t): one batched collision check per scenario
            sel = self.seeds[rows] == seed
            q_tilde[sel], kept[sel] = perturb_states(self.center[rows[sel]], self.factors[rows[sel]], rng,
                                                     self._env(int(seed)), cfg.max_tries)
        r, q_tilde = rows[kept], q_tilde[kept]  # states still invalid after max_tries are dropped
        # velocity = demo tangent + N(0, (0.3 of the paper's median step per frame)²) per joint
        v = self.velocity[r] + velocity_noise_std(cfg, self.stats) * rng.standard_normal(q_tilde.shape)
        t_proj = monotone_projection(q_tilde, self.trajectory, self.t_glob[r], window=cfg.projection_window,
                                     t_end=self.end_glob[r])
        ok = t_proj < self.end_glob[r] - cfg.near_end_steps  # not within near_end_steps of the end
        chunks, mask = self.return_chunks(r[ok], q_tilde[ok], v[ok], t_proj[ok], limits)
        taught = mask.any(axis=1)  # a label with no step in the loss teaches nothing: redrawn
        ok[ok] = taught
        return (r[ok], q_tilde[ok], v[ok], chunks[taught], mask[taught]), r[~ok]

    def return_chunks(self, rows: np.ndarray, q_tilde: np.ndarray, v: np.ndarray, t_proj: np.ndarray, limits):
        """The labels of noised states q̃ (m, dof) with velocities v (m, dof) drawn at table rows `rows` (m,),
        projected to t_proj (m,): (chunks (m, H, dof), mask (m, H) bool, True = in the loss). Sec. IV-E's PD,
        `corrective_labels`: every step of its chunk is in the loss."""
        chunks = corrective_labels(q_tilde, v, self.trajectory, self.t_glob[rows], self.end_glob[rows], self.stats,
                                   self.cfg, limits=limits, t_proj=t_proj, t_start=self.start_glob[rows])
        return chunks, np.ones(chunks.shape[:2], dtype=bool)

    def _observe(self, rows: np.ndarray, q_tilde: np.ndarray, v: np.ndarray) -> np.ndarray:
        """obs (m, obs_dim) float32 of noised states, one batched env call per scenario: the previous frame
        is q̃ - v; env.make_obs_near recomputes what depends on q̃ (an image env keeps the recorded image)."""
        obs = None
        for seed in np.unique(self.seeds[rows]):
            sel = self.seeds[rows] == seed
            env, r = self._env(int(seed)), rows[sel]
            recorded = np.stack([self._episode_obs[e][t] for e, t in zip(self.episode_of[r], self.step_of[r])])
            part = np.asarray(env.make_obs_near(q_tilde[sel], q_tilde[sel] - v[sel], recorded), dtype=np.float32)
            if obs is None:
                obs = np.empty((len(rows), part.shape[1]), np.float32)
            obs[sel] = part
        return obs

    def _env(self, seed: int):
        """The env of a scenario seed, made by `make_env` and reset once, then reused."""
        if seed not in self._envs:
            env = self._make_env()
            env.reset(seed=seed)
            self._envs[seed] = env
        return self._envs[seed]


class ChunkSampler:
    """Intervention frames as recorded: (obs, expert chunk) at every valid label start (HG-DAgger's data)."""

    def __init__(self, episodes, H):
        self.obs, self.chunks = chunk_dataset(episodes, H)

    def __call__(self, n, rng):
        pick = rng.integers(len(self.obs), size=n)
        return self.obs[pick], self.chunks[pick]


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


# ---- 6. Fig. 1: expert trajectory, policy-calibrated noise ellipses, sampled recovery trajectories

def plot_recovery(env, episode: dict, sigma, path: str, rng: np.random.Generator, stats: DemoStats,
                  cfg: RelabelConfig, n_recoveries: int = 6, n_ellipses: int = 6) -> str:
    """The paper's Fig. 1: the expert (intervention) end-effector path in blue, 2σ ellipses of the
    policy-calibrated noise pushed through the end-effector Jacobian (J Σ_t Jᵀ), and sampled recovery
    trajectories (end-effector paths of the labels `cfg` makes from noised states) in orange; left the
    scene, right a close-up of a fan of returns from one state. A 3-D env (env.dim == 3) is drawn in its
    top view (x, y in m). sigma as in `noise_factors`. Saves a PNG to `path` and returns it."""
    import matplotlib
    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    q, expert = np.asarray(episode["q"], dtype=np.float64), np.asarray(episode["expert"], dtype=bool)
    _, end = expert_runs(expert, cfg.horizon)[0]  # the first intervention segment [start, end) ...
    seg = np.flatnonzero(label_mask(expert, cfg.horizon)[:end])  # ... and its labelable steps
    env.reset(seed=int(episode["seed"]))
    xy = lambda qs: env.ee(qs)[:, :2]  # (B, 2) end effector in the drawn plane (x, y)

    def cov_at(ts):  # (n, dof, dof): the joint covariances Σ_t = L_t L_tᵀ at steps ts
        f = noise_factors(sigma, ts, q.shape[1], median_step=stats.median_step)
        return f @ np.swapaxes(f, 1, 2)

    ell_t = seg[np.linspace(0, len(seg) - 1, min(n_ellipses, len(seg))).round().astype(int)]  # a handful
    # recovery trajectories from noised states at evenly spread steps of the segment, and a fan of them
    # from one state in the middle (the close-up)
    mid = int(seg[len(seg) // 2])
    steps = np.concatenate([seg[np.linspace(0, len(seg) - 1, n_recoveries).round().astype(int)],
                            np.full(n_recoveries, mid)])  # (2 n,)
    factors = noise_factors(sigma, steps, q.shape[1], median_step=stats.median_step)
    q_tilde, kept = perturb_states(q[steps], factors, rng, env, cfg.max_tries)
    q_tilde, t = q_tilde[kept], steps[kept]
    v = q[t] - q[np.maximum(t - 1, 0)]
    chunks = corrective_labels(q_tilde, v, q, t, np.full(len(t), end), stats, cfg, limits=env.joint_limits)
    recoveries = [xy(np.concatenate([qt[None], ch])) for qt, ch in zip(q_tilde, chunks)]  # (H+1, 2) each

    env.set_state(q[seg[0]])  # the arm is drawn where the intervention starts
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.5))
    top_view = env.dim == 3
    for ax in axes:
        if top_view:  # the goal and the arm's base as markers (render would show a camera image)
            ax.plot(*env.goal[:2], "*", color="tab:green", ms=14, zorder=3)
            ax.plot(*env.fk(q[:1])[0, 0, :2], "s", color="k", ms=6)
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
        else:  # the scene and the arm, faded: the path, noise and returns are the message
            env.render(ax, alpha=0.35)
        env.draw_noise_ellipses(ax, q[ell_t], cov_at(ell_t), "tab:blue", alpha=0.2)
        for rec in recoveries:
            ax.plot(rec[:, 0], rec[:, 1], color="tab:orange", lw=1.3)
            ax.plot(rec[0, 0], rec[0, 1], "o", color="tab:orange", ms=3)
        ax.plot(*xy(q[seg[0]:end]).T, color="tab:blue", lw=2.0)
        ax.set_aspect("equal")
    # close-up: the fan of returns from the middle state and its ellipse, the path a chunk either side of it in
    # view, with a margin of the ellipse's 2σ radius (m) cut at the frame (a briefly trained policy's is wide)
    cov_mid = cov_at(np.array([mid]))
    env.draw_noise_ellipses(axes[1], q[mid:mid + 1], cov_mid, "tab:blue", alpha=0.2)
    fan = [rec for rec, ti in zip(recoveries, t) if ti == mid]
    pts = np.concatenate([xy(q[max(mid - cfg.horizon // 2, seg[0]):min(mid + cfg.horizon + 1, end)]), *fan])
    jac = env.ee_jacobian(q[mid:mid + 1])[0, :2]  # (2, dof)
    radius = 2 * np.sqrt(max(np.linalg.eigvalsh(jac @ cov_mid[0] @ jac.T).max(), 0))  # 2σ, m
    span = float(np.max(pts.max(axis=0) - pts.min(axis=0)))
    env.square_view(axes[1], pts, min(radius, max(span, 0.05)))
    handles = [Line2D([], [], color="tab:blue", lw=2, label="expert intervention (end effector)"),
               Patch(facecolor="tab:blue", alpha=0.2, label="policy-calibrated noise (2σ)"),
               Line2D([], [], color="tab:orange", label="sampled recovery trajectories")]
    if top_view:  # the scene around the path, the goal and the base (a planar env's render sets its own window)
        scene = np.concatenate([xy(q[seg[0]:end]), env.goal[None, :2], env.fk(q[:1])[0, :1, :2]])
        env.square_view(axes[0], scene, 0.05)
        handles += [Line2D([], [], marker="*", color="tab:green", ls="", ms=10, label="goal"),
                    Line2D([], [], marker="s", color="k", ls="", ms=6, label="arm base")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)  # below the panels
    axes[0].set_title("scene (top view)" if top_view else "scene")
    axes[1].set_title("close-up (top view)" if top_view else "close-up")
    fig.suptitle("Policy-calibrated noise around an intervention and the return labels (paper Fig. 1)")
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


if __name__ == "__main__":
    # Demo on the planar env: the RRT oracle's demonstrations as stand-in interventions, noised with a pooled Σ
    # of 3-5 median steps per joint (the paper's calibrated range), labelled and drawn. Timings: bench_relabel.py.
    import envs  # the demo only; the module itself never imports the env or the oracle
    import oracle

    env = envs.make_env("planar")
    rng = np.random.default_rng(0)
    cfg = RelabelConfig(horizon=16)
    episodes = [oracle.Oracle().demonstrate(env, s) for s in env.train_seeds(12)]
    stats = demo_stats(episodes, envs.median_step(episodes), env.max_step,
                       paper_median_step=env.paper_median_step, frames_per_step=env.dt / envs.PAPER_FRAME_DT)
    sigma = np.diag([5.0, 3.0, 4.0]) ** 2 * stats.median_step ** 2  # a pooled Σ̄^α stand-in
    sampler = AugmentationSampler(episodes, lambda: envs.make_env("planar"), stats, "pooled", sigma, cfg)
    obs, chunks, mask = sampler(128, rng)
    print(f"{len(episodes)} episodes, median step {stats.median_step:.4f} rad; obs {obs.shape}, chunks {chunks.shape}, "
          f"{mask.mean():.0%} of steps in the loss, {sampler.n_kept / sampler.n_drawn:.1%} of noised states kept")
    print("wrote", plot_recovery(env, episodes[0], sigma, "fig1_recovery_demo.png", rng, stats, cfg))
