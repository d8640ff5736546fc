"""Policy calibration: how much noise does the policy itself make? (paper Sec. III-A and IV-D)

DART (Sec. III-A) picks the noise of its augmentation from two statistics of the policy:

    Eq. (1)  Sigma_hat = 1/T E sum_t (pi_theta(s_t) - pi*(s_t)) (pi_theta(s_t) - pi*(s_t))^T
    Eq. (2)  Sigma^alpha = alpha / (T tr(Sigma_hat)) Sigma_hat

The paper measures both offline, without an expert in the loop (Sec. IV-D). In this file, in order:

1. `open_loop_sigma` - Sigma_hat_t of Eq. (1) at every other step of the expert data, open loop (Fig. 2a).
2. `blend_rollouts` - closed-loop rollouts partial-denoised toward the expert (Sec. IV-B) at 13 blend
   ratios beta; `settling_error` - how far each settles from the expert's path (Fig. 2b).
3. `equilibrium`, `fit_equilibrium` - Eqs. (8)-(12), x = W s / (s + r (1 - s)) at s = sigma^2_{k_sw},
   fitted for the policy's settling error W and the gain ratio r = K*/K_theta (Fig. 4).
4. `dart_alpha`, `dart_sigma`, `calibrated_sigma`, `pooled_sigma` - alpha = T ||W||^2 (Eq. 13) in
   Eq. (2) gives Sigma^alpha_t (Eq. 14, Fig. 2c) and the pooled Sigma_bar^alpha (Eqs. 15-16, Fig. 2d).
5. `calibrate` - steps 1-4 for one DAgger round, returned as a JSON-serializable `Calibration`.
6. Figures: `plot_method_overview` (Fig. 2) and `plot_blend_fit` (Fig. 4).

Units: radians (rad^2) and env steps (0.1 s); reports and figures add our median steps and the paper's
(0.0176 rad planar, the unit of every sigma and W it quotes; benchmarks/SETUP.md §1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

import envs
from diffusion import expert_runs, label_mask
from partial_denoise import noise_fraction, partial_denoise


# ---- Config ------------------------------------------------------------------------------------------------

@dataclass
class CalibrationConfig:
    """Sec. IV-D as the authors ran it (benchmarks/SETUP.md §5), in our 10 Hz steps."""
    n_act: int                           # steps executed per decision, and compared in Eq. (1)
    n_samples: int = 4                   # policy chunks sampled per step for Eq. (1)
    stride: int = 2                      # steps: Sigma_hat_t at every other valid step (Fig. 2a)
    betas: tuple = tuple(float(b) for b in np.linspace(0.05, 0.90, 13))  # 13 ratios in [0.05, 0.90], once each
    settle_window: int = 16              # steps searched for the nearest expert state
    settle_start: int = 13               # steps: settling error = RMS over steps [settle_start, settle_end] of
    settle_end: int = 40                 # a rollout, after the transient
    diverge_threshold: float = 15.0      # the paper's median steps: a rollout that gets this far from the
                                         # expert's states has diverged and is discarded
    min_rollout_steps: int = 20          # steps: shorter rollouts are discarded
    min_survivors: int = 3               # a ratio with fewer kept rollouts is left out of the fit
    W_bounds: tuple = (1.0, 60.0)        # the paper's median steps: the fitted W's range (authors' bounds)
    r_bounds: tuple = (1e-3, 1e2)        # the gain ratio r = K*/K_theta's range (authors' bounds on R)
    bootstrap: int = 200                 # resamples of the kept rollouts for W's 95 % interval (authors' code)
    bootstrap_seed: int = 0              # seed of the bootstrap's numpy Generator (deterministic interval)
    max_batch: int = 2048                # rows per policy.sample call (memory bound, not a result knob)


def diverge_radius(threshold: float, median_step: float, paper_median_step: float | None) -> float:
    """Radians: `threshold` of the paper's median steps (benchmarks/SETUP.md §5); for an env without one, of ours."""
    return threshold * (median_step if paper_median_step is None else paper_median_step)


def other_units(rad, paper_median_step: float | None, digits: int = 2) -> str:
    """A length in rad (a number, or one per joint) in radians and, where the env has one, in the paper's
    median steps: '0.141 rad = 8.00 paper median steps'."""
    values = np.atleast_1d(np.asarray(rad, dtype=np.float64))
    text = ", ".join(f"{v:.3f}" for v in values) + " rad"
    if paper_median_step is not None:
        text += " = " + ", ".join(f"{v / paper_median_step:.{digits}f}" for v in values) + " paper median steps"
    return text


# ---- The expert's chunk (segments and label steps: the label rule diffusion.expert_runs / label_mask) -------

def expert_chunk(actions: np.ndarray, t: int, horizon: int, end: int | None = None) -> np.ndarray:
    """actions[t:t+H], actions at or past `end` (default: the episode end) replaced by the last one before
    it: past an intervention the recorded actions are the policy's (diffusion.chunk_dataset's padding)."""
    end = len(actions) if end is None else end
    idx = np.minimum(np.arange(t, t + horizon), end - 1)
    return actions[idx]                                                     # (H, dof)


# ---- Step 1: open-loop Sigma_hat_t along the expert data (Eq. 1) -------------------------------------------

@dataclass
class StepCovariances:
    """Per-step covariances with where they were measured."""
    sigma: np.ndarray           # (M, dof, dof)
    episode_index: np.ndarray   # (M,) index into the episode list
    timestep: np.ndarray        # (M,) step t inside that episode
    samples: np.ndarray | None = None   # (M, n_samples, H, dof) the policy's chunks (drawn in Fig. 2a)


