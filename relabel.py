"""Corrective labels around expert interventions (paper Sec. IV-E, "Generating Corrective Labels").

Policy-Calibrated DAgger noises the states of the expert intervention data D_k and labels each
noised state with an action chunk that returns to the expert trajectory (Sec. IV-A, steps 3-4).
This file implements that augmentation, top to bottom:

1. demonstration statistics: the median step (the unit of every noise level), the median speed and
   the acceleration clamp "seen in the demonstrations" (Sec. IV-E);
2. `perturb_states`: joint states drawn from N(q_t, Σ) around intervention states, with Σ one of
   - 'isotropic'  (σ · median_step)² I   -- the fixed-noise baselines of Table I,
   - 'pooled'     Σ̄^α                     -- Eqs. (15)-(16), computed in calibrate.py,
   - 'per_step'   Σ^α_t                    -- Eq. (14) per measured timestep, from calibrate.py,
   rejecting states in collision or outside the joint limits;
3. `monotone_projection`: the closest point of the expert trajectory, never earlier in time;
4. the return chunk of H absolute joint targets that rejoins the trajectory, then follows it:
   `servo_return_chunk` (default): the authors' critically damped servo at its own monotone cursor
   (PAPER_SETUP.md §6), with a mask that drops the held tail at the segment's end from the loss;
   `pd_return_chunk` (RelabelConfig.label='pd'): a critically damped PD with velocity feed-forward
   toward a reference advancing from the projection (see `lookahead_steps` for the paper's
   "a state a few timesteps further");
5. `AugmentationSampler`: (observation, chunk, mask) training triples generated on the fly for co-training
   (diffusion.train's `sampler` hook), kept in a pool that is partly regenerated every few calls;
6. `plot_recovery`: the paper's Fig. 1 on the planar env.

Units: everything is per control step. Velocities are rad/step, accelerations rad/step², so the
env's `max_step` is directly the velocity clamp and no dt appears anywhere.

The small Gaussian observation noise that leaves labels unchanged (Sec. V, last paragraph) is NOT
here: it applies to every training batch of every method (augmented or not), so it lives in one
place, the training loop: `diffusion.TrainConfig.obs_noise`.

The env is used only through the duck-typed interface of CONTRACT.md, passed in as an argument:
`in_collision`, `make_obs`, `joint_limits`, `max_step`, `reset(seed=...)`, and for the figure
`ee` and `render`. This module imports numpy only (matplotlib lazily, inside `plot_recovery`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from diffusion import expert_runs, label_mask  # the paper's label rule, one place


@dataclass
class RelabelConfig:
    horizon: int = 16  # H: length of a label chunk (CONTRACT default, same as the policy's)
    projection_window: int = 32  # the projection looks at most this many steps ahead of t; bounded
    #   so that a trajectory that later passes near the same configuration (untangling manoeuvres)
    #   cannot pull the projection far into the future. At the demos' typical speed 2H steps of path
    #   are far longer than the largest noise of Table I (16 median steps per joint).
    lookahead: str = "time_matched"  # where the PD aims at chunk step k (see `lookahead_steps`):
    #   'time_matched': trajectory[t_proj + k], the lag-free form of the paper's "state a few
    #   timesteps further"; 'gap': L = ceil(gap / median speed) steps further still, the literal
    #   reading -- measured worse on oracle demos (benchmarks/bench_relabel.py, label quality)
    max_lookahead: int = 8  # cap on L for lookahead='gap' (H/2)
    settle_steps: float = 8.0  # the PD gains make the unclamped error settle (to 2 %) in this many
    #   steps: H/2, so the second half of every chunk follows the expert trajectory.
    max_tries: int = 10  # rejection rounds for a perturbed state before it is dropped
    # --- the authors' relabeling (PAPER_SETUP.md §6), their 30 Hz frames converted to our 10 Hz steps.
    #   Their median step m' (per 1/30 s frame) is 1/3 of ours m (per 0.1 s step): same joint speed.
    label: str = "servo"  # 'servo': `servo_return_chunk` (the authors' label); 'pd': `pd_return_chunk`
    velocity_noise: float = 0.3  # σ_v of the noised velocity, in median steps per step: theirs is
    #   0.3 m' per frame, a speed relative to the median speed, so unit-free: stays 0.3
    a_clamp_scale: float = 0.9  # a_clamp = 0.9 · max(2√dof · acc_p95, accel_floor · m): unit-free factor
    accel_floor: float = 0.6  # a_clamp floor in m per step²: theirs 0.2 m' per frame²
    #   = 0.2 · (m/3) / (1/3 step)² = 0.2 · 3 = 0.6 m per step²
    gain_floor: float = 4.0 / 3.0  # Kp = a_clamp / max(d0, gain_floor · m): theirs 4 m' = 4/3 m (a distance)
    jerk_slew: float = 1.5  # |a_k - a_{k-1}| <= jerk_slew · a_clamp: theirs 0.5 · a_clamp per frame,
    #   and a step is 3 frames, so 1.5 · a_clamp per step
    speed_cap: float = 1.68  # |v| <= max(1.68 · m, 1.05 · |v0|): theirs 1.4 · 1.2 m' per frame, a speed
    #   relative to the median speed, so unit-free: stays 1.68
    speed_cap_v0: float = 1.05  # ... the 1.05 · |v0| part: unit-free
    cursor_advance: int = 3  # the servo's cursor moves at most this many trajectory indices per step:
    #   theirs 3 m' of arc per frame = 3 m per step, and one index of our demos is about one m
    hold_tol: float = 0.02  # a chunk step is "held" when |q_{k+1} - q_k| < hold_tol · m at the segment end;
    #   2 % of a median step: the servo's stop at the end decays like k e^{-ωk}, and at 1e-3 it was
    #   not reached within H = 16 steps even for a segment ending 2 steps ahead (measured)
    min_moving_steps: int = 3  # a servo label needs >= this many unmasked steps, else the state is
    #   redrawn: theirs 8 frames = 0.27 s = 2.7 of our steps -> 3
    near_end_steps: int = 3  # a noised state projecting within this many steps of its segment's end
    #   is redrawn: theirs 8 frames -> 3 steps, as above
    max_redraws: int = 6  # ... at most this many times (theirs: 6), then it is dropped
    pool_size: int = 4096  # AugmentationSampler: pairs kept in the pool
    refresh_size: int = 512  # ... fresh pairs per refresh (they replace the oldest pairs)
    reuse: float = 4.0  # ... a refresh follows every reuse * refresh_size pairs served, so on average
    #   a pair is served `reuse` times: the price of keeping a call near 1 ms (bench_relabel.py)
    episodes_per_refresh: int = 16  # ... drawn from this many (episode) draws, so the env calls
    #   (collision check, observation) are batched per scenario instead of per pair


# --------------------------------------------------------------------------------------------
# 1. Demonstration statistics (Sec. IV-E: "with respect to the demonstration dataset's velocity
#    and acceleration statistics")
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class DemoStats:
    median_step: float  # rad/step: envs.median_step(base demos); 1 unit of every noise level σ
    median_speed: float  # rad/step: median over moving steps of ‖q[t+1] - q[t]‖₂ (sets lookahead)
    accel_max: np.ndarray  # (dof,) rad/step²: per-joint clamp on the PD acceleration
    max_step: np.ndarray  # (dof,) rad/step: the env's speed limit, clamp on the PD velocity
    acc_p95: float  # rad/step²: 95th percentile of ‖q[t+1] - 2 q[t] + q[t-1]‖₂, sets the servo's a_clamp
    #   (PAPER_SETUP §6; measured per step of our demos, so already in our units)


def demo_stats(episodes: Sequence[dict], median_step: float, max_step, accel_percentile: float = 99.0) -> DemoStats:
    """Statistics of the base demonstrations D0 that shape the corrective labels.

    `median_step` must be `envs.median_step(episodes)` (this module does not import envs); `max_step`
    is the env's per-step joint speed limit (scalar or (dof,)). The acceleration clamp is the
    `accel_percentile` of |q[t+1] - 2 q[t] + q[t-1]| per joint: a high percentile rather than the
    max, so that one odd step of one demo does not set the clamp for every label.
    """
    if not np.isfinite(median_step) or median_step <= 0:
        raise ValueError(f"median_step must be a finite positive number (rad/step), got {median_step!r}")
    if not 0 < accel_percentile <= 100:
        raise ValueError(f"accel_percentile must be in (0, 100], got {accel_percentile!r}")
    steps, accels = [], []
    for ep in episodes:
        q = np.asarray(ep["q"], dtype=np.float64)  # (T, dof)
        if len(q) >= 2:
            steps.append(np.diff(q, axis=0))
        if len(q) >= 3:
            accels.append(np.abs(q[2:] - 2 * q[1:-1] + q[:-2]))  # second differences, rad/step²
    if not accels:
        raise ValueError("demo_stats needs at least one episode with >= 3 steps to measure accelerations")
    speed = np.linalg.norm(np.concatenate(steps), axis=1)
    speed = speed[speed > 0]  # standing still is not a speed
    if speed.size == 0:
        raise ValueError("the demonstrations never move; no median speed can be measured")
    accels = np.concatenate(accels)  # (sum T-2, dof)
    accel_max = np.percentile(accels, accel_percentile, axis=0)  # (dof,)
    acc_p95 = float(np.percentile(np.linalg.norm(accels, axis=1), 95))  # PCD: norm over joints, all steps
    if np.any(accel_max <= 0):
        raise ValueError(f"the demonstrations show no acceleration on joints {np.flatnonzero(accel_max <= 0).tolist()}; "
                         "the PD return could never move them (accel clamp would be 0)")
    dof = accel_max.shape[0]
    max_step = np.broadcast_to(np.asarray(max_step, dtype=np.float64), (dof,)).copy()
    if np.any(~np.isfinite(max_step)) or np.any(max_step <= 0):
        raise ValueError(f"max_step must be positive and finite (rad/step), got {max_step}")
    return DemoStats(float(median_step), float(np.median(speed)), accel_max, max_step, acc_p95)


# --------------------------------------------------------------------------------------------
# 2. Noised states around the intervention data
# --------------------------------------------------------------------------------------------

def label_steps(expert: np.ndarray, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Steps t whose chunk is a valid label (diffusion.label_mask, the paper's label rule), and seg_end (N,):
    the end (exclusive) of the expert run containing t -- the part of the trajectory labels may follow."""
    expert = np.asarray(expert, dtype=bool)
    seg_end = np.zeros(len(expert), dtype=np.int64)
    for start, end in expert_runs(expert, horizon):
        seg_end[start:end] = end
    t = np.flatnonzero(label_mask(expert, horizon))
    return t, seg_end[t]


