"""Partial denoising: blend an expert action chunk with the policy's own prior (paper Sec. IV-B, IV-C, Fig. 3).

Paper map (the paper), in the paper's order:
  - linear interpolation, Eq. (3) ................................ lerp_blend
  - switching step k_sw = ToInteger(beta K) (Sec. IV-B) .......... switch_step
  - partial diffusion as the learned interpolator f_theta, Eq. (4),
    extended to chunks (Sec. IV-C: flatten (H, dof) into one vector) partial_denoise (Eqs. 5-6 in diffusion.py)
  - SDEdit bound, Eq. (7) ........................................ sdedit_bound
  - sigma^2_{k_sw} = 1 - alphabar_{k_sw} (Sec. IV-D) ............. noise_fraction
  - Fig. 3 (samples at several beta at one state) ................ plot_partial_denoising

Partial diffusion (Yoneda et al., "To the noise and back"; SDEdit, Meng et al.): diffuse the expert chunk
forward to an intermediate noise level with Eq. (5), then let the policy run the reverse process Eq. (6)
back to a clean chunk. beta = 0 keeps the expert chunk, beta = 1 forgets it (unguided sampling).

Index convention (where public code for this method is off by one): beta picks the paper's step
k_sw = ToInteger(beta K) in 0..K; forward, a_{k_sw} = sqrt(alphabar_{k_sw}) a* + sqrt(1 - alphabar_{k_sw}) eps
(Eq. 5 in closed form); reverse, Eq. (6) at paper steps k_sw, ..., 1. diffusion.py's code level c is paper step
c + 1: q_sample at k_sw - 1, then reverse_process from code level k_sw - 1 down to 0, so the first reverse step
gets the noise level the chunk holds. k_sw = 0 returns the expert chunk unchanged.
"""

import math

import numpy as np
import torch

from diffusion import check_array, q_sample


def _check_beta(beta):
    """beta as a float64 array; ValueError unless every entry is a finite ratio in [0, 1]."""
    b = np.asarray(beta, dtype=np.float64)
    if not np.all((b >= 0) & (b <= 1)):  # NaN fails too
        raise ValueError(f"blend ratio beta must be in [0, 1] (and not NaN), got {beta!r}")
    return b


# ---- Blending: Eq. (3), then the learned interpolator of Eq. (4) by partial diffusion ----------------------
def lerp_blend(a_policy, a_expert, beta):
    """Eq. (3): a_lerp = beta a_policy + (1 - beta) a_expert (beta = 0: the expert, 1: the policy)."""
    b = _check_beta(beta)
    a_policy, a_expert = np.asarray(a_policy, dtype=np.float64), np.asarray(a_expert, dtype=np.float64)
    if a_policy.shape != a_expert.shape:
        raise ValueError(f"a_policy {a_policy.shape} and a_expert {a_expert.shape} must have the same shape")
    # >>> exercise 4: linear blend (Eq. 3), noise fraction sigma^2_k_sw and the SDEdit bound (Eq. 7)
    if b.ndim == 1:                                         # per-row beta for a batch (B, ...)
        b = b.reshape((-1,) + (1,) * (a_policy.ndim - 1))
    # Eq. (3)
    return b * a_policy + (1.0 - b) * a_expert
    # <<< exercise 4


def switch_step(beta, K):
    """k_sw = ToInteger(beta K) in 0..K (paper step number), for a scalar or an array of betas. ToInteger rounds
    halves up, floor(beta K + 1/2): not floor, as 0.29 * 100 = 28.999999999999996; not Python's round-half-to-even,
    so that k_sw is monotone in beta."""
    b = _check_beta(beta)
    assert isinstance(K, (int, np.integer)) and K >= 1, K
    # >>> exercise 3: partial denoising and its index convention (Eq. 4, Sec. IV-B/C)
    k_sw = np.floor(b * K + 0.5).astype(np.int64)
    return int(k_sw) if k_sw.ndim == 0 else k_sw
    # <<< exercise 3