def open_loop_sigma(policy, episodes: list[dict], stride: int, n_samples: int,
                    generator: torch.Generator | None = None, max_batch: int = 2048,
                    n_act: int | None = None) -> StepCovariances:
    """Sigma_hat_t of Eq. (1) at every `stride`-th valid label step of the expert data: the mean of d d^T,
    d = sampled chunk - expert chunk, over `n_samples` samples from the recorded obs[t] and the first n_act
    steps (the executed ones; default policy.cfg.n_act). Uncentered: Eq. (1) compares with the expert.
    """
    H = int(policy.cfg.horizon)
    n_act = int(getattr(policy.cfg, "n_act", H)) if n_act is None else int(n_act)
    if stride < 1 or n_samples < 1 or not 1 <= n_act <= H:
        raise ValueError(f"need stride >= 1, n_samples >= 1 and n_act in 1..H = {H}, got stride={stride}, "
                         f"n_samples={n_samples}, n_act={n_act}")
    obs_rows, chunks, ep_idx, steps = [], [], [], []
    for e, ep in enumerate(episodes):
        starts = np.flatnonzero(label_mask(ep["expert"], H))                  # steps with a valid expert label
        actions = np.asarray(ep["action"], dtype=np.float64)
        for start, end in expert_runs(ep["expert"], H):
            for t in starts[(starts >= start) & (starts < end)][::stride]:   # every other step
                obs_rows.append(ep["obs"][t])
                chunks.append(expert_chunk(actions, int(t), H, end))
                ep_idx.append(e)
                steps.append(int(t))
    if not obs_rows:
        raise ValueError(f"no valid expert label of horizon {H} in {len(episodes)} episodes: "
                         "open_loop_sigma needs expert segments of at least H steps")
    # >>> exercise 5: open-loop Sigma_hat_t along the expert data (Eq. 1)
    obs = np.repeat(np.stack(obs_rows).astype(np.float32), n_samples, axis=0)   # (M*n, obs_dim)
    samples = _sample_batched(policy, obs, generator, max_batch).astype(np.float64)
    M, dof = len(obs_rows), samples.shape[-1]
    samples = samples.reshape(M, n_samples, H, dof)                             # (M, n, H, dof)
    d = (samples - np.stack(chunks)[:, None])[:, :, :n_act]                     # (M, n, n_act, dof): executed steps
    # Eq. (1): mean over samples and executed chunk steps of the outer product d d^T
    sigma = np.einsum("mnhi,mnhj->mij", d, d) / (n_samples * n_act)             # (M, dof, dof)
    return StepCovariances(sigma, np.asarray(ep_idx, dtype=np.int64), np.asarray(steps, dtype=np.int64), samples)
    # <<< exercise 5


def _sample_batched(policy, obs: np.ndarray, generator, max_batch: int) -> np.ndarray:
    """policy.sample over rows of obs in slices of at most max_batch rows (a memory bound)."""
    parts = [policy.sample(obs[i:i + max_batch], generator=generator)
             for i in range(0, len(obs), max_batch)]
    return np.concatenate(parts, axis=0)                                    # (B, H, dof)


# ---- Step 2: closed-loop rollouts blended toward the expert by partial denoising, their settling error -----

def blend_schedule(episodes: list[dict], horizon: int, cfg: CalibrationConfig) -> tuple[np.ndarray, list]:
    """The blend rollouts: ratios (B,) and their (episode index, segment). Every ratio of cfg.betas starts
    one rollout from each expert segment long enough to be kept (>= min_rollout_steps; the authors: one per
    source intervention); if none is, from the longest (too short: the fit falls back, and says so)."""
    segs = [(e, seg) for e, ep in enumerate(episodes) for seg in expert_runs(ep["expert"], horizon)]
    segs = sorted(segs, key=lambda item: (-(item[1][1] - item[1][0]), item[0], item[1][0]))   # longest first
    assert segs, f"no expert segment of >= {horizon} steps in {len(episodes)} episodes: nothing to blend"
    segs = [item for item in segs if item[1][1] - item[1][0] >= cfg.min_rollout_steps] or segs[:1]
    jobs = [(beta, seg) for beta in cfg.betas for seg in segs]
    return np.array([b for b, _ in jobs], dtype=np.float64), [seg for _, seg in jobs]


@dataclass
class Rollouts:
    """B closed-loop rollouts, each from the first state of an expert segment (scenarios may differ).
    Entries of the (B, L + 1[, dof]) arrays past a rollout's n_recorded repeat its last one."""
    trajectory: np.ndarray      # (B, L + 1, dof) joint positions
    reference: np.ndarray       # (B, L + 1, dof) time-matched expert joint positions (padded with the last)
    n_steps: np.ndarray         # (B,) length of each rollout's expert segment, in steps (L = max)
    n_recorded: np.ndarray      # (B,) steps executed
    diverged: np.ndarray        # (B,) True if the nearest-state distance ever reached the threshold
    cursor: np.ndarray          # (B, L + 1) expert index the monotone projection assigned to each step
    nearest_error: np.ndarray   # (B, L + 1) distance to the nearest expert state in the window (rad)
    min_steps: int = 0          # rollouts that recorded fewer steps are discarded

    @property
    def discarded(self) -> np.ndarray:
        """True for rollouts that left the expert's route or are too short (Sec. IV-D discards them)."""
        return self.diverged | (self.n_recorded < self.min_steps)          # (B,)


@dataclass
class BlendRollouts:
    """Blended rollouts and the points (s, x) they give for the fit of Eq. (12)."""
    betas: np.ndarray           # (B,) blend ratios
    s: np.ndarray               # (B,) sigma^2_{k_sw} = 1 - alphabar_{k_sw}
    x: np.ndarray               # (B,) settling error (radians, nearest-state distance)
    kept: np.ndarray            # (B,) False for discarded rollouts (diverged, too short)
    rollouts: Rollouts