def covariance_factor(cov: np.ndarray) -> np.ndarray:
    """L with L Lᵀ = Σ for a batch of covariances (..., dof, dof).

    An eigendecomposition rather than a Cholesky: Σ̂ from a handful of policy samples is often
    (near-)singular -- a flat ellipse -- where Cholesky fails. Eigenvalues that are negative only by
    round-off are set to 0; clearly negative ones mean the matrix is not a covariance (ValueError).
    """
    cov = np.asarray(cov, dtype=np.float64)
    if cov.ndim < 2 or cov.shape[-1] != cov.shape[-2]:
        raise ValueError(f"a covariance must be (..., dof, dof), got shape {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise ValueError("covariance contains NaN or inf; valid covariances are finite")
    scale = float(np.abs(cov).max(initial=0.0))  # relative tolerances: covariances are ~1e-4 rad²
    if np.abs(cov - np.swapaxes(cov, -1, -2)).max(initial=0.0) > 1e-8 * scale:
        raise ValueError("covariance is not symmetric; valid covariances satisfy Σ = Σᵀ")
    w, v = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    tol = 1e-9 * np.maximum(np.abs(w).max(axis=-1, keepdims=True), 1e-300)
    if np.any(w < -tol):
        raise ValueError(f"covariance is not positive semi-definite (smallest eigenvalue {w.min():.3g}); "
                         "valid covariances have eigenvalues >= 0")
    return v * np.sqrt(np.clip(w, 0.0, None))[..., None, :]  # (..., dof, dof): columns scaled


def noise_factors(sigma, steps: np.ndarray, dof: int, median_step: float | None = None, n_steps: int | None = None) -> np.ndarray:
    """Noise factors L_t (len(steps), dof, dof) for the timesteps `steps` of one episode.

    The three noise models, told apart by the form of `sigma`:
      - isotropic: a scalar σ >= 0 in median steps -> Σ = (σ · median_step)² I  (needs median_step)
      - pooled:    an array (dof, dof)             -> Σ̄ at every step
      - per_step:  a pair (timesteps (M,), covs (M, dof, dof)) -> Σ_t from the nearest measured
                   timestep (calibrate.py measures every other step); or an array (n_steps, dof, dof)
                   aligned with the episode's steps.
    """
    steps = np.asarray(steps, dtype=np.int64)
    if isinstance(sigma, tuple):  # per_step with explicit timesteps
        if len(sigma) != 2:
            raise ValueError("per-step sigma must be a pair (timesteps (M,), covs (M, dof, dof))")
        measured_t = np.asarray(sigma[0], dtype=np.int64)
        covs = np.asarray(sigma[1], dtype=np.float64)
        if covs.ndim != 3 or covs.shape[1:] != (dof, dof) or measured_t.shape != (len(covs),) or len(covs) == 0:
            raise ValueError(f"per-step sigma must be timesteps (M,) with covs (M, {dof}, {dof}), M >= 1; "
                             f"got timesteps {measured_t.shape} and covs {covs.shape}")
        order = np.argsort(measured_t, kind="stable")
        measured_t, covs = measured_t[order], covs[order]
        # nearest measured timestep (ties -> the earlier one)
        right = np.clip(np.searchsorted(measured_t, steps), 0, len(measured_t) - 1)
        left = np.clip(right - 1, 0, len(measured_t) - 1)
        nearest = np.where(np.abs(measured_t[left] - steps) <= np.abs(measured_t[right] - steps), left, right)
        return covariance_factor(covs)[nearest]
    s = np.asarray(sigma, dtype=np.float64)
    if s.ndim == 0:  # isotropic baseline
        if not np.isfinite(s) or s < 0:
            raise ValueError(f"isotropic sigma must be a finite number >= 0 (in median steps), got {sigma!r}")
        if median_step is None or not np.isfinite(median_step) or median_step <= 0:
            raise ValueError(f"isotropic sigma needs a finite positive median_step, got {median_step!r}")
        return np.broadcast_to(float(s) * median_step * np.eye(dof), (len(steps), dof, dof))
    if s.shape == (dof, dof):  # pooled
        return np.broadcast_to(covariance_factor(s), (len(steps), dof, dof))
    if s.ndim == 3 and s.shape[1:] == (dof, dof):  # per_step, aligned with the episode
        if n_steps is not None and len(s) != n_steps:
            raise ValueError(f"per-step sigma of shape {s.shape} is not aligned with the episode's {n_steps} steps; "
                             "pass (timesteps, covs) to say which steps the covariances belong to")
        return covariance_factor(s)[steps]
    raise ValueError(f"sigma must be a scalar (isotropic), ({dof}, {dof}) (pooled), ({n_steps}, {dof}, {dof}) or "
                     f"(timesteps, covs) (per-step); got shape {s.shape}")


def _in_limits(q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.all((q >= lo) & (q <= hi), axis=-1)


def _draw_valid(center: np.ndarray, factors: np.ndarray, rng: np.random.Generator, env, max_tries: int) -> tuple[np.ndarray, np.ndarray]:
    """q̃ = q_t + L z, z ~ N(0, I) (so q̃ ~ N(q_t, L Lᵀ)) for each row; rows in collision or outside
    the joint limits are redrawn up to `max_tries` rounds. Returns (q̃ (m, dof), kept (m,) bool).
    Rejecting (rather than clipping to the limits) keeps the accepted states Gaussian-shaped
    instead of piling probability mass onto the limit."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in env.joint_limits)
    q = center.copy()
    kept = np.zeros(len(center), dtype=bool)
    todo = np.arange(len(center))
    for _ in range(max_tries):
        if todo.size == 0:
            break
        z = rng.standard_normal((todo.size, center.shape[1]))
        cand = center[todo] + np.einsum("mij,mj->mi", factors[todo], z)  # (m, dof)
        ok = _in_limits(cand, lo, hi)
        if ok.any():
            ok[ok] = ~np.asarray(env.in_collision(cand[ok]), dtype=bool)
        q[todo[ok]] = cand[ok]
        kept[todo[ok]] = True
        todo = todo[~ok]
    return q, kept


def _check_episode(episode: dict) -> tuple[np.ndarray, np.ndarray]:
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


def perturb_states(episode: dict, sigma, rng: np.random.Generator, n: int, env, t_index=None,
                   median_step: float | None = None, horizon: int = 16, max_tries: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Draw n noised joint states q̃ ~ N(q_t, Σ_t) around the intervention states of `episode`.

    sigma: see `noise_factors` (isotropic scalar in median steps / pooled (dof, dof) / per-step).
    t_index: None -> t uniform over the steps with a valid label (see `label_steps`); an int -> all
      n around that step; an array (n,) -> one state around each given step.
    env: is reset to the episode's scenario (`env.reset(seed=episode['seed'])`) for collision checks.
    Returns (q̃ (m, dof), t (m,)) with m <= n: states still in collision or outside the joint limits
    after `max_tries` redraws are dropped, so m is the number kept.
    """
    q, expert = _check_episode(episode)
    if not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n must be an integer >= 0, got {n!r}")
    if t_index is None:
        valid_t, _ = label_steps(expert, horizon)
        if valid_t.size == 0:
            raise ValueError(f"episode has no intervention step with a valid label (expert runs >= H={horizon})")
        t = rng.choice(valid_t, size=n)
    else:
        t = np.broadcast_to(np.asarray(t_index, dtype=np.int64), (n,)).copy()
        if t.size and (t.min() < 0 or t.max() >= len(q)):
            raise ValueError(f"t_index must be in [0, {len(q)}), got range [{t.min()}, {t.max()}]")
    factors = noise_factors(sigma, t, q.shape[1], median_step=median_step, n_steps=len(q))
    env.reset(seed=int(episode["seed"]))
    q_tilde, kept = _draw_valid(q[t], np.asarray(factors), rng, env, max_tries)
    return q_tilde[kept], t[kept]


# --------------------------------------------------------------------------------------------
# 3. Monotone closest-point projection
# --------------------------------------------------------------------------------------------

def monotone_projection(q: np.ndarray, trajectory: np.ndarray, t_start, window: int | None = None, t_end=None):
    """Index of the trajectory point closest to q among t_start <= t < min(t_start + window, t_end).

    "Monotone": the search never looks before t_start, so a noised copy of the state at step t is
    associated with step t or later even when an earlier point of the path is closer -- the label
    never tells the robot to go back in time. Ties go to the earliest index.
    q: (B, dof) or (dof,); trajectory (T, dof); t_start, t_end: int or (B,) (t_end exclusive,
    default T); window: None = no bound. Returns (B,) int64 (or an int for a single q).
    """
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


# --------------------------------------------------------------------------------------------
# 4. Critically damped PD return chunk
# --------------------------------------------------------------------------------------------

def critically_damped_gains(settle_steps: float) -> tuple[float, float]:
    """(Kp, Kd) per step for a critically damped PD on the discrete double integrator
    v ← v + a, q ← q + v (one control step, dt = 1).

    Continuous time: e'' + Kd e' + Kp e = 0 is critically damped for Kd = 2 √Kp (double pole -ω,
    ω = √Kp), and e(t) = (1 + ωt) e0 e^{-ωt} falls below 2 % at ωt ≈ 5.83. With dt = 1 and
    ω ≈ 0.7 (settling in ~8 steps) an Euler step of the continuous gains overshoots, so we place the
    discrete double pole exactly at p = e^{-ω}: the error map [[1-Kp, 1-Kd], [-Kp, 1-Kd]] has
    trace 2 - Kp - Kd = 2p and determinant 1 - Kd = p², i.e. Kp = (1-p)², Kd = 1 - p² -- which
    tends to Kd = 2 √Kp as ω -> 0.
    """
    if not np.isfinite(settle_steps) or settle_steps <= 0:
        raise ValueError(f"settle_steps must be a positive number of steps, got {settle_steps!r}")
    # >>> exercise 9: the critically damped PD return chunk, accelerations clamped (Sec. IV-E)
    p = np.exp(-5.83 / settle_steps)  # 5.83: (1 + x) e^{-x} = 0.02 at x = 5.83 (2 % settling)
    return float((1 - p) ** 2), float(1 - p ** 2)
    # <<< exercise 9


def lookahead_steps(q0: np.ndarray, q_proj: np.ndarray, median_speed: float, max_lookahead: int) -> np.ndarray:
    """The literal reading of Sec. IV-E's target, "a state a few timesteps further in the expert
    trajectory (computed with the median velocity in the dataset)": L = the steps the demos take at
    their median speed to cover the gap ‖q0 - q_proj‖, capped at max_lookahead (0 on the path).

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


def pd_return_chunk(q0: np.ndarray, v0: np.ndarray, trajectory: np.ndarray, t_proj, H: int, lookahead,
                    accel_max, max_step, settle_steps: float | None = None, t_end=None, limits=None) -> np.ndarray:
    """Roll out a critically damped PD controller from (q0, v0) back onto the expert trajectory.

    The reference at rollout step k is r_k = trajectory[t_proj + lookahead + k] (held at the last
    point of the segment, index t_end - 1): it starts `lookahead` steps ahead of the projection and
    advances one index per step, so the chunk REJOINS the trajectory, then follows it. With
    e_k = q_k - r_k the tracking error and u_k = r_k - r_{k-1} the reference velocity, the control
    is PD on the error plus the reference's own acceleration as feed-forward,
        a_k = -Kp e_k - Kd (v_k - u_k) + (u_{k+1} - u_k),
    which makes e obey the critically damped map of `critically_damped_gains` exactly (it settles
    in ~settle_steps, default H/2) as long as the clamps are inactive:
        |a| <= accel_max (per joint, from the demos), |v| <= max_step (the env's speed limit).
    The PD is written in cascade form, a = Kd (w* - (v - u)) with closing speed w* = -(Kp/Kd) e
    (identical in the linear region), so that w* can be capped at √(2 accel_max |e|): the speed
    from which the clamped deceleration can still stop at the path. Without the cap a saturated PD
    winds up speed and overshoots the path (in tests/test_relabel.py by 25 % of the initial error,
    with the cap by 8 %).
    Units are per step (rad/step, rad/step²). Because |q_{k+1} - q_k| <= max_step, the env executes
    every target of the chunk exactly.

    q0, v0: (B, dof) or (dof,); trajectory (T, dof); t_proj, lookahead, t_end: int or (B,);
    limits: optional (lo, hi) joint limits the positions are clipped to.
    Returns the absolute joint targets q_1 .. q_H: (B, H, dof) (or (H, dof) for a single q0).
    """
    trajectory, q, v, single = _return_chunk_inputs(q0, v0, trajectory, H)
    B, dof = q.shape
    accel_max = np.broadcast_to(np.asarray(accel_max, dtype=np.float64), (dof,))
    max_step = np.broadcast_to(np.asarray(max_step, dtype=np.float64), (dof,))
    if np.any(~(accel_max > 0)) or np.any(~(max_step > 0)):
        raise ValueError(f"accel_max and max_step must be > 0 per joint, got {accel_max} and {max_step}")
    T = len(trajectory)
    t_end = np.broadcast_to(np.asarray(T if t_end is None else t_end, dtype=np.int64), (B,))
    start = np.broadcast_to(np.asarray(t_proj, dtype=np.int64), (B,)) + np.broadcast_to(np.asarray(lookahead, dtype=np.int64), (B,))
    if B and (np.any(start < 0) or np.any(t_end > T) or np.any(t_end < 1)):
        raise ValueError(f"need t_proj + lookahead >= 0 and 1 <= t_end <= T={T}")
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


def servo_return_chunk(q0: np.ndarray, v0: np.ndarray, trajectory: np.ndarray, t_proj, H: int, median_step: float,
                       acc_p95: float, max_step, t_end=None, limits=None, cfg: RelabelConfig | None = None):
    """The authors' label (PAPER_SETUP.md §6): a critically damped servo that tracks the expert
    segment at its own monotone cursor, rolled out from (q0, v0).

    Every step k the cursor c_k is the monotone projection of the label's own point x_k, searched
    from c_{k-1} at most `cursor_advance` indices ahead (it starts at t_proj), and the servo pulls
    toward the expert's position and velocity there:
        a_k = Kp (r_c - x_k) + Kd (u_c - v_k),   r_c = trajectory[c], u_c = r_{c+1} - r_c (0 at the end)
        a_clamp = 0.9 · max(2√dof · acc_p95, accel_floor · m),  Kp = a_clamp / max(d0, gain_floor · m),
        Kd = 2 √Kp  (critical damping; discretized exactly, see below),  d0 = ‖q0 - trajectory[t_proj]‖,
        m = median_step;
    then ‖a_k‖ <= a_clamp, ‖a_k - a_{k-1}‖ <= jerk_slew · a_clamp (a_{-1} = 0),
    ‖v‖ <= max(speed_cap · m, speed_cap_v0 · ‖v0‖), |v| <= max_step per joint, x within `limits`.
    (Norm clamps, as the authors'; the per-joint max_step is our env's.) Constants: RelabelConfig,
    converted from the authors' 30 Hz frames to our steps.

    The held tail: once the cursor is at the segment's last point and the arm has stopped
    (|x_{k+1} - x_k| < hold_tol · m on every joint) for the rest of the chunk, those steps only
    repeat the end pose; mask is False there so the training loss ignores them.

    q0, v0: (B, dof) or (dof,); trajectory (T, dof); t_proj, t_end: int or (B,) (t_end exclusive).
    Returns (chunk (B, H, dof) absolute joint targets x_1 .. x_H, mask (B, H) bool, True = in the
    loss); (H, dof) and (H,) for a single q0.
    """
    cfg = cfg or RelabelConfig()
    trajectory, x, v, single = _return_chunk_inputs(q0, v0, trajectory, H)
    B, dof = x.shape
    if not (median_step > 0 and np.isfinite(acc_p95) and acc_p95 >= 0):
        raise ValueError(f"need median_step > 0 and acc_p95 >= 0, got {median_step!r} and {acc_p95!r}")
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
    # Kd = 2 √Kp (critical damping) in continuous time. Per step (dt = 0.1 s) ω reaches ~1.1, where
    # Euler with the continuous gains is unstable (the label chattered ±a_clamp every step; at the
    # authors' 30 Hz ω is 3x smaller). So the double pole is placed exactly at e^{-ω}, as in
    # `critically_damped_gains`: Kp = (1 - p)², Kd = 1 - p², which tends to (ω², 2ω) as ω -> 0.
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


def corrective_labels(q_tilde: np.ndarray, v: np.ndarray, trajectory: np.ndarray, t: np.ndarray, t_end: np.ndarray,
                      stats: DemoStats, cfg: RelabelConfig, limits=None, t_proj=None) -> tuple[np.ndarray, np.ndarray]:
    """The labelling pipeline of Sec. IV-E for noised states q̃ (m, dof) with velocities v (m, dof)
    that came from steps t (m,): monotone projection -> return chunk, by `cfg.label`:
    'servo' (default, the authors', `servo_return_chunk`) or 'pd' (`pd_return_chunk`, with the
    optional lookahead). `t_end` (m,) is the (exclusive) end of each state's expert segment in
    `trajectory`; `t_proj` (m,) may pass projections already computed.
    Returns (chunks (m, H, dof), mask (m, H) bool, True = in the loss; all True for 'pd')."""
    if t_proj is None:
        t_proj = monotone_projection(q_tilde, trajectory, t, window=cfg.projection_window, t_end=t_end)
    if cfg.label == "servo":
        return servo_return_chunk(q_tilde, v, trajectory, t_proj, cfg.horizon, stats.median_step, stats.acc_p95,
                                  stats.max_step, t_end=t_end, limits=limits, cfg=cfg)
    if cfg.label != "pd":
        raise ValueError(f"RelabelConfig.label must be 'servo' or 'pd', got {cfg.label!r}")
    if cfg.lookahead == "time_matched":
        ahead = 0
    elif cfg.lookahead == "gap":
        ahead = lookahead_steps(q_tilde, trajectory[t_proj], stats.median_speed, cfg.max_lookahead)
    else:
        raise ValueError(f"RelabelConfig.lookahead must be 'time_matched' or 'gap', got {cfg.lookahead!r}")
    chunks = pd_return_chunk(q_tilde, v, trajectory, t_proj, cfg.horizon, ahead, stats.accel_max, stats.max_step,
                             settle_steps=cfg.settle_steps, t_end=t_end, limits=limits)
    return chunks, np.ones(chunks.shape[:2], dtype=bool)


# --------------------------------------------------------------------------------------------
# 5. On-the-fly augmentation for co-training (Sec. IV-A steps 3-4)
# --------------------------------------------------------------------------------------------

NOISE_KINDS = ("isotropic", "pooled", "per_step")


class AugmentationSampler:
    """sampler(n, rng) -> (obs (n, obs_dim) float32, chunks (n, H, dof) float32, mask (n, H) bool):
    noised intervention states with corrective labels, the D̂_1 ∪ ... ∪ D̂_k of Sec. IV-A, made on the fly.

    noise / sigma (explicit, validated):
      'isotropic': sigma is a scalar σ in median steps                       (Table I baselines)
      'pooled':    sigma is Σ̄^α, (dof, dof)                                  (Eqs. 15-16)
      'per_step':  sigma[e] for episode index e is a pair (timesteps (M,), covs (M, dof, dof)) --
                   a list aligned with `episodes` or a dict {episode index: pair}; steps without a
                   measurement use the nearest measured step of the same episode       (Eq. 14)
    make_env: a no-argument factory (e.g. `lambda: envs.make_env('planar')`); one env per scenario
      seed is created on demand, reset once to that seed, and cached.

    A pair is made like this: draw (episode, t) uniformly among the intervention steps with a valid
    label; q̃ ~ N(q_t, Σ_t) (collision-free, within limits); v = (q_t - q_{t-1}) + N(0, (0.3 m)²)
    (PAPER_SETUP §6, m = median step); obs = env.make_obs(q̃, q̃ - v) in the episode's scenario;
    chunk, mask = `corrective_labels` (monotone projection, servo return from (q̃, v)); states that
    project within `near_end_steps` of the segment's end or whose label is mostly a held tail are
    redrawn. With image observations
    (env.image_shape non-empty) the noised state reuses the recorded image of state t, and only the
    joint positions change: the paper's approximation for its image policy (Sec. V).

    Cost: env calls cost per call, not per state, so pairs are generated in batches grouped by
    scenario and kept in a pool of `cfg.pool_size` pairs. Each call returns n pairs drawn uniformly
    from the pool; after every `cfg.reuse * cfg.refresh_size` pairs served, the `cfg.refresh_size`
    oldest pairs are replaced by fresh ones (from `cfg.episodes_per_refresh` episode draws). So a
    pair is served `reuse` (= 4) times on average, and with n = 128 a refresh comes every 16 calls
    (32 fresh pairs per call). Counting pairs rather than calls keeps the cost per served pair the
    same when several samplers share a batch (one per DAgger round). All randomness comes from the
    rng passed to each call, so the same seed and call sequence give the same pairs; `state_dict`
    saves the pool for a resumed training run.
    """

    def __init__(self, episodes: Sequence[dict], make_env: Callable[[], object], stats: DemoStats,
                 noise: str, sigma, cfg: RelabelConfig | None = None):
        self.cfg = cfg or RelabelConfig()
        H = self.cfg.horizon
        if noise not in NOISE_KINDS:
            raise ValueError(f"noise must be one of {NOISE_KINDS}, got {noise!r}")
        if self.cfg.label not in ("servo", "pd"):
            raise ValueError(f"RelabelConfig.label must be 'servo' or 'pd', got {self.cfg.label!r}")
        if self.cfg.lookahead not in ("time_matched", "gap"):
            raise ValueError(f"RelabelConfig.lookahead must be 'time_matched' or 'gap', got {self.cfg.lookahead!r}")
        if self.cfg.refresh_size < 1 or self.cfg.pool_size < self.cfg.refresh_size or not self.cfg.reuse > 0:
            raise ValueError("need 1 <= refresh_size <= pool_size and reuse > 0, got refresh_size="
                             f"{self.cfg.refresh_size}, pool_size={self.cfg.pool_size}, reuse={self.cfg.reuse}")
        self.noise, self.stats, self._make_env, self._envs = noise, stats, make_env, {}
        # One flat table of every labelable intervention step; the expert segments of all episodes
        # are concatenated into one trajectory array so projection and PD run once for a whole batch.
        traj, center, vel, t_glob, end_glob, factors, seeds, ep_of, offset = [], [], [], [], [], [], [], [], 0
        self._episode_obs = [ep["obs"] for ep in episodes]  # recorded images are reused (references, no copy)
        for e, ep in enumerate(episodes):
            q, expert = _check_episode(ep)
            t, seg_end = label_steps(expert, H)
            if t.size == 0:
                offset += len(q)
                traj.append(q)
                continue
            dof = q.shape[1]
            if noise == "isotropic" and np.ndim(sigma) != 0:
                raise ValueError(f"noise='isotropic' needs a scalar sigma (median steps), got shape {np.shape(sigma)}")
            if noise == "pooled" and np.shape(sigma) != (dof, dof):
                raise ValueError(f"noise='pooled' needs sigma of shape ({dof}, {dof}), got {np.shape(sigma)}")
            if noise == "per_step":
                try:
                    per_ep = sigma[e]
                except (KeyError, IndexError, TypeError):
                    raise ValueError(f"noise='per_step': no covariances for episode {e}; pass a list aligned with "
                                     "episodes or a dict {episode index: (timesteps, covs)}") from None
                if not isinstance(per_ep, tuple):
                    raise ValueError(f"noise='per_step': sigma[{e}] must be a pair (timesteps, covs)")
                factors.append(noise_factors(per_ep, t, dof))
            else:
                factors.append(noise_factors(sigma, t, dof, median_step=stats.median_step))
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
        self.trajectory = np.concatenate(traj)  # (sum T, dof)
        self.center = np.concatenate(center)  # (N, dof) q_t
        self.velocity = np.concatenate(vel)  # (N, dof) q_t - q_{t-1}
        self.t_glob = np.concatenate(t_glob)  # (N,) index of q_t in self.trajectory
        self.end_glob = np.concatenate(end_glob)  # (N,) exclusive end of its expert segment
        self.factors = np.ascontiguousarray(np.concatenate(factors))  # (N, dof, dof)
        self.seeds = np.concatenate(seeds)
        self.episode_of = np.concatenate(ep_of)
        self.step_of = self.t_glob - np.concatenate([[0], np.cumsum([len(q) for q in traj])])[self.episode_of]
        # contiguous block of rows per episode, for the "episodes first" draw
        self._ep_ids, self._ep_start, self._ep_count = np.unique(self.episode_of, return_index=True, return_counts=True)
        self._pool_obs = self._pool_chunks = self._pool_mask = None
        self._filled = self._write = self._served = 0  # pool fill, ring position, served since refresh
        self.n_drawn = self.n_kept = 0  # acceptance bookkeeping (collision / limit rejections)

    def _env(self, seed: int):
        if seed not in self._envs:
            env = self._make_env()
            env.reset(seed=seed)
            self._envs[seed] = env
        return self._envs[seed]

    def _observe(self, rows: np.ndarray, q_tilde: np.ndarray, v: np.ndarray) -> np.ndarray:
        """obs (m, obs_dim) float32 of noised states, one batched env call per scenario. The previous
        frame is rebuilt as q̃ - v (PAPER_SETUP §6); make_obs recomputes the end effector from q̃."""
        obs = None
        for seed in np.unique(self.seeds[rows]):
            sel = self.seeds[rows] == seed
            env, r = self._env(int(seed)), rows[sel]
            n_pix = int(np.prod(env.image_shape)) if getattr(env, "image_shape", ()) else 0
            if n_pix:  # Sec. V: noised states reuse the original image; only the joints are noised
                image = np.stack([self._episode_obs[e][t, -n_pix:] for e, t in zip(self.episode_of[r], self.step_of[r])])
                part = env.make_obs(q_tilde[sel], q_tilde[sel] - v[sel], image=image)
            else:
                part = env.make_obs(q_tilde[sel], q_tilde[sel] - v[sel])
            part = np.asarray(part, dtype=np.float32)
            if obs is None:
                obs = np.empty((len(rows), part.shape[1]), np.float32)
            obs[sel] = part
        return obs

    def generate(self, m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """m fresh pairs (fewer if some states were dropped): obs (m', obs_dim) float32, chunks
        (m', H, dof) float32, mask (m', H) bool (True = in the loss). Episodes are drawn first
        (probability proportional to their number of labelable steps, so steps are uniform overall),
        then steps within them. A state is dropped when it stays in collision / outside the limits
        for `max_tries` draws; it is redrawn (up to `max_redraws` times, PAPER_SETUP §6) when it
        projects within `near_end_steps` of its segment's end or its label has fewer than
        `min_moving_steps` unmasked steps."""
        if not isinstance(m, (int, np.integer)) or m < 1:
            raise ValueError(f"m must be a positive integer, got {m!r}")
        cfg, dof = self.cfg, self.center.shape[1]
        k = min(cfg.episodes_per_refresh, m)
        draws = rng.choice(len(self._ep_ids), size=k, p=self._ep_count / self._ep_count.sum())
        per_draw = np.full(k, m // k)
        per_draw[: m % k] += 1
        todo = np.concatenate([self._ep_start[d] + rng.integers(self._ep_count[d], size=c) for d, c in zip(draws, per_draw)])
        limits = self._env(int(self.seeds[todo[0]])).joint_limits
        out_rows, out_q, out_v, out_chunks, out_mask = [], [], [], [], []
        self.n_drawn += m
        for _ in range(cfg.max_redraws + 1):
            if todo.size == 0:
                break
            q_tilde, kept = np.empty((len(todo), dof)), np.zeros(len(todo), dtype=bool)
            for seed in np.unique(self.seeds[todo]):  # one batched collision check per scenario
                sel = self.seeds[todo] == seed
                q_tilde[sel], kept[sel] = _draw_valid(self.center[todo[sel]], self.factors[todo[sel]], rng,
                                                      self._env(int(seed)), cfg.max_tries)
            r, q_tilde = todo[kept], q_tilde[kept]  # states still invalid after max_tries are dropped
            # PAPER_SETUP §6: velocity = demo tangent + N(0, (velocity_noise · median_step)²) per joint
            v = self.velocity[r] + cfg.velocity_noise * self.stats.median_step * rng.standard_normal(q_tilde.shape)
            t_proj = monotone_projection(q_tilde, self.trajectory, self.t_glob[r], window=cfg.projection_window,
                                         t_end=self.end_glob[r])
            ok = t_proj < self.end_glob[r] - cfg.near_end_steps  # not within near_end_steps of the end
            chunks, mask = corrective_labels(q_tilde[ok], v[ok], self.trajectory, self.t_glob[r[ok]],
                                             self.end_glob[r[ok]], self.stats, cfg, limits=limits, t_proj=t_proj[ok])
            moving = mask.sum(axis=1) >= cfg.min_moving_steps  # enough steps left in the loss
            ok[ok] = moving
            out_rows.append(r[ok]), out_q.append(q_tilde[ok]), out_v.append(v[ok])
            out_chunks.append(chunks[moving]), out_mask.append(mask[moving])
            todo = r[~ok]  # redraw these
        r = np.concatenate(out_rows)
        self.n_kept += r.size
        if r.size == 0:
            return (np.empty((0, 0), np.float32), np.empty((0, cfg.horizon, dof), np.float32),
                    np.empty((0, cfg.horizon), bool))
        obs = self._observe(r, np.concatenate(out_q), np.concatenate(out_v))
        return obs, np.concatenate(out_chunks).astype(np.float32), np.concatenate(out_mask)

    def _refresh(self, rng: np.random.Generator) -> int:
        obs, chunks, mask = self.generate(self.cfg.refresh_size, rng)
        if self._pool_obs is None and len(obs):
            P = self.cfg.pool_size
            self._pool_obs = np.empty((P, obs.shape[1]), np.float32)
            self._pool_chunks = np.empty((P, *chunks.shape[1:]), np.float32)
            self._pool_mask = np.empty((P, chunks.shape[1]), bool)
        if len(obs):  # ring buffer: overwrite the oldest pairs
            slots = (self._write + np.arange(len(obs))) % self.cfg.pool_size
            self._pool_obs[slots], self._pool_chunks[slots], self._pool_mask[slots] = obs, chunks, mask
            self._write = int((self._write + len(obs)) % self.cfg.pool_size)
            self._filled = min(self.cfg.pool_size, self._filled + len(obs))
        return len(obs)

    def state_dict(self) -> dict:
        """The pool and its counters, so a resumed training run can continue with the same pairs
        (the rng is the caller's and is restored by the caller)."""
        copy = lambda a: None if a is None else a.copy()
        return {"pool_obs": copy(self._pool_obs), "pool_chunks": copy(self._pool_chunks),
                "pool_mask": copy(self._pool_mask), "filled": self._filled,
                "write": self._write, "served": self._served, "n_drawn": self.n_drawn, "n_kept": self.n_kept}

    def load_state_dict(self, state: dict) -> None:
        copy = lambda a, dtype: None if a is None else np.array(a, dtype=dtype)
        self._pool_obs, self._pool_chunks = copy(state["pool_obs"], np.float32), copy(state["pool_chunks"], np.float32)
        self._pool_mask = copy(state.get("pool_mask"), bool)
        if self._pool_mask is None and self._pool_chunks is not None:  # a pool saved before masks existed
            self._pool_mask = np.ones(self._pool_chunks.shape[:2], dtype=bool)
        self._filled, self._write, self._served = int(state["filled"]), int(state["write"]), int(state["served"])
        self.n_drawn, self.n_kept = int(state["n_drawn"]), int(state["n_kept"])

    def __call__(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """n pairs from the pool (diffusion.train's sampler hook): obs (n, obs_dim), chunks (n, H, dof),
        mask (n, H) bool (True = in the loss). Fills the pool on the first call."""
        if not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n must be an integer >= 0, got {n!r}")
        if self._filled == 0:  # first call: fill the pool (bounded number of attempts)
            for _ in range(4 * self.cfg.pool_size // self.cfg.refresh_size):
                self._refresh(rng)
                if self._filled >= self.cfg.pool_size:
                    break
            if self._filled == 0:
                raise ValueError(f"every perturbed state was in collision or outside the joint limits after "
                                 f"{self.cfg.max_tries} tries, or too near its segment's end after "
                                 f"{self.cfg.max_redraws} redraws; the noise ({self.noise}) is too large for these scenarios")
        elif self._served >= self.cfg.reuse * self.cfg.refresh_size:
            self._refresh(rng)
            self._served = 0
        self._served += n
        pick = rng.integers(self._filled, size=n)
        return self._pool_obs[pick], self._pool_chunks[pick], self._pool_mask[pick]


# --------------------------------------------------------------------------------------------
# 6. Fig. 1: expert trajectory, policy-calibrated noise ellipses, sampled recovery trajectories
# --------------------------------------------------------------------------------------------

def _ee_jacobian(env, q: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    """Central-difference Jacobian of the end effector, (B, dim, dof), through the batched env.ee."""
    B, dof = q.shape
    offsets = eps * np.eye(dof)
    plus = env.ee((q[:, None, :] + offsets[None]).reshape(-1, dof))  # (B*dof, dim)
    minus = env.ee((q[:, None, :] - offsets[None]).reshape(-1, dof))
    jac = (plus - minus).reshape(B, dof, -1) / (2 * eps)  # (B, dof, dim)
    return np.swapaxes(jac, 1, 2)


def plot_recovery(env, episode: dict, sigma, path: str, rng: np.random.Generator, stats: DemoStats,
                  cfg: RelabelConfig | None = None, n_recoveries: int = 6, n_ellipses: int = 6) -> str:
    """The paper's Fig. 1 on the planar env: the expert (intervention) end-effector path in blue,
    2-σ ellipses of the policy-calibrated noise pushed to the end-effector plane through the fk
    Jacobian (J Σ_t Jᵀ), and sampled recovery trajectories (end-effector paths of PD return chunks
    from noised states) in orange. Left: the whole scene; right: a close-up of the noised stretch.
    sigma as in `noise_factors`. Saves a PNG to `path` and returns it."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Ellipse, Patch

    cfg = cfg or RelabelConfig()
    q, expert = _check_episode(episode)
    valid_t, seg_end = label_steps(expert, cfg.horizon)
    if valid_t.size == 0:
        raise ValueError(f"episode has no intervention of at least H={cfg.horizon} expert steps to draw")
    seg = valid_t[seg_end == seg_end[0]]  # labelable steps of the first intervention segment
    end = int(seg_end[0])
    env.reset(seed=int(episode["seed"]))

    # noise ellipses: Σ_t in joint space -> J Σ_t Jᵀ in the end-effector plane
    ell_t = seg[np.linspace(0, len(seg) - 1, min(n_ellipses, len(seg))).round().astype(int)]  # a handful
    factors = noise_factors(sigma, ell_t, q.shape[1], median_step=stats.median_step, n_steps=len(q))
    cov_q = factors @ np.swapaxes(factors, 1, 2)  # (n, dof, dof)
    jac = _ee_jacobian(env, q[ell_t])  # (n, dim, dof)
    cov_ee = jac @ cov_q @ np.swapaxes(jac, 1, 2)  # (n, 2, 2)
    centers = env.ee(q[ell_t])
    # recovery trajectories from noised states at evenly spread steps of the segment, and a fan of them
    # from one state in the middle (the close-up)
    mid = int(seg[len(seg) // 2])
    steps = np.concatenate([seg[np.linspace(0, len(seg) - 1, n_recoveries).round().astype(int)],
                            np.full(n_recoveries, mid)])  # (2 n,)
    q_tilde, t = perturb_states(episode, sigma, rng, len(steps), env, t_index=steps,
                                median_step=stats.median_step, horizon=cfg.horizon, max_tries=cfg.max_tries)
    v = q[t] - q[np.maximum(t - 1, 0)]
    chunks, _ = corrective_labels(q_tilde, v, q, t, np.full(len(t), end), stats, cfg, limits=env.joint_limits)
    recoveries = [env.ee(np.concatenate([qt[None], ch])) for qt, ch in zip(q_tilde, chunks)]  # (H+1, 2) each
    expert_ee = env.ee(q[seg[0]:end])

    env.set_state(q[seg[0]])  # the arm is drawn where the intervention starts
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.5))
    for ax in axes:
        env.render(ax, alpha=0.35)  # the arm faded: the path, noise and returns are the message
        for c, cv in zip(centers, cov_ee):
            w, vec = np.linalg.eigh(cv)
            angle = np.degrees(np.arctan2(vec[1, 1], vec[0, 1]))
            ax.add_patch(Ellipse(c, 4 * np.sqrt(max(w[1], 0)), 4 * np.sqrt(max(w[0], 0)), angle=angle,
                                 facecolor="tab:blue", alpha=0.2, edgecolor="tab:blue", lw=0.6))
        for rec in recoveries:
            ax.plot(rec[:, 0], rec[:, 1], color="tab:orange", lw=1.3)
            ax.plot(rec[0, 0], rec[0, 1], "o", color="tab:orange", ms=3)
        ax.plot(expert_ee[:, 0], expert_ee[:, 1], color="tab:blue", lw=2.0)
        ax.set_aspect("equal")
    # close-up: the fan of returns from the middle state and the path a chunk either side of it
    reach = cfg.horizon
    fan = [rec for rec, ti in zip(recoveries, t) if ti == mid]
    mid_ell = env.ee(q[mid:mid + 1])[0]
    jm = _ee_jacobian(env, q[mid:mid + 1])
    fm = noise_factors(sigma, np.array([mid]), q.shape[1], median_step=stats.median_step, n_steps=len(q))
    cov_mid = (jm @ (fm @ np.swapaxes(fm, 1, 2)) @ np.swapaxes(jm, 1, 2))[0]
    w, vec = np.linalg.eigh(cov_mid)
    axes[1].add_patch(Ellipse(mid_ell, 4 * np.sqrt(max(w[1], 0)), 4 * np.sqrt(max(w[0], 0)),
                              angle=np.degrees(np.arctan2(vec[1, 1], vec[0, 1])), facecolor="tab:blue", alpha=0.2,
                              edgecolor="tab:blue", lw=0.6))
    box = np.concatenate([env.ee(q[max(mid - reach // 2, seg[0]):min(mid + reach + 1, end)]), *fan])
    radius = 2 * np.sqrt(max(w.max(), 0))
    lo, hi = box.min(0) - radius, box.max(0) + radius
    half = 0.5 * max(hi - lo) * 1.1  # a square window keeps the aspect ratio equal
    axes[1].set_xlim((lo + hi)[0] / 2 - half, (lo + hi)[0] / 2 + half)
    axes[1].set_ylim((lo + hi)[1] / 2 - half, (lo + hi)[1] / 2 + half)
    axes[0].legend(handles=[Line2D([], [], color="tab:blue", lw=2, label="expert intervention (end effector)"),
                            Patch(facecolor="tab:blue", alpha=0.2, label="policy-calibrated noise (2σ)"),
                            Line2D([], [], color="tab:orange", label="sampled recovery trajectories")],
                   loc="lower left", fontsize=8)
    axes[0].set_title("scene")
    axes[1].set_title("close-up")
    fig.suptitle("Policy-calibrated noise around an intervention and the return labels (paper Fig. 1)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


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
    stats = demo_stats(episodes, envs.median_step(episodes), env.max_step)
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