def partial_denoise(policy, obs, expert_chunk, beta, generator=None, use_ema=True):
    """a_hat = f_theta(a*, beta | o) (Eq. 4) by partial diffusion: obs (B, obs_dim), expert_chunk (B, H, dof),
    beta a scalar or (B,) -> (B, H, dof) float64, joint units. Index convention: the module docstring. Noise in
    policy.sample's per-row layout: beta = 1 is policy.sample up to the sqrt(alphabar_K) a* term."""
    cfg = policy.cfg
    obs = check_array("obs", obs, (None, cfg.obs_dim))
    B = obs.shape[0]
    expert_chunk = check_array("expert_chunk", expert_chunk, (B, cfg.horizon, cfg.dof))
    beta = _check_beta(beta)
    if beta.ndim > 1 or (beta.ndim == 1 and len(beta) != B):
        raise ValueError(f"beta must be a scalar or have shape ({B},), got shape {beta.shape}")
    k_sw = np.broadcast_to(switch_step(beta, cfg.K), (B,))   # (B,) paper steps in 0..K
    dev = policy.device
    with torch.inference_mode():
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=dev)
        obs_norm = policy.normalize_obs(obs_t)
        a_star = policy.normalize_actions(torch.as_tensor(expert_chunk, dtype=torch.float32, device=dev), obs_t)
        noise = policy.draw_noise(B, generator)                  # (B, K + 1, H, dof)
        # >>> exercise 3: partial denoising and its index convention (Eq. 4, Sec. IV-B/C)
        k_start = torch.as_tensor(k_sw - 1, device=dev)          # code level of a_{k_sw}; -1 = no step
        # Step 1, Eq. (5) in closed form: the expert chunk diffused to paper level k_sw (code k_sw - 1).
        diffused = q_sample(policy.schedule, a_star, k_start.clamp(min=0), noise[:, 0])
        a_start = torch.where((k_start >= 0).view(B, 1, 1), diffused, a_star)
        # Step 2, Eq. (6) k_sw times: code levels k_sw - 1, ..., 0.
        a_hat = policy.reverse_process(a_start, k_start, obs_norm, noise[:, 1:], use_ema)
        # <<< exercise 3
        out = policy.unnormalize_actions(a_hat.double(), obs_t.double()).cpu().numpy()
    keep = k_sw == 0
    out[keep] = expert_chunk[keep]                               # beta ~ 0: the expert chunk, bit for bit
    return out


# ---- How far the blend may move: Eq. (7) and the noise fraction sigma^2_{k_sw} (Sec. IV-D) -----------------
def sdedit_bound(sigma2, bound, d, delta):
    """Eq. (7): with probability >= 1 - delta, ||a* - a_hat||^2 <= this, for normalized actions in [-1, 1]^d
    and ||eps_theta|| <= bound (SDEdit, Meng et al., Theorem 1). The scale of the blend, sigma^2_{k_sw}, not a
    guarantee for this sampler: it counts only the forward noise (test_eq7_counts_only_the_forward_noise)."""
    sigma2 = np.asarray(sigma2, dtype=np.float64)
    if not (np.all((sigma2 >= 0) & (sigma2 <= 1)) and bound >= 0 and d >= 1 and 0 < delta < 1):
        raise ValueError(f"need sigma2 in [0, 1], bound >= 0, d >= 1, 0 < delta < 1; "
                         f"got {sigma2!r}, {bound}, {d}, {delta}")
    # >>> exercise 4: linear blend (Eq. 3), noise fraction sigma^2_k_sw and the SDEdit bound (Eq. 7)
    log_delta = np.log(delta)
    # Eq. (7)
    return sigma2 * (bound * sigma2 + d + 2.0 * np.sqrt(-d * log_delta) - 2.0 * log_delta)
    # <<< exercise 4


def _alphabar_with_zero(schedule):
    """(K + 1,) float64: alphabar_k for paper steps k = 0..K, with alphabar_0 = 1 (the clean chunk)."""
    return np.concatenate([[1.0], schedule.alphas_cumprod.double().cpu().numpy()])


def noise_fraction(schedule, beta):
    """sigma^2_{k_sw} = 1 - alphabar_{k_sw} in [0, 1]: the share of noise in the diffused expert chunk."""
    # >>> exercise 4: linear blend (Eq. 3), noise fraction sigma^2_k_sw and the SDEdit bound (Eq. 7)
    return 1.0 - _alphabar_with_zero(schedule)[switch_step(beta, schedule.K)]
    # <<< exercise 4