def blend_rollouts(env, policy, jobs: list[tuple[dict, tuple[int, int]]], betas, cfg: CalibrationConfig,
                   generator: torch.Generator | None, diverge_rad: float) -> BlendRollouts:
    """Sec. IV-D's blended rollouts, one per job (episode, segment) from its first state for its length: each
    decision executes the first cfg.n_act actions of partial_denoise (Eq. 4) toward the expert chunk at the
    rollout's cursor (`advance_cursor`), at betas[b]. A rollout that gets diverge_rad (rad) from the expert's
    states or records < cfg.min_rollout_steps steps is discarded but runs on (Fig. 4 shows it). Contacts are
    not checked (benchmarks/HISTORY.md)."""
    betas = np.asarray(betas, dtype=np.float64).reshape(-1)
    H, n_act, B = int(policy.cfg.horizon), cfg.n_act, len(jobs)
    refs = []                                         # (n + 1, dof) each: the expert states a cursor moves on
    for episode, (start, end) in jobs:
        q_exp = np.asarray(episode["q"], dtype=np.float64)
        n = min(end, len(q_exp) - 1) - start          # the last recorded state is q[T - 1]
        refs.append(q_exp[start:start + n + 1])
    n_steps = np.array([len(r) - 1 for r in refs], dtype=np.int64)
    L = int(n_steps.max())
    reference = np.stack([np.concatenate([r, np.repeat(r[-1:], L + 1 - len(r), axis=0)]) for r in refs])
    traj = np.repeat(reference[:, :1], L + 1, axis=1)                        # (B, L + 1, dof)
    q = reference[:, 0].copy()                                               # (B, dof)
    q_prev = np.stack([np.asarray(ep["q"], dtype=np.float64)[max(start - 1, 0)] for ep, (start, _) in jobs])
    n_recorded = np.zeros(B, dtype=np.int64)
    cursor = np.zeros((B, L + 1), dtype=np.int64)                            # starts on the expert's first state
    nearest_error = np.zeros((B, L + 1))                                     # 0 at the start
    diverged = np.zeros(B, dtype=bool)
    seeds = np.array([int(ep["seed"]) for ep, _ in jobs])

    obs = np.zeros((B, env.obs_dim), dtype=np.float32)
    for seed in np.unique(seeds):                                            # first observations
        env.reset(seed=int(seed))
        rows = np.flatnonzero(seeds == seed)
        obs[rows] = env.make_obs(q[rows], q_prev[rows])                      # (b, obs_dim)
    scenario = seeds.max()                                                   # the seed the env holds now
    recorded = np.stack([np.asarray(ep["obs"][start], dtype=np.float32) for ep, (start, _) in jobs])
    wrong = np.flatnonzero(~np.isclose(obs, recorded, atol=1e-4).all(axis=1))
    if len(wrong):
        raise ValueError(f"the env's scenario for seed {seeds[wrong[0]]} does not reproduce the recorded observation "
                         f"at step {jobs[wrong[0]][1][0]}: the episode was recorded with another env; re-record it")
    for t in range(0, L, n_act):
        rows = np.flatnonzero(n_steps > t)                                   # the live rollouts
        # the expert chunk from where the cursor is on the segment (not from step start + t)
        expert = np.stack([expert_chunk(np.asarray(jobs[b][0]["action"], dtype=np.float64),
                                        jobs[b][1][0] + int(cursor[b, t]), H, jobs[b][1][1])
                           for b in rows])                                   # (b, H, dof)
        chunks = partial_denoise(policy, obs[rows], expert, betas[rows], generator=generator)   # (b, H, dof)
        for row in np.argsort(seeds[rows], kind="stable"):                   # grouped by scenario
            b, chunk = rows[row], chunks[row]
            if seeds[b] != scenario:
                env.reset(seed=int(seeds[b]))
                scenario = seeds[b]
            env.set_state(q[b], q_prev[b])
            for j in range(min(n_act, n_steps[b] - t)):
                env.set_state(env.clip_action(env.q, chunk[j]), env.q)   # env.step's motion, no contact check
                i = t + j + 1
                traj[b, i:] = env.q
                n_recorded[b] = i
                c, err = advance_cursor(env.q, refs[b], int(cursor[b, i - 1]), cfg.settle_window)
                cursor[b, i:], nearest_error[b, i:] = c, err
                diverged[b] |= err >= diverge_rad
            q[b], q_prev[b] = env.q, env.q_prev
            obs[b] = env.make_obs(q[b], q_prev[b])
    roll = Rollouts(traj, reference, n_steps, n_recorded, diverged, cursor, nearest_error, cfg.min_rollout_steps)
    # s = sigma^2_{k_sw} = 1 - alphabar_{k_sw}, k_sw = round(beta K): the noise our sampler injects
    # (the authors' code reads round(beta (K - 1)), its sampler's switch: at most one step apart)
    s = np.asarray(noise_fraction(policy.schedule, betas), dtype=np.float64)   # (B,)
    x = settling_error(roll, cfg.settle_start, cfg.settle_end)
    return BlendRollouts(betas, s, x, ~roll.discarded, roll)


def advance_cursor(q: np.ndarray, expert_q: np.ndarray, cursor: int, window: int) -> tuple[int, float]:
    """The paper's "time-matched" expert state, as the authors' code finds it: one step of a cursor on the
    expert segment that moves toward the nearest state in the window, never back and at most one index a
    step -> (the new cursor, the distance from q to the nearest expert state around it)."""
    j, _ = nearest_expert_state(q, expert_q, cursor, window)
    cursor = min(max(j, cursor), cursor + 1)                                 # monotone, <= 1 index per step
    _, distance = nearest_expert_state(q, expert_q, cursor, window)
    return cursor, distance


def nearest_expert_state(q: np.ndarray, expert_q: np.ndarray, cursor: int, window: int) -> tuple[int, float]:
    """The expert state nearest to q (dof,) among expert_q (m + 1, dof) within window // 2 steps of the
    cursor -> (its index, ||q - q*_j|| in radians)."""
    lo, hi = max(cursor - window // 2, 0), min(cursor + window // 2 + 1, len(expert_q))
    dist = np.linalg.norm(expert_q[lo:hi] - q, axis=-1)                       # (w,)
    j = int(np.argmin(dist))
    return lo + j, float(dist[j])


def settling_error(rollouts: Rollouts, settle_start: int = CalibrationConfig.settle_start,
                   settle_end: int = CalibrationConfig.settle_end) -> np.ndarray:
    """x of Eq. (12) per rollout: sqrt(mean_t e_t^2), e_t the nearest-state distance (rad), over the recorded
    steps t in [settle_start, settle_end] (before: the transient); a rollout that stopped before settle_start
    (discarded anyway) over all its steps."""
    x = np.zeros(len(rollouts.n_recorded))
    for b, n in enumerate(rollouts.n_recorded):
        e = rollouts.nearest_error[b, settle_start:min(settle_end, n) + 1]   # (steps,)
        if len(e) == 0:
            e = rollouts.nearest_error[b, 1:n + 1]
        if len(e):
            x[b] = math.sqrt(float(np.mean(e ** 2)))
    return x


@dataclass
class RatioCells:
    """The fit's points: per blend ratio, the RMS settling error of its kept rollouts (the authors' cells)."""
    betas: np.ndarray           # (R,) the distinct blend ratios
    s: np.ndarray               # (R,) their sigma^2_{k_sw}
    x: np.ndarray               # (R,) RMS of the kept rollouts' settling errors (radians; NaN: none kept)
    n: np.ndarray               # (R,) kept rollouts
    spread: np.ndarray          # (R,) SD of the kept settling errors (radians; 0 with fewer than 2)
    fitted: np.ndarray          # (R,) bool: n >= min_survivors, the ratios the fit uses


def ratio_cells(betas, s, x, kept, min_survivors: int = CalibrationConfig.min_survivors) -> RatioCells:
    """Average the blended rollouts per ratio, as the authors do: x_beta = sqrt(mean x_i^2) over the kept
    rollouts i at ratio beta; a ratio with fewer than min_survivors kept rollouts is not fitted."""
    betas, s, x, kept = (np.asarray(a) for a in (betas, s, x, kept))
    unique = np.unique(betas)
    cells = [(s[betas == b][0], x[(betas == b) & kept]) for b in unique]
    rms = np.array([math.sqrt(float(np.mean(v ** 2))) if len(v) else math.nan for _, v in cells])
    n = np.array([len(v) for _, v in cells], dtype=np.int64)
    spread = np.array([float(np.std(v, ddof=1)) if len(v) > 1 else 0.0 for _, v in cells])
    return RatioCells(unique.astype(np.float64), np.array([c[0] for c in cells], dtype=np.float64), rms, n,
                      spread, n >= min_survivors)


# ---- Step 3: the equilibrium of expert and policy (Eqs. 8-12) and its fit for W ----------------------------

def equilibrium(s, W, r):
    """Eq. (12): settling error of the blend u = s u_theta + (1 - s) u* (Eq. 8) with u* = K* (-x) (Eq. 9),
    u_theta = K_theta (W - x) (Eq. 10) at rest, u = 0 (Eq. 11); r = K*/K_theta > 0, x(0) = 0, x(1) = W."""
    s = np.asarray(s, dtype=np.float64)
    if np.any((s < 0) | (s > 1)) or not np.all(np.isfinite(s)) or not r > 0:
        raise ValueError(f"need s = sigma^2_k_sw in [0, 1] and the gain ratio r = K*/K_theta > 0, got s = {s}, r = {r}")
    # >>> exercise 6: the blend equilibrium and its fit for W (Eqs. 8-12)
    # Eq. (12): x = W s / (s + r (1 - s))
    return np.asarray(W, dtype=np.float64) * s / (s + r * (1.0 - s))
    # <<< exercise 6


@dataclass
class EquilibriumFit:
    """fit_equilibrium's result."""
    W: float                    # settling error of the unguided policy (same units as x)
    r: float                    # gain ratio K*/K_theta
    n_points: int               # points used
    rms_residual: float         # RMS of x - equilibrium(s, W, r) over the points used


def fit_equilibrium(s, x, r_bounds: tuple = (1e-3, 1e3), n_grid: int = 241) -> EquilibriumFit:
    """Least squares for W and r > 0 in Eq. (12) from the finite points (s_i, x_i), as the authors' curve_fit:
    W in closed form for each r (`_best_W`), r on a log grid over r_bounds, then golden section in log r between
    the best grid point's neighbours. x is the norm of the joint deviation (with isotropic gains
    ||x|| = ||W|| g(s), Eq. 12 again; Eq. 14 needs only ||W||^2)."""
    s = np.asarray(s, dtype=np.float64).reshape(-1)
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    ok = np.isfinite(s) & np.isfinite(x)
    s, x = s[ok], x[ok]
    if len(s) < 3 or len(np.unique(s[s > 0])) < 2:
        raise ValueError(f"fit_equilibrium needs >= 3 finite points with >= 2 distinct s > 0, "
                         f"got {len(s)} points with s = {np.round(s, 4).tolist()}")
    if not np.any(x != 0):
        return EquilibriumFit(0.0, 1.0, len(s), 0.0)
    # >>> exercise 6: the blend equilibrium and its fit for W (Eqs. 8-12)
    w = np.ones_like(x)                                                # (n,) every point weighs the same
    log_r_grid = np.linspace(math.log(r_bounds[0]), math.log(r_bounds[1]), n_grid)   # (G,)
    _, sse = _best_W(s, x, w, np.exp(log_r_grid))                     # closed-form W at every r: its SSE (G,)
    i = int(np.argmin(sse))                                            # the grid's best r ...
    a, b = log_r_grid[max(i - 1, 0)], log_r_grid[min(i + 1, n_grid - 1)]
    log_r = _golden_min(lambda v: float(_best_W(s, x, w, np.exp([v]))[1][0]), a, b)   # ... refined between its
    W, r = float(_best_W(s, x, w, np.exp([log_r]))[0][0]), math.exp(log_r)          # neighbours
    res = x - equilibrium(s, W, r)                                     # residuals of Eq. (12)
    return EquilibriumFit(W, r, len(s), math.sqrt(float(np.mean(res ** 2))))
    # <<< exercise 6


def _best_W(s, x, w, r):
    """For each r in r (G,), the weighted least-squares W (closed form) and its weighted SSE."""
    # >>> exercise 6: the blend equilibrium and its fit for W (Eqs. 8-12)
    g = s[None] / (s[None] + r[:, None] * (1.0 - s[None]))                   # (G, n)
    W = np.sum(w * g * x, axis=1) / np.maximum(np.sum(w * g * g, axis=1), 1e-300)
    sse = np.sum(w * (x[None] - W[:, None] * g) ** 2, axis=1)
    return W, sse
    # <<< exercise 6


def _golden_min(f, a: float, b: float, n_iter: int = 60) -> float:
    """Minimizer of a unimodal f on [a, b] by golden-section search."""
    phi = (math.sqrt(5) - 1) / 2
    c, d = b - phi * (b - a), a + phi * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(n_iter):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - phi * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + phi * (b - a)
            fd = f(d)
    return (a + b) / 2


def W_interval(betas, s, x, kept, W_range: tuple, cfg: CalibrationConfig) -> tuple[float, float]:
    """W's 95 % bootstrap interval: cfg.bootstrap resamples of the kept rollouts within each ratio (with
    replacement), each averaged per ratio (`ratio_cells`) and fitted like W, held within W_range (radians)."""
    betas, s, x, kept = (np.asarray(a) for a in (betas, s, x, kept))
    rng = np.random.default_rng(cfg.bootstrap_seed)
    groups = [np.flatnonzero((betas == b) & kept) for b in np.unique(betas)]
    Ws = []
    for _ in range(cfg.bootstrap):
        idx = np.concatenate([g[rng.integers(0, len(g), len(g))] for g in groups if len(g)])
        cells = ratio_cells(betas[idx], s[idx], x[idx], np.ones(len(idx), dtype=bool), cfg.min_survivors)
        Ws.append(fit_equilibrium(cells.s[cells.fitted], cells.x[cells.fitted], r_bounds=cfg.r_bounds).W)
    lo, hi = np.percentile(np.clip(Ws, *W_range), [2.5, 97.5])
    return float(lo), float(hi)


# ---- Step 4: scale Sigma_hat to the closed-loop error (Eqs. 2, 13-16) --------------------------------------

def dart_alpha(W, T: int) -> float:
    """Eq. (13): DART's alpha approximated by the settling error, alpha = T ||W||^2."""
    # >>> exercise 7: Sigma^alpha_t and the pooled Sigma_bar^alpha (Eqs. 2, 13-16)
    return T * float(np.sum(np.square(W)))
    # <<< exercise 7


def dart_sigma(sigma_hat: np.ndarray, alpha: float, T: int) -> np.ndarray:
    """Eq. (2): Sigma^alpha = alpha / (T tr(Sigma_hat)) Sigma_hat (per matrix of a (..., d, d) stack)."""
    # >>> exercise 7: Sigma^alpha_t and the pooled Sigma_bar^alpha (Eqs. 2, 13-16)
    sigma_hat = np.asarray(sigma_hat, dtype=np.float64)
    tr = np.trace(sigma_hat, axis1=-2, axis2=-1)[..., None, None]
    return alpha / (T * tr) * sigma_hat
    # <<< exercise 7


def calibrated_sigma(sigma_hat: np.ndarray, W) -> np.ndarray:
    """Eq. (14): Sigma^alpha_t = ||W||^2 / tr(Sigma_hat_t) Sigma_hat_t, for a (..., d, d) stack: Eq. (2) with
    alpha from Eq. (13), T cancels; W the scalar norm or a vector. A step with tr(Sigma_hat_t) = 0 has no
    direction to keep: it gets ||W||^2 / d I (the same trace)."""
    sigma_hat = np.asarray(sigma_hat, dtype=np.float64)
    # >>> exercise 7: Sigma^alpha_t and the pooled Sigma_bar^alpha (Eqs. 2, 13-16)
    d = sigma_hat.shape[-1]
    zero = np.trace(sigma_hat, axis1=-2, axis2=-1)[..., None, None] <= 1e-300   # (..., 1, 1)
    # Eq. (14): Eq. (2) with alpha = T ||W||^2 (Eq. 13); T cancels, so T = 1
    return dart_sigma(np.where(zero, np.eye(d), sigma_hat), dart_alpha(W, 1), 1)
    # <<< exercise 7


def pooled_sigma(sigma_hats: np.ndarray, W) -> np.ndarray:
    """Eqs. (15)-(16): Sigma_bar = mean_m Sigma_hat_m, then Sigma_bar^alpha = ||W||^2/tr(Sigma_bar) Sigma_bar."""
    sigma_hats = np.asarray(sigma_hats, dtype=np.float64)
    if sigma_hats.ndim != 3 or len(sigma_hats) == 0:
        raise ValueError(f"sigma_hats must be a non-empty (M, d, d) stack, got shape {sigma_hats.shape}")
    # >>> exercise 7: Sigma^alpha_t and the pooled Sigma_bar^alpha (Eqs. 2, 13-16)
    sigma_bar = sigma_hats.mean(axis=0)                                      # Eq. (15)
    return calibrated_sigma(sigma_bar, W)                                    # Eq. (16)
    # <<< exercise 7


# ---- One calibration per DAgger round, and its record ------------------------------------------------------

def calibrate(env, policy, episodes: list[dict], median_step: float, cfg: CalibrationConfig,
              generator: torch.Generator | None = None, log=None) -> Calibration:
    """Sec. IV-D for one round on its intervention episodes (median_step in rad; log: an optional callable(str)).
    Without a fit (fewer than 3 ratios with min_survivors kept rollouts) W falls back to the open-loop error,
    ||W||^2 = tr(Sigma_bar) (Sigma^alpha = Sigma_hat unscaled), r is None and fit_note says "FALLBACK"."""
    paper_unit = env.paper_median_step                                      # rad, or None
    say = log or (lambda msg: None)

    # Step 1 (Fig. 2a): Sigma_hat_t open loop along the expert data, Eq. (1)
    steps = open_loop_sigma(policy, episodes, cfg.stride, cfg.n_samples, generator, cfg.max_batch, cfg.n_act)
    say(f"Sigma_hat at {len(steps.sigma)} anchors; blended rollouts next")

    # Step 2 (Fig. 2b): blended rollouts, one per ratio from every long enough segment, all batched,
    # averaged per ratio (the authors' cells)
    blend_beta, chosen = blend_schedule(episodes, int(policy.cfg.horizon), cfg)
    blend = blend_rollouts(env, policy, [(episodes[e], seg) for e, seg in chosen], blend_beta, cfg, generator,
                           diverge_radius(cfg.diverge_threshold, median_step, paper_unit))
    s, x, kept = blend.s, blend.x, blend.kept
    cells = ratio_cells(blend_beta, s, x, kept, cfg.min_survivors)
    say(f"{int(kept.sum())} of {len(kept)} blended rollouts kept; {int(cells.fitted.sum())} of {len(cells.s)} "
        f"ratios with >= {cfg.min_survivors} of them; fitting W")

    # Step 3 (Fig. 4): fit Eq. (12) on the ratios' averages (least squares, as the authors' curve_fit); W (x
    # extrapolated to s = 1) held within the authors' bounds, in radians
    unit = median_step if paper_unit is None else paper_unit
    W_range = (cfg.W_bounds[0] * unit, cfg.W_bounds[1] * unit)
    try:
        fit = fit_equilibrium(cells.s[cells.fitted], cells.x[cells.fitted], r_bounds=cfg.r_bounds)
    except ValueError as err:
        W = math.sqrt(float(np.trace(steps.sigma.mean(axis=0))))          # ||W||^2 = tr(Sigma_bar)
        r, note, W_ci = None, f"FALLBACK: no fit, W from the open-loop error ({err})", None
        say(f"!! {note}")
    else:
        r, W, note = fit.r, min(max(fit.W, W_range[0]), W_range[1]), "fit"
        if W != fit.W:
            note = (f"fit, W at the fit's bound {W / unit:.0f} (the fit extrapolated to {fit.W / unit:.1f}; "
                    "units: the paper's median steps)")
        W_ci = W_interval(blend_beta, s, x, kept, W_range, cfg)

    # Step 4 (Fig. 2c, 2d): Eq. (14) per step, Eqs. (15)-(16) pooled
    return Calibration(W=W, r=r, fit_note=note, median_step=float(median_step),
                       sigma_hat=steps.sigma, sigma_alpha=calibrated_sigma(steps.sigma, W),
                       episode_index=steps.episode_index, timestep=steps.timestep,
                       pooled=pooled_sigma(steps.sigma, W), blend_beta=blend_beta, blend_s=s, blend_x=x,
                       blend_kept=kept, blend_episode=np.array([e for e, _ in chosen], dtype=np.int64),
                       blend_start=np.array([seg[0] for _, seg in chosen], dtype=np.int64), W_ci=W_ci,
                       paper_median_step=paper_unit)


@dataclass
class Calibration:
    """Everything one round's calibration measured (radians; `report` gives median steps)."""
    W: float                        # ||W||: settling error of the unguided policy (Eq. 12), radians
    r: float | None                 # fitted gain ratio K*/K_theta; None when the fit fell back
    fit_note: str                   # "fit" or "FALLBACK: <why>" (see `calibrate`)
    median_step: float              # median per-step joint displacement of the base demos (radians)
    sigma_hat: np.ndarray           # (M, dof, dof) open-loop Sigma_hat_t (Eq. 1)
    sigma_alpha: np.ndarray         # (M, dof, dof) per-step Sigma^alpha_t (Eq. 14)
    episode_index: np.ndarray       # (M,) episode of each step
    timestep: np.ndarray            # (M,) step inside that episode
    pooled: np.ndarray              # (dof, dof) pooled Sigma_bar^alpha (Eq. 16)
    blend_beta: np.ndarray          # (B,) blend ratios of the rollouts
    blend_s: np.ndarray             # (B,) their sigma^2_{k_sw}
    blend_x: np.ndarray             # (B,) their settling errors (radians)
    blend_kept: np.ndarray          # (B,) False where the rollout was discarded (diverged or too short)
    blend_episode: np.ndarray       # (B,) episode of each blend rollout's segment
    blend_start: np.ndarray         # (B,) first step of that segment
    sigma_per_joint: np.ndarray | None = None   # (dof,) sqrt(diag pooled) in median steps (derived)
    W_ci: tuple | None = None       # (lo, hi) 95 % bootstrap interval of W, radians; None on fallback
    paper_median_step: float | None = None   # the env's paper median step (rad); None: it has none

    def __post_init__(self):
        if self.sigma_per_joint is None:
            self.sigma_per_joint = sigma_in_median_steps(self.pooled, self.median_step)
        if self.W_ci is not None:
            self.W_ci = (float(self.W_ci[0]), float(self.W_ci[1]))         # JSON gives a list


def sigma_in_median_steps(sigma: np.ndarray, median_step: float) -> np.ndarray:
    """Per-joint standard deviation sqrt(diag Sigma) in units of the median per-step displacement."""
    return np.sqrt(np.diagonal(np.asarray(sigma, dtype=np.float64), axis1=-2, axis2=-1)) / median_step


# ---- Figures -----------------------------------------------------------------------------------------------

def _pyplot():
    """matplotlib.pyplot on the file-only Agg backend."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_method_overview(env, episode: dict, calibration: Calibration, policy, path,
                         betas=(0.2, 0.5, 0.7, 0.9), n_samples: int = 6, stride: int = 6,
                         generator: torch.Generator | None = None) -> None:
    """Fig. 2 (a)-(d) on the episode's longest expert segment: Sigma_hat_t at every `stride`-th label step,
    blended rollouts at `betas`, both with the policy's n_act. Covariances are 2-sigma ellipses of
    J Sigma J^T at the end effector (env.draw_noise_ellipses); a 3-D env in top view (x, y), with its goal.
    """
    plt, c, planar = _pyplot(), calibration, env.dim == 2
    env.reset(seed=int(episode["seed"]))
    cfg = CalibrationConfig(n_samples=n_samples, n_act=int(policy.cfg.n_act), stride=stride)
    q_exp = np.asarray(episode["q"], dtype=np.float64)
    start, end = max(expert_runs(episode["expert"], int(policy.cfg.horizon)), key=lambda se: se[1] - se[0])
    # Eq. (1) on that segment alone, then the blended rollouts from its first state
    t = np.arange(len(episode["expert"]))
    segment = dict(episode, expert=(t >= start) & (t < end))
    open_loop = open_loop_sigma(policy, [segment], stride, n_samples, generator, n_act=cfg.n_act)
    steps = open_loop.timestep                                               # (m,)
    radius = diverge_radius(cfg.diverge_threshold, c.median_step, c.paper_median_step)
    blend = blend_rollouts(env, policy, [(episode, (start, end))] * len(betas), betas, cfg, generator, radius)

    # each panel: a planar env's scene (env.render at the segment's first state) or a 3-D env's goal, the expert
    expert_path = env.ee(q_exp[start:end])[:, :2]                            # (n, 2): the plane or the top view
    fig, axes = plt.subplots(1, 4, figsize=(18, 5.8))
    titles = [r"(a) open-loop samples, $\hat\Sigma_t$ (Eq. 1)", r"(b) blended rollouts, partial denoising at $\beta$",
              r"(c) per-step $\Sigma^\alpha_t$ (Eq. 14)", r"(d) pooled $\bar\Sigma^\alpha$ (Eq. 16)"]
    for ax, title in zip(axes, titles):
        if planar:                                   # the planar render labels its axes in metres itself
            env.render(ax, q=q_exp[start], alpha=0.5)
        else:
            ax.plot(*env.goal[:2], marker="*", markersize=14, color="tab:green", linestyle="none", label="goal")
            ax.set(aspect="equal", xlabel="x (m)", ylabel="y (m)")
        ax.plot(*expert_path.T, color="tab:blue", lw=2, label="expert intervention")
        ax.set_title(title, fontsize=10)

    # (a) each sampled chunk's executed steps from its state
    for t, chunks in zip(steps, open_loop.samples):
        for chunk in chunks:
            axes[0].plot(*env.ee(np.concatenate([q_exp[t][None], chunk[:cfg.n_act]]))[:, :2].T,
                         color="tab:orange", lw=0.7, alpha=0.6)
    axes[0].plot([], [], color="tab:orange", label="policy chunks")

    # (b) the blended rollouts, dashed where discarded, with their settling error x
    paths = [env.ee(blend.rollouts.trajectory[b])[:, :2] for b in range(len(blend.betas))]    # (L + 1, 2) each
    colors = plt.cm.viridis(np.linspace(0.1, 0.9, len(blend.betas)))
    for b, (beta, color) in enumerate(zip(blend.betas, colors)):
        axes[1].plot(*paths[b][:blend.rollouts.n_recorded[b] + 1].T, color=color, lw=1.5,
                     linestyle="-" if blend.kept[b] else "--",
                     label=rf"$\beta$={beta:.2f}, x={blend.x[b] / c.median_step:.1f} med. steps"
                           + ("" if blend.kept[b] else " (discarded)"))

    # (a) Sigma_hat_t, (c) Sigma^alpha_t = Sigma_hat_t scaled to ||W||^2 (Eq. 14), (d) the pooled Sigma_bar^alpha
    for ax, cov, color in ((axes[0], open_loop.sigma, "tab:orange"),
                           (axes[2], calibrated_sigma(open_loop.sigma, c.W), "tab:red"),
                           (axes[3], np.repeat(c.pooled[None], len(steps), axis=0), "tab:purple")):
        env.draw_noise_ellipses(ax, q_exp[steps], cov, color, alpha=0.35)

    # per-joint sigma and the legends below the panels (outside the data), a common zoom on the intervention
    per_joint = ", ".join(f"{v:.1f}" for v in c.sigma_per_joint)
    axes[3].text(0.5, -0.14, f"per-joint sigma: {per_joint} median steps\n= "
                 f"{other_units(np.sqrt(np.diag(c.pooled)), c.paper_median_step, 1)}",
                 transform=axes[3].transAxes, fontsize=8, ha="center", va="top")
    for ax in axes[:2]:
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), frameon=False)
    fig.suptitle(f"Policy calibration on scenario {episode['seed']} (W = {c.W / c.median_step:.2f} median steps = "
                 f"{other_units(c.W, c.paper_median_step)}; ellipses 2 sigma" + ("" if planar else "; top view") + ")")
    goal = np.empty((0, 2)) if planar else env.goal[None, :2]
    env.square_view(list(axes), np.concatenate([expert_path, *paths, goal]), 0.06)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")  # the legends below the panels stay in the picture
    plt.close(fig)


def plot_blend_fit(calibration: Calibration, median_step: float | None, path) -> None:
    """Fig. 4: settling error vs sigma^2_{k_sw} in median steps (median_step rad; None: the calibration's):
    every blended rollout (kept: dots; discarded: crosses), the per-ratio RMS of the kept ones with their
    spread (fitted: filled; too few kept: open), the fitted Eq. (12), W and its 95 % bootstrap interval."""
    plt, c, min_survivors = _pyplot(), calibration, CalibrationConfig.min_survivors
    unit = c.median_step if median_step is None else median_step
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    kept = c.blend_kept
    ax.scatter(c.blend_s[kept], c.blend_x[kept] / unit, s=9, color="C0", alpha=0.35, zorder=2,
               label=f"kept rollouts ({int(kept.sum())})")
    # the axis ends a little above the divergence radius, so that the fit and W are what one sees; a discarded
    # rollout whose error runs past the top is drawn at the top edge
    radius = diverge_radius(CalibrationConfig.diverge_threshold, c.median_step, c.paper_median_step) / unit
    top = 1.25 * max(radius, float(np.max(c.blend_x[kept], initial=0.0)) / unit, c.W / unit)
    ax.axhline(radius, color="C3", linestyle=":", linewidth=1,
               label=f"divergence radius ({CalibrationConfig.diverge_threshold:g} paper median steps)")
    if np.any(~kept):
        ax.scatter(c.blend_s[~kept], np.minimum(c.blend_x[~kept] / unit, top * 0.98), s=12, marker="x",
                   color="C3", alpha=0.5, zorder=2,
                   label=f"discarded: crossed the radius, or too short ({int((~kept).sum())}; "
                         f"beyond the axis: at its top)")
    cells = ratio_cells(c.blend_beta, c.blend_s, c.blend_x, kept, min_survivors)
    for fitted, face in ((cells.fitted, "C0"), (~cells.fitted & (cells.n > 0), "white")):
        if fitted.any():
            ax.errorbar(cells.s[fitted], cells.x[fitted] / unit, yerr=cells.spread[fitted] / unit, fmt="o",
                        ms=7, mfc=face, mec="C0", ecolor="C0", capsize=3, zorder=3,
                        label="per-ratio RMS of the kept ± SD" + (" (fitted)" if face == "C0" else
                                                                 f" (< {min_survivors} kept: not fitted)"))
    if c.r is not None:
        s = np.linspace(0.0, 1.0, 201)
        ax.plot(s, equilibrium(s, c.W, c.r) / unit, color="C1",
                label=f"Eq. (12) fit, r = K*/K$_\\theta$ = {c.r:.3g}")
    W = c.W / unit
    ax.axhline(W, color="k", linestyle="--", linewidth=1,
               label=f"W = {W:.2f} median steps = {other_units(c.W, c.paper_median_step)}"
                     + ("" if c.r is not None else " (FALLBACK: no fit)"))
    if c.W_ci is not None:                                                       # an error bar at s = 1
        lo, hi = c.W_ci[0] / unit, c.W_ci[1] / unit
        ax.errorbar([1.0], [W], yerr=[[max(W - lo, 0.0)], [max(hi - W, 0.0)]], fmt="o", color="k", capsize=4,
                    clip_on=False, zorder=4, label=f"W, 95 % bootstrap interval {lo:.2f}–{hi:.2f}")
    # the right axis: the paper's median steps (the unit of its Fig. 4 and W = 8.0), or rad without one
    scale = unit / (c.paper_median_step or 1.0)
    right = ax.secondary_yaxis("right", functions=(lambda y: y * scale, lambda y: y / scale))
    right.set_ylabel("[the paper's median steps]" if c.paper_median_step else "[rad]")
    ax.set(ylim=(0, top), xlim=(0, 1.04), title="Blend fit for W (paper Fig. 4)",   # x: room for W's error bar
           xlabel=r"noise fraction $\sigma^2_{k_{sw}} = 1 - \bar\alpha_{k_{sw}}$",
           ylabel="settling error [our median steps]")
    # the legend below the axes, in two columns: off the data, and the plot keeps the figure's width
    ax.legend(fontsize=7.5, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    fig.savefig(path, dpi=150, bbox_inches="tight")  # the legend below the axes stays in the picture
    plt.close(fig)


# ---- Demo: a small policy trained on 100 oracle demonstrations, calibrated; Figs. 2 and 4 in this folder ---
# (the oracle is imported here only: the method itself needs no expert in the loop)

if __name__ == "__main__":
    import oracle
    from diffusion import DiffusionPolicy, PolicyConfig, TrainConfig, chunk_dataset, train

    env = envs.make_env("planar")
    expert = oracle.Oracle(oracle.OracleConfig(seed=0, n_attempts=1))
    episodes = [expert.demonstrate(env, seed) for seed in env.train_seeds(100)]
    unit = envs.median_step(episodes)
    policy = DiffusionPolicy(PolicyConfig(obs_dim=env.obs_dim, dof=env.dof, horizon=16, n_act=8, K=100,
                                          down_dims=(32, 64, 128)))
    train(policy, *chunk_dataset(episodes, 16), TrainConfig(steps=1000, warmup_steps=100, log_every=250))
    calibration = calibrate(env, policy, episodes[:8], unit, CalibrationConfig(n_act=8),
                            torch.Generator().manual_seed(0))
    print(f"W = {calibration.W / unit:.2f} median steps ({calibration.fit_note}); pooled Sigma_bar^alpha per-joint "
          f"sigma {np.round(calibration.sigma_per_joint, 2)} median steps")
    plot_blend_fit(calibration, unit, "fig4_blend_fit.png")
    plot_method_overview(env, episodes[int(calibration.blend_episode[0])], calibration, policy,
                         "fig2_method_overview.png", generator=torch.Generator().manual_seed(1))