# ---- Fig. 3 ------------------------------------------------------------------------------------------------
def plot_partial_denoising(env, policy, obs, expert_chunk, betas, path, generator=None, q=None, n_samples=16):
    """The paper's Fig. 3: at one state (obs (obs_dim,), joints q, default env.q), the expert chunk (H, dof) and
    n_samples partial-denoising samples per beta and unguided (beta = 1) as end-effector paths (no mean path: at
    large beta the samples split between modes), in the planar env's plane or a 3-D env's top view (x, y in m)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    obs, expert_chunk = np.asarray(obs, dtype=np.float32), np.asarray(expert_chunk, dtype=np.float64)
    assert obs.ndim == 1 and expert_chunk.ndim == 2 and env.dim in (2, 3), (obs.shape, expert_chunk.shape, env.dim)
    planar = env.dim == 2
    levels = [float(b) for b in _check_beta(np.atleast_1d(betas))] + [1.0]      # and unguided
    names = [rf"$\beta$ = {b:.2f}" for b in levels[:-1]] + [r"unguided policy, $\beta$ = 1"]
    q = np.asarray(env.q if q is None else q, dtype=np.float64)
    start = env.ee(q[None])[:, :2]                              # (1, 2): the plane, or the top view (x, y)
    rows = n_samples * len(levels)
    samples = partial_denoise(policy, np.repeat(obs[None], rows, axis=0), np.repeat(expert_chunk[None], rows, axis=0),
                              np.repeat(levels, n_samples), generator=generator)   # (n * L, H, dof)
    paths = np.stack([np.concatenate([start, env.ee(chunk)[:, :2]]) for chunk in samples])
    paths = paths.reshape(len(levels), n_samples, -1, 2)                           # (L, n, H + 1, 2)
    expert_xy = np.concatenate([start, env.ee(expert_chunk)[:, :2]])                # (H + 1, 2)

    # panel 0: the whole scene with every path; panels 1..L: one beta each, zoomed to all paths
    ncols = min(3, len(levels) + 1)
    nrows = math.ceil((len(levels) + 1) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.6 * ncols, 4.4 * nrows + 0.6), squeeze=False)
    axes = axes.ravel()
    colors = plt.cm.plasma(np.linspace(0.05, 0.8, len(levels)))   # dark: close to the expert, light: the policy
    sigma2 = noise_fraction(policy.schedule, levels)
    for ax in axes[len(levels) + 1:]:
        ax.set_visible(False)
    for p, ax in enumerate(axes[:len(levels) + 1]):
        if planar:
            env.render(ax, q=q, alpha=0.35)
        else:
            ax.plot(*env.goal[:2], marker="*", markersize=14, color="tab:green", linestyle="none")
            ax.set(aspect="equal", xlabel="x (m)", ylabel="y (m)")
        ax.plot(*expert_xy.T, "-o", color="tab:blue", lw=2.5, ms=3, alpha=0.9, zorder=5)   # on top: the reference
        for i in (range(len(levels)) if p == 0 else [p - 1]):
            for path_xy in paths[i]:
                ax.plot(*path_xy.T, "-", color=colors[i], lw=1.0, alpha=0.6)
        ax.plot(*start[0], "ko", ms=5)
        ax.set_title("the scene, every beta" + ("" if planar else " (top view)") if p == 0 else
                     rf"{names[p - 1]} ($k_{{sw}}$ = {switch_step(levels[p - 1], policy.cfg.K)}, "
                     rf"$\sigma^2_{{k_{{sw}}}}$ = {sigma2[p - 1]:.3f})", fontsize=10)
    all_xy = np.concatenate([paths.reshape(-1, 2), expert_xy])
    env.square_view(list(axes[1:len(levels) + 1]), all_xy, 0.02)    # the same close-up for every beta
    if not planar:                                             # the scene panel: paths, start and goal
        env.square_view(axes[0], np.concatenate([all_xy, env.goal[None, :2]]), 0.02)

    # one legend for all panels, below them (outside the data)
    handles = ([plt.Line2D([], [], color="tab:blue", marker="o", ms=3, lw=2.5, label="expert chunk"),
                plt.Line2D([], [], color="k", marker="o", lw=0, label="end effector now")]
               + [plt.Line2D([], [], color=c, lw=1.5, label=name) for c, name in zip(colors, names)]
               + [plt.Line2D([], [], lw=0, label=f"{n_samples} samples per beta")]
               + ([] if planar else [plt.Line2D([], [], color="tab:green", marker="*", ms=12, lw=0, label="goal")]))
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 5), fontsize=8, frameon=False)
    fig.suptitle("Partial denoising at one state (Fig. 3): end-effector paths of the chunks"
                 + ("" if planar else ", top view"))
    fig.tight_layout(rect=(0, 0.6 / (4.4 * nrows + 0.6) + 0.04, 1, 0.96))
    fig.savefig(path, dpi=150)
    plt.close(fig)
    return path


# ---- Demo --------------------------------------------------------------------------------------------------
# On the two-mode toy task (chunks go up-right or down-left), an expert chunk that bends off the up-right
# mode. Small beta keeps the bend; at beta = 1 half of the samples take the other mode (Fig. 3 in numbers).

if __name__ == "__main__":
    from diffusion import DiffusionPolicy, PolicyConfig, TrainConfig, toy_two_mode_data, train
    obs, chunks = toy_two_mode_data(4000, H=4)
    policy = DiffusionPolicy(PolicyConfig(obs_dim=4, dof=2, horizon=4, n_act=2, K=100, down_dims=(32, 64)))
    train(policy, obs, chunks, TrainConfig(steps=3000, warmup_steps=200, log_every=1000))
    n = 500
    o = np.zeros((n, 4), dtype=np.float32)  # (q_t, q_{t-1}) of an arm at rest at the origin
    t = np.arange(1, 5)[:, None] / 4                          # (H, 1)
    expert = np.repeat((0.5 * t * np.array([[1.0, 0.4]]))[None], n, axis=0)   # (n, H, 2), off the (+, +) mode
    print(" beta  k_sw  sigma^2  mean ||a* - a_hat||  share of samples in the other mode")
    for beta in (0.0, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0):
        a_hat = partial_denoise(policy, o, expert, beta, generator=torch.Generator().manual_seed(0))
        dist = np.linalg.norm((a_hat - expert).reshape(n, -1), axis=1).mean()
        other = (a_hat[:, -1].sum(1) < 0).mean()
        print(f" {beta:4.2f}  {switch_step(beta, 100):4d}  {noise_fraction(policy.schedule, beta):7.4f}"
              f"  {dist:19.3f}  {other:.0%}")
