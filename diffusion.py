"""A DDPM diffusion policy over action chunks, written from the DDPM equations (Ho et al. 2020).

Paper map (paper.tex, Sec. IV-B "Partial Denoising as a Learned Action Interpolator", Sec. IV-C):
  - noise schedule beta_k, alpha_k = 1 - beta_k, alphabar_k (defined with Eqs. 5-6) .. make_schedule, Schedule
  - forward process, Eq. (5), in closed form ............................. q_sample
  - reverse process, Eq. (6), one step ................................... p_sample
  - epsilon network eps_theta(a_k, k | o) over a chunk ................... ConditionalUnet1D (behind the
                                                                           banner: the paper does not give it)
  - the policy pi_theta(a_{t:t+H} | o_t): sampling, DDPM loss ............ DiffusionPolicy
  - action chunks of horizon H; the label rule (Sec. IV-C) ............... expert_runs, label_mask,
                                                                           chunk_dataset
  - BC, co-training, fine-tuning (Sec. IV-A steps 1, 4, 6) ............... train
  - how the network reads the observation ................................ OBS_ENCODERS (behind the banner;
                                                                           the UR5's camera images, Sec. V, are a
                                                                           variant's: experiment/image_obs.py)

Index convention (read this once, it is used everywhere):
  The paper numbers the diffusion steps k = 1..K, with alphabar_k = prod_{s=1..k} alpha_s and
  alphabar_0 = 1 (the clean chunk a_0). In code the arrays are indexed k = 0..K-1 and
      code index k  <->  paper step k + 1.
  So schedule.betas[k] = beta_{k+1}, schedule.alphas_cumprod[k] = alphabar_{k+1} and
  schedule.alphas_cumprod_prev[k] = alphabar_k (= 1 at k = 0). A chunk "at level k" (code) is distributed
  like q_sample(schedule, a0, k, eps) = sqrt(alphabar_{k+1}) a0 + sqrt(1 - alphabar_{k+1}) eps, the network
  is told that k, and p_sample(..., a_k, k) returns the chunk at level k - 1; from level 0 it returns the
  clean chunk (the posterior variance at k = 0 is zero). Pure noise N(0, I) stands in for level K - 1.

The network is the authors' (PAPER_SETUP.md §2: LeRobot's diffusion policy, the CNN variant of Chi et al.
2023). On a CPU it is the expensive part of the project (benchmarks/bench_diffusion.py measures it;
PolicyConfig.down_dims picks the width).
"""

import copy
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
import torch.nn as nn


# ----------------------------------------------------------------------------------------------
# Config (the longer notes on some knobs: "Config notes", behind the banner)


@dataclass
class PolicyConfig:
    # the paper (Sec. IV-B/C) and the authors' setup (PAPER_SETUP.md §1-2)
    obs_dim: int                 # length of the flat observation vector o_t (entries)
    dof: int                     # joints per action, d (3 planar, 6 UR5)
    horizon: int = 16            # H: actions per predicted chunk (steps)
    n_act: int = 8               # actions of a chunk executed before re-planning (steps; used by the rollout loop)
    K: int = 100                 # diffusion steps (the authors': 100)
    # The epsilon network: 'unet', the authors' 1-D conv U-Net (ConditionalUnet1D); 'mlp', a residual MLP with
    # the same FiLM interface (ResidualMLP; not the authors': ~8x the training samples per CPU second)
    network: str = "unet"
    down_dims: tuple = (64, 128, 256)  # U-Net channels per level (the authors: (128, 256, 512))
    mlp_width: int = 256         # network='mlp': width of the hidden layers
    mlp_blocks: int = 3          # network='mlp': FiLM-conditioned residual blocks
    kernel_size: int = 5         # temporal convolution kernel (steps; odd)
    n_groups: int = 8            # GroupNorm groups; every down_dim must be a multiple
    step_embed_dim: int = 128    # size of the sinusoidal diffusion-step embedding and of the step features
    joint_obs: bool = False      # obs starts with (q_t, q_{t-1}): chunks relative to q_t, velocity as an input
    # not in the paper
    obs_encoder: str = "flat"    # how the network reads the observation: an OBS_ENCODERS name ('flat': as numbers)
    obs_encoder_args: dict = field(default_factory=dict)   # its keyword arguments (a variant's env gives both)
    seed: int = 0                # seed of the weight initialisation

    def __post_init__(self):
        _check_policy_config(self)                                     # ValueError on a bad knob (behind the banner)

    @property
    def encoder_sizes(self):     # (observation entries at its end the encoder reads, features it gives for them)
        return OBS_ENCODERS[self.obs_encoder].sizes(**self.obs_encoder_args)

    @property
    def low_dim(self):           # entries of the observation min-max normalized: all before the encoder's
        return self.obs_dim - self.encoder_sizes[0]

    @property
    def cond_input_dim(self):    # observation features for FiLM: low-dim obs, velocity (joint_obs), encoder's
        return self.low_dim + (self.dof if self.joint_obs else 0) + self.encoder_sizes[1]


@dataclass
class TrainConfig:
    # the paper (Sec. IV-A) and the authors' setup (PAPER_SETUP.md §2)
    steps: int = 10_000              # optimizer steps of this run (the total, also when resuming)
    batch_size: int = 256            # chunks per step (base + augmented)
    lr: float = 1e-3                 # peak AdamW learning rate (after warmup)
    weight_decay: float = 1e-6       # AdamW weight decay (the authors')
    warmup_steps: int = 500          # optimizer steps of linear warmup from 0 to lr, then cosine decay to 0
    schedule_steps: int = 0          # step at which the cosine reaches 0 (0: steps). The authors' pi_0 is the 75k
    #                                  point of one 175k-step schedule that their fine-tuning continues (continue_from)
    constant_lr: bool = False        # lr at every step, no warm-up or cosine (the authors' lever fine-tuning)
    aug_fraction: float = 0.0        # fraction of each batch drawn from `sampler` (co-training, Sec. IV-A step 4)
    obs_noise: object = 0.0          # observation noise std in training, raw units (rad, m): one, or (obs_dim,)
    # not in the paper
    ema_decay: float = 0.999         # EMA of the weights used for sampling; timescale 1/(1 - decay) optimizer steps
    seed: int = 0                    # seeds batch indices (numpy) and diffusion noise (torch)
    log_every: int = 500             # optimizer steps between progress lines (0 = silent)
    log_seconds: float = 10.0        # ... and a line at least this often (seconds, wall clock) unless silent
    checkpoint_steps: tuple = ()     # optimizer steps after which a checkpoint is written
    checkpoint_path: str = ""        # where; '{step}' in the path is replaced by the step number

    def __post_init__(self):
        _check_train_config(self)                                      # validates and normalizes (behind the banner)


# ----------------------------------------------------------------------------------------------
# Noise schedule (DDPM, Ho et al. 2020; names follow the DDPM paper)


@dataclass
class Schedule:
    """All per-step DDPM coefficients, float32 tensors of shape (K,), indexed k = 0..K-1 = paper k + 1."""
    betas: torch.Tensor                          # beta_{k+1}
    alphas: torch.Tensor                         # alpha = 1 - beta
    alphas_cumprod: torch.Tensor                 # alphabar_{k+1} = prod_{s<=k} alphas[s]
    alphas_cumprod_prev: torch.Tensor            # alphabar_k, with alphabar_0 = 1
    sqrt_alphas_cumprod: torch.Tensor            # Eq. (5) closed form: mean coefficient
    sqrt_one_minus_alphas_cumprod: torch.Tensor  # Eq. (5) closed form: noise coefficient
    sqrt_recip_alphas_cumprod: torch.Tensor      # x0 from eps: a0 = sqrt(1/abar) a_k - sqrt(1/abar - 1) eps
    sqrt_recipm1_alphas_cumprod: torch.Tensor
    posterior_variance: torch.Tensor             # beta~ = beta (1 - abar_prev) / (1 - abar)  ("fixed small")
    posterior_mean_coef1: torch.Tensor           # multiplies the (clipped) predicted clean chunk a0
    posterior_mean_coef2: torch.Tensor           # multiplies the current noisy chunk a_k

    @property
    def K(self):
        return int(self.betas.shape[0])

    def to(self, device):
        return Schedule(**{name: value.to(device) for name, value in self.__dict__.items()})


def make_schedule(K=100):
    """The DDPM coefficients of the squared-cosine schedule (the authors') for K steps (computed in float64,
    stored as float32 tensors)."""
    if not isinstance(K, (int, np.integer)) or K < 1:
        raise ValueError(f"K must be a positive int, got {K!r}")
    # Nichol & Dhariwal (2021): alphabar(t) = f(t) / f(0), f(t) = cos^2((t + s) / (1 + s) * pi / 2).
    # s = 0.008 keeps beta_1 from being vanishingly small; the cap 0.999 avoids the singular last step
    # (f(1) = 0 would give beta_K = 1). This is diffusers' 'squaredcos_cap_v2', used by diffusion policy.
    # >>> exercise 1: the noise schedule and q_sample (Eq. 5)
    s = 0.008
    t = np.arange(K + 1, dtype=np.float64) / K
    f = np.cos((t + s) / (1 + s) * np.pi / 2) ** 2
    betas = np.minimum(1.0 - f[1:] / f[:-1], 0.999)
    alphas = 1.0 - betas
    alphas_cumprod = np.cumprod(alphas)
    alphas_cumprod_prev = np.concatenate([[1.0], alphas_cumprod[:-1]])
    # <<< exercise 1
    # >>> exercise 2: the DDPM posterior and one reverse step p_sample (Eq. 6)
    # Posterior q(a_{k-1} | a_k, a_0) = N(coef1 a_0 + coef2 a_k, beta~ I)  (DDPM Eqs. 6-7).
    posterior_variance = betas * (1.0 - alphas_cumprod_prev) / (1.0 - alphas_cumprod)
    posterior_mean_coef1 = betas * np.sqrt(alphas_cumprod_prev) / (1.0 - alphas_cumprod)
    posterior_mean_coef2 = (1.0 - alphas_cumprod_prev) * np.sqrt(alphas) / (1.0 - alphas_cumprod)
    # <<< exercise 2
    arrays = dict(
        betas=betas, alphas=alphas, alphas_cumprod=alphas_cumprod, alphas_cumprod_prev=alphas_cumprod_prev,
        sqrt_alphas_cumprod=np.sqrt(alphas_cumprod),
        sqrt_one_minus_alphas_cumprod=np.sqrt(1.0 - alphas_cumprod),
        sqrt_recip_alphas_cumprod=np.sqrt(1.0 / alphas_cumprod),
        sqrt_recipm1_alphas_cumprod=np.sqrt(1.0 / alphas_cumprod - 1.0),
        posterior_variance=posterior_variance,
        posterior_mean_coef1=posterior_mean_coef1, posterior_mean_coef2=posterior_mean_coef2)
    return Schedule(**{name: torch.tensor(value, dtype=torch.float32) for name, value in arrays.items()})


def q_sample(schedule, a0, k, eps):
    """Forward process: the chunk a0 diffused to code level k (paper step k + 1) with noise eps.

    Eq. (5) applied k + 1 times, a_k = sqrt(alpha_k) a_{k-1} + sqrt(1 - alpha_k) eps_k, collapses (the sum of
    independent Gaussians is Gaussian) to the closed form
        a_k = sqrt(alphabar_k) a_0 + sqrt(1 - alphabar_k) eps,   eps ~ N(0, I).
    """
    # _per_row(coef, k, a0): coef[k] of each row's level, shaped to broadcast against a0 (behind the banner)
    # >>> exercise 1: the noise schedule and q_sample (Eq. 5)
    # Eq. (5), closed form over k + 1 steps.
    return (_per_row(schedule.sqrt_alphas_cumprod, k, a0) * a0
            + _per_row(schedule.sqrt_one_minus_alphas_cumprod, k, a0) * eps)
    # <<< exercise 1


def p_sample(schedule, eps_pred, a_k, k, generator=None, noise=None, clip=True):
    """Reverse process: one step from code level k to k - 1 (from k = 0: the clean chunk).

    Implemented through the predicted clean chunk, as in DDPM's code and diffusion policy:
        a0_hat = (a_k - sqrt(1 - alphabar_k) eps_pred) / sqrt(alphabar_k), clipped to [-1, 1]
        mean   = posterior_mean_coef1 * a0_hat + posterior_mean_coef2 * a_k
        a_{k-1} = mean + sqrt(posterior_variance) z,   z ~ N(0, I)
    Without the clip, substituting a0_hat gives mean = (a_k - beta_k / sqrt(1 - alphabar_k) eps_pred) / sqrt(alpha_k),
    which is exactly Eq. (6) with sigma_k^2 = posterior variance (tested). The clip keeps the chunk inside the
    normalized action box [-1, 1] that the data came from (diffusion policy's clip_sample).
    noise: the z to use (B, H, dof); drawn from `generator` when None.
    """
    # >>> exercise 2: the DDPM posterior and one reverse step p_sample (Eq. 6)
    a0_hat = (_per_row(schedule.sqrt_recip_alphas_cumprod, k, a_k) * a_k
              - _per_row(schedule.sqrt_recipm1_alphas_cumprod, k, a_k) * eps_pred)
    if clip:
        a0_hat = a0_hat.clamp(-1.0, 1.0)
    # Eq. (6): posterior mean (equal to Eq. (6)'s mean when a0_hat is not clipped)
    mean = (_per_row(schedule.posterior_mean_coef1, k, a_k) * a0_hat
            + _per_row(schedule.posterior_mean_coef2, k, a_k) * a_k)
    if noise is None:
        noise = torch.randn(a_k.shape, generator=generator,
                            device=generator.device if generator is not None else a_k.device)
    # Eq. (6): + sigma_k z, sigma_k^2 = posterior variance (0 at k = 0, so the last step adds no noise)
    return mean + _per_row(schedule.posterior_variance, k, a_k).sqrt() * noise.to(a_k.device)
    # <<< exercise 2


# ----------------------------------------------------------------------------------------------
# The policy: the DDPM loss, sampling by the reverse process


class DiffusionPolicy(nn.Module):
    """pi_theta(a_{t:t+H} | o_t): DDPM over action chunks, with an EMA copy of eps_theta for sampling.

    Observations and chunks are min-max normalized to [-1, 1] (fitted on the dataset, saved with the
    weights; with cfg.joint_obs chunks relative to q_t). The interface stays in joint units and absolute
    targets: sample() returns chunks of joint positions.
    """

    def __init__(self, cfg, device="cpu"):
        super().__init__()
        self.cfg = cfg
        with torch.random.fork_rng(devices=[]):                       # init from cfg.seed; caller's RNG untouched
            torch.manual_seed(cfg.seed)
            self.net = NETWORKS[cfg.network](cfg)                      # eps_theta (behind the banner)
        self.ema_net = copy.deepcopy(self.net).requires_grad_(False)
        _register_normalizer(self)                                     # min-max buffers (behind the banner)
        self.schedule = make_schedule(cfg.K)
        self.to(device)

    # Plumbing (the details behind the banner): device, normalization to [-1, 1], FiLM pieces, noise, files.
    @property
    def device(self):
        return self.obs_center.device

    def _apply(self, fn, *args, **kwargs):     # .to(device): the schedule (derived, not a buffer) follows
        super()._apply(fn, *args, **kwargs)
        self.schedule = make_schedule(self.cfg.K).to(self.obs_center.device)
        return self

    def fit_normalizer(self, obs, actions):    # min-max fit on obs (N, obs_dim), actions (N, H, dof), joint units
        _fit_min_max(self, obs, actions)

    def normalize_obs(self, obs):              # raw (B, obs_dim) -> the network's observation input
        return _normalize_obs(self, obs)

    def normalize_actions(self, a, obs=None):  # chunks (B, H, dof), joint units -> [-1, 1]; obs: raw, for joint_obs
        return (a - _action_origin(self, obs) - self.act_center) / self.act_half

    def unnormalize_actions(self, a, obs=None):  # the inverse of normalize_actions
        return a * self.act_half + self.act_center + _action_origin(self, obs)

    def condition(self, obs_norm, use_ema=True):  # FiLM pieces: (obs terms (B, F), step table (K, F))
        net = self.ema_net if use_ema else self.net
        return net.obs_terms(obs_norm), net.step_table()

    def draw_noise(self, B, generator=None):   # (B, K + 1, H, dof): [:, 0] start noise, [:, 1 + k] z at level k
        return _draw_noise_rows(self, B, generator)

    def save(self, path, extra=None):          # config, weights, EMA weights, normalizer (+ extra) in one file
        _write_checkpoint(self, path, extra)

    @classmethod
    def load(cls, path, device="cpu"):         # FileNotFoundError, or CheckpointDamagedError (a ValueError)
        return _load_policy(cls, path, device)

    # The paper: eps_theta, the loss, the reverse process (Eq. 6) and sampling.
    def predict_eps(self, a_k_norm, k, obs_norm, use_ema=True, cond=None):
        """eps_theta(a_k, k | o): a_k_norm (B, H, dof), k (B,) long, obs_norm = normalize_obs(obs) -> (B, H, dof).
        The network's FiLM input is the sum of an observation part and a step part (ConditionalUnet1D);
        cond: optional result of self.condition(obs_norm, use_ema) to reuse across reverse steps."""
        B = a_k_norm.shape[0]
        obs_part, step_part = cond if cond is not None else self.condition(obs_norm, use_ema)
        k = k.to(self.device).long() if torch.is_tensor(k) else torch.full((B,), int(k), device=self.device)
        film = obs_part + step_part[k]                                # (B, F)
        return (self.ema_net if use_ema else self.net)(a_k_norm, film)   # (B, H, dof)

    def loss(self, obs_norm, chunk_norm, generator=None, mask=None):
        """DDPM's simple loss: || eps - eps_theta(q_sample(a0, k, eps), k | o) ||^2, k ~ U{0..K-1}.
        mask: optional (B, H) bool, True = the chunk step is in the loss (_masked_mse, behind the banner)."""
        B = chunk_norm.shape[0]
        gdev = generator.device if generator is not None else self.device
        k = torch.randint(0, self.cfg.K, (B,), generator=generator, device=gdev).to(self.device)
        eps = torch.randn(chunk_norm.shape, generator=generator, device=gdev).to(self.device)
        a_k = q_sample(self.schedule, chunk_norm, k, eps)              # Eq. (5)
        eps_pred = self.predict_eps(a_k, k, obs_norm, use_ema=False)   # (B, H, dof)
        if mask is None:
            return nn.functional.mse_loss(eps_pred, eps)
        return _masked_mse(eps_pred, eps, mask, self.device)

    @torch.inference_mode()
    def reverse_process(self, a_k, k_start, obs_norm, z, use_ema=True):
        """Run Eq. (6) from per-row code level k_start (B,) down to the clean chunk.

        a_k (B, H, dof) normalized, row i at level k_start[i]; k_start[i] = -1 means row i is already clean
        and is returned unchanged. z (B, K, H, dof): z[:, k] is the noise of the step at level k.
        """
        cond = self.condition(obs_norm, use_ema)
        a = a_k.clone()
        top = int(k_start.max()) if len(k_start) else -1
        for k in range(top, -1, -1):
            active = k_start >= k                                      # rows that have reached level k
            idx = active.nonzero().squeeze(1) if not bool(active.all()) else None
            if idx is None:
                eps = self.predict_eps(a, k, None, use_ema, cond=cond)
                a = p_sample(self.schedule, eps, a, k, noise=z[:, k])   # Eq. (6)
            else:
                sub_cond = (cond[0][idx], cond[1])
                eps = self.predict_eps(a[idx], k, None, use_ema, cond=sub_cond)
                a[idx] = p_sample(self.schedule, eps, a[idx], k, noise=z[idx, k])
        return a

    def sample(self, obs, generator=None, use_ema=True):
        """Unguided sampling: obs (B, obs_dim) np.ndarray -> chunks (B, H, dof) float64 in joint units."""
        obs = check_array("obs", obs, (None, self.cfg.obs_dim))
        B = obs.shape[0]
        with torch.inference_mode():
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            obs_norm = self.normalize_obs(obs_t)
            noise = self.draw_noise(B, generator)
            a_K = noise[:, 0]                                          # pure noise stands in for level K - 1
            k_start = torch.full((B,), self.cfg.K - 1, device=self.device)
            a0 = self.reverse_process(a_K, k_start, obs_norm, noise[:, 1:], use_ema)
            return self.unnormalize_actions(a0.double(), obs_t.double()).cpu().numpy()


# ----------------------------------------------------------------------------------------------
# Chunk dataset (Sec. IV-C: a chunk is a label only if the expert drove all of its H steps)


def expert_runs(expert, H, pad=False):
    """The paper's label rule, part 1 (Sec. IV-C): the maximal runs [start, end) of expert-driven steps that
    can label chunks of H steps. A run counts if it is at least H steps long, or if it is the whole episode
    (a demonstration, padded at its end however short). A shorter intervention teaches nothing with chunks
    of H and is discarded, also when it ends the episode. Every other module derives its labels from here.
    pad=True: the authors' lever runs instead (PAPER_SETUP.md; their teleop_pad_short_episodes): every run
    counts, however short; its chunks are padded past its end and those steps masked out of the loss."""
    expert = np.asarray(expert, dtype=bool)
    T = len(expert)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], expert.astype(np.int8), [0]])))  # run starts, ends
    runs = [(int(s), int(e)) for s, e in zip(edges[::2], edges[1::2])]
    return [(s, e) for s, e in runs if pad or e - s >= H or (s == 0 and e == T)]


def label_mask(expert, H, pad=False):
    """The paper's label rule, part 2: (T,) bool, True where the chunk starting at t is a valid label, i.e.
    t lies in a run of expert_runs and the chunk stays inside it: t + H <= end, or the run ends the episode
    (the chunk is then padded with the last action). pad=True: every step of every run starts a label (the
    steps past its run's end padded and masked: chunk_dataset)."""
    expert = np.asarray(expert, dtype=bool)
    T = len(expert)
    mask = np.zeros(T, dtype=bool)
    for start, end in expert_runs(expert, H, pad):
        mask[start:(end if end == T or pad else end - H + 1)] = True
    return mask


def chunk_dataset(episodes, H, pad=False):
    """(obs (N, obs_dim) float32, chunks (N, H, dof) float32) over all valid label starts of all episodes.
    A chunk is action[t : t + H]; past the episode end it repeats the last action. pad=True (the authors'
    lever runs; their do_mask_loss_for_padding): every expert step starts a chunk, which repeats its run's last
    action past the run's end, and a third array, the loss mask (N, H) bool, is False on those padded steps."""
    if not isinstance(H, (int, np.integer)) or H < 1:
        raise ValueError(f"H must be a positive int, got {H!r}")
    obs_list, chunk_list, mask_list = [], [], []
    for i, ep in enumerate(episodes):
        for key in ("obs", "action", "expert"):
            if key not in ep:
                raise ValueError(f"episode {i} has no {key!r} array (has {sorted(ep)})")
        obs, action, expert = np.asarray(ep["obs"]), np.asarray(ep["action"]), np.asarray(ep["expert"])
        T = len(action)
        if len(obs) != T or len(expert) != T or action.ndim != 2:
            raise ValueError(f"episode {i}: obs {obs.shape}, action {action.shape}, expert {expert.shape} "
                             "must share the length T, with action of shape (T, dof)")
        starts = np.nonzero(label_mask(expert, H, pad))[0]             # (n,)
        steps = starts[:, None] + np.arange(H)[None, :]                # (n, H)
        last = np.full(len(starts), T - 1)                             # the last step a chunk may read
        if pad:                                                        # the end of each start's own run
            for start, end in expert_runs(expert, H, pad):
                last[(starts >= start) & (starts < end)] = end - 1
            mask_list.append(steps <= last[:, None])                   # (n, H): padded steps out of the loss
        obs_list.append(obs[starts].astype(np.float32))
        chunk_list.append(action[np.minimum(steps, last[:, None])].astype(np.float32))  # (n, H, dof), padded
    if not obs_list:
        raise ValueError("chunk_dataset needs at least one episode")
    data = np.concatenate(obs_list), np.concatenate(chunk_list)
    return (*data, np.concatenate(mask_list)) if pad else data


# ----------------------------------------------------------------------------------------------
# Training: AdamW on the DDPM loss, the co-training hook (Sec. IV-A steps 1, 4, 6)


def train(policy, obs, chunks, cfg, sampler=None, resume_from=None, continue_from=None, log=print):
    """Train (or fine-tune) `policy` in place on (obs (N, obs_dim), chunks (N, H, dof)) in joint units.

    - Fits the normalizer on (obs, chunks) only if the policy has none yet; fine-tuning a loaded checkpoint
      keeps the checkpoint's normalizer, a fresh optimizer and runs cfg.steps steps.
    - sampler(n, rng) -> (obs (n, obs_dim), chunks (n, H, dof)) or (obs, chunks, mask (n, H) bool): augmented
      pairs made on the fly; they fill round(cfg.aug_fraction * batch_size) rows of every batch (co-training,
      Sec. IV-A step 4). With a mask, only its True steps enter the loss (base rows: every step).
    - resume_from: a checkpoint written by this function (cfg.checkpoint_steps), see _resume_training.
    - continue_from: a checkpoint written by this function, e.g. pi_0 at the end of BC: its weights, AdamW
      state and step count continue (the step counts on to cfg.steps, the lr along cfg's schedule), with
      this run's own data and random streams. How the authors' fine-tuning ran (PAPER_SETUP.md §2): no
      warm-up, no fresh optimizer, the tail of BC's own cosine schedule.
    """
    pc = policy.cfg
    obs, chunks = _check_train_inputs(policy, obs, chunks, cfg, sampler)
    n_aug = int(round(cfg.aug_fraction * cfg.batch_size))            # augmented rows per batch
    n_base = cfg.batch_size - n_aug                                    # rows from (obs, chunks)
    if not bool(policy.normalizer_fitted):
        policy.fit_normalizer(obs, chunks)
    dev = policy.device
    with torch.no_grad():
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=dev)     # raw: the noise is in raw units
        chunks_n = policy.normalize_actions(torch.as_tensor(chunks, dtype=torch.float32, device=dev), obs_t)
    noise_std = torch.as_tensor(np.broadcast_to(np.asarray(cfg.obs_noise, dtype=np.float32), (pc.obs_dim,)).copy(),
                                device=dev)                            # (obs_dim,)
    noisy = bool((noise_std > 0).any())

    optimizer = torch.optim.AdamW(policy.net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay,
                                  foreach=True)
    rng = np.random.default_rng(cfg.seed)                              # batch indices, sampler
    gen = torch.Generator(device=dev).manual_seed(cfg.seed)            # diffusion steps, noise
    step = 0
    if resume_from is not None:                                        # weights, optimizer, rng, gen, sampler
        step = _resume_training(resume_from, policy, optimizer, rng, gen, sampler)
    elif continue_from is not None:                                    # weights, optimizer, step
        step = _continue_training(continue_from, policy, optimizer, cfg)

    policy.train()
    progress = _Progress(cfg, step, log)                               # progress lines (behind the banner)
    while step < cfg.steps:
        lr = lr_at(step, cfg)                                          # warmup + cosine (behind the banner)
        for group in optimizer.param_groups:
            group["lr"] = lr
        idx = torch.as_tensor(rng.integers(0, len(obs_t), n_base), device=dev)
        o, a = obs_t[idx], chunks_n[idx]                               # raw (B, obs_dim), normalized (B, H, dof)
        mask = None                                                    # None: every step is in the loss
        if n_aug:                                                      # co-training (Sec. IV-A step 4)
            o, a, mask = _append_augmented(policy, sampler, n_aug, rng, o, a)   # + n_aug rows, mask or None
        with torch.no_grad():
            if noisy:
                # Observation noise in raw units, labels unchanged (Sec. V; PAPER_SETUP.md §2): the chunk stays
                # relative to the true q_t, so the policy learns to act well from a slightly wrong reading.
                o = o + noise_std * torch.randn(o.shape, generator=gen, device=dev)
            o = policy.normalize_obs(o)                                # (B, cond input)
        loss = policy.loss(o, a, generator=gen, mask=mask)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        update_ema(policy, step, cfg.ema_decay)                        # EMA copy for sampling (behind the banner)
        step += 1
        progress.update(step, loss.item())
        if step in cfg.checkpoint_steps:
            _save_training_checkpoint(policy, cfg, step, optimizer, rng, gen, sampler)
    policy.eval()
    return policy


# ==== Beyond the paper (safe to skip) ====================================================
# Config notes, argument checks, the epsilon network (the authors' U-Net), the observation encoders, the min-max
# normalizer, the per-row indexing of the schedule (_per_row), the noise draws of a reverse process, the
# masked loss, train()'s learning-rate schedule, EMA and progress lines, checkpoint files and train()'s resume
# plumbing, the toy data.


# ----------------------------------------------------------------------------------------------
# Config notes (the longer "why" of some PolicyConfig / TrainConfig knobs)
#
# PolicyConfig.down_dims: the U-Net halves the chunk in time between levels, so horizon must divide by
#   2**(len(down_dims) - 1); every width must be a multiple of n_groups (GroupNorm). The authors use
#   (128, 256, 512); our default is narrower for a CPU (benchmarks/bench_diffusion.py measures the widths).
# PolicyConfig.kernel_size: odd, so that padding kernel_size // 2 keeps the chunk's length.
# PolicyConfig.joint_obs: the observation starts with (q_t, q_{t-1}) as in envs.py; chunks are learned
#   relative to q_t and the network also sees the joint velocity q_t - q_{t-1} (why: at _fit_min_max).
# PolicyConfig.obs_encoder: see OBS_ENCODERS; the envs give it as env.obs_encoder, env.obs_encoder_args.
# TrainConfig.obs_noise: raw observation units, rad on the joints and m on the environment numbers (the
#   authors: 0.01 rad and 0.005 m); a float for every entry or one std per entry (obs_dim,). 0 = none.
# TrainConfig.ema_decay: the authors use no EMA; with 0.999 the average spans ~1/(1 - decay) = 1000
#   optimizer steps (update_ema).


# ----------------------------------------------------------------------------------------------
# Argument checks: a clear ValueError naming the bad value


def _check_policy_config(cfg):
    """PolicyConfig.__post_init__: ValueError on a bad field; makes down_dims an int tuple."""
    if cfg.network not in NETWORKS:
        raise ValueError(f"PolicyConfig.network must be one of {', '.join(NETWORKS)}, got {cfg.network!r}")
    for name in ("obs_dim", "dof", "horizon", "n_act", "K", "kernel_size", "n_groups", "step_embed_dim",
                 "mlp_width", "mlp_blocks"):
        value = getattr(cfg, name)
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"PolicyConfig.{name} must be a positive int, got {value!r}")
    dims = cfg.down_dims
    if (not isinstance(dims, (tuple, list)) or not dims
            or any(not isinstance(d, (int, np.integer)) or d < 1 or d % cfg.n_groups for d in dims)):
        raise ValueError(f"PolicyConfig.down_dims must be a non-empty tuple of positive multiples of "
                         f"n_groups={cfg.n_groups} (GroupNorm splits every width into n_groups groups), "
                         f"got {dims!r}")
    cfg.down_dims = tuple(int(d) for d in dims)                        # a list from a JSON config, numpy ints
    if cfg.network == "unet" and cfg.horizon % 2 ** (len(cfg.down_dims) - 1):
        raise ValueError(f"PolicyConfig.horizon={cfg.horizon} must be divisible by "
                         f"2**(len(down_dims) - 1) = {2 ** (len(cfg.down_dims) - 1)}: the U-Net halves the "
                         f"chunk {len(cfg.down_dims) - 1} times (down_dims={cfg.down_dims})")
    if cfg.kernel_size % 2 == 0:
        raise ValueError(f"PolicyConfig.kernel_size must be odd (padding k // 2 keeps the length), "
                         f"got {cfg.kernel_size}")
    if cfg.n_act > cfg.horizon:
        raise ValueError(f"PolicyConfig.n_act={cfg.n_act} must be <= horizon={cfg.horizon}")
    if cfg.step_embed_dim % 2:
        raise ValueError(f"PolicyConfig.step_embed_dim must be even, got {cfg.step_embed_dim}")
    if cfg.obs_encoder not in OBS_ENCODERS:
        raise ValueError(f"PolicyConfig.obs_encoder must be one of {', '.join(OBS_ENCODERS)}, got {cfg.obs_encoder!r} "
                         f"(a research variant registers its encoder when its module is imported, e.g. "
                         f"experiment.image_obs: 'image_cnn')")
    try:
        encoded = cfg.encoder_sizes[0]                                 # the encoder checks its own arguments
    except TypeError as err:                                           # an argument it does not take
        raise ValueError(f"PolicyConfig.obs_encoder_args {cfg.obs_encoder_args!r} do not fit the obs_encoder "
                         f"{cfg.obs_encoder!r}: {err}") from None
    if encoded >= cfg.obs_dim:
        raise ValueError(f"PolicyConfig.obs_encoder {cfg.obs_encoder!r} reads {encoded} entries at the observation's "
                         f"end; the observation (obs_dim={cfg.obs_dim}) must be longer (joint positions come first)")
    if cfg.joint_obs and cfg.low_dim < 2 * cfg.dof:
        raise ValueError(f"PolicyConfig.joint_obs needs obs_dim >= 2 * dof = {2 * cfg.dof} (obs starts with "
                         f"q_t, q_t-1), got obs_dim={cfg.obs_dim}; use joint_obs=False")


def _check_train_config(cfg):
    """TrainConfig.__post_init__: ValueError on a bad field; obs_noise becomes a float or a tuple of floats."""
    if cfg.steps < 0 or cfg.batch_size < 1 or cfg.warmup_steps < 0:
        raise ValueError(f"TrainConfig needs steps >= 0, batch_size >= 1, warmup_steps >= 0; got "
                         f"{cfg.steps}, {cfg.batch_size}, {cfg.warmup_steps}")
    if not 0.0 <= cfg.aug_fraction <= 1.0:
        raise ValueError(f"TrainConfig.aug_fraction must be in [0, 1], got {cfg.aug_fraction}")
    if not 0.0 <= cfg.ema_decay < 1.0:
        raise ValueError(f"TrainConfig.ema_decay must be in [0, 1), got {cfg.ema_decay}")
    noise = np.asarray(cfg.obs_noise, dtype=np.float64)
    if noise.ndim > 1 or not np.all(np.isfinite(noise)) or np.any(noise < 0):
        raise ValueError(f"TrainConfig.obs_noise must be a std >= 0 or a vector of them (one per observation "
                         f"entry), got {cfg.obs_noise!r}")
    cfg.obs_noise = float(noise) if noise.ndim == 0 else tuple(float(x) for x in noise)
    if cfg.schedule_steps < 0 or (cfg.schedule_steps and cfg.schedule_steps < cfg.steps):
        raise ValueError(f"TrainConfig.schedule_steps must be 0 (= steps) or >= steps={cfg.steps}, "
                         f"got {cfg.schedule_steps}")
    cfg.checkpoint_steps = tuple(int(s) for s in cfg.checkpoint_steps)
    if cfg.checkpoint_steps and not cfg.checkpoint_path:
        raise ValueError("TrainConfig.checkpoint_steps given but checkpoint_path is empty")


def check_array(name, x, shape):
    """x (numpy or torch) must be finite and of the given shape (None = any size on that axis); else ValueError."""
    x = np.asarray(x) if not torch.is_tensor(x) else x
    if x.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, x.shape)):
        raise ValueError(f"{name} must have shape {tuple('N' if s is None else s for s in shape)}, "
                         f"got {tuple(x.shape)}")
    finite = torch.isfinite(x).all() if torch.is_tensor(x) else np.isfinite(x).all()
    if not finite:
        raise ValueError(f"{name} contains NaN or inf")
    return x


def _check_train_inputs(policy, obs, chunks, cfg, sampler):
    """train()'s arguments: the dataset's shapes, a sampler where aug_fraction needs one, one obs_noise std per
    observation entry. Returns (obs, chunks) as check_array gives them."""
    pc = policy.cfg
    obs = check_array("obs", obs, (None, pc.obs_dim))
    chunks = check_array("chunks", chunks, (None, pc.horizon, pc.dof))
    if len(obs) != len(chunks) or len(obs) == 0:
        raise ValueError(f"obs and chunks need the same non-zero length, got {len(obs)} and {len(chunks)}")
    if round(cfg.aug_fraction * cfg.batch_size) and sampler is None:
        raise ValueError(f"aug_fraction={cfg.aug_fraction} needs a sampler")
    if np.ndim(cfg.obs_noise) and len(cfg.obs_noise) != pc.obs_dim:
        raise ValueError(f"TrainConfig.obs_noise has {len(cfg.obs_noise)} stds, the observation has "
                         f"obs_dim={pc.obs_dim} entries: give one per entry or a single float")
    return obs, chunks


def _append_augmented(policy, sampler, n_aug, rng, o, a):
    """train()'s co-training rows: n_aug pairs from the sampler, checked, appended to the base rows o (raw,
    (n_base, obs_dim)) and a (normalized, (n_base, H, dof)). Returns (o, a, mask): mask (B, H) bool with the
    base rows all True if the sampler gives a mask, else None."""
    pc, dev = policy.cfg, policy.device
    drawn = sampler(n_aug, rng)
    if len(drawn) not in (2, 3):
        raise ValueError(f"sampler must return (obs, chunks) or (obs, chunks, mask), got {len(drawn)} arrays")
    o_aug = check_array("sampler obs", drawn[0], (n_aug, pc.obs_dim))
    a_aug = check_array("sampler chunks", drawn[1], (n_aug, pc.horizon, pc.dof))
    m_aug = None
    if len(drawn) == 3:
        m_aug = np.asarray(drawn[2])
        if m_aug.shape != (n_aug, pc.horizon) or m_aug.dtype != bool:
            raise ValueError(f"sampler mask must be bool ({n_aug}, {pc.horizon}), got {m_aug.dtype} {m_aug.shape}")
        m_aug = torch.as_tensor(m_aug, device=dev)
    with torch.no_grad():
        o_aug = torch.as_tensor(o_aug, dtype=torch.float32, device=dev)
        a_aug = torch.as_tensor(a_aug, dtype=torch.float32, device=dev)
        a_aug = policy.normalize_actions(a_aug, o_aug)
        o, a = torch.cat([o, o_aug]), torch.cat([a, a_aug])
        mask = None
        if m_aug is not None:
            mask = torch.cat([torch.ones(len(o) - n_aug, pc.horizon, dtype=torch.bool, device=dev),
                              m_aug])                                  # (B, H): base rows all True
    return o, a, mask


# ----------------------------------------------------------------------------------------------
# The epsilon network eps_theta(a_k, k | o): Chi et al.'s 1-D temporal convolution U-Net, FiLM-conditioned
# on (k, o). The paper does not describe its network; this is the authors' (PAPER_SETUP.md §2: LeRobot's
# diffusion policy, the CNN variant), with PolicyConfig.down_dims picking the width.


def step_embedding(k, dim):
    """Sinusoidal embedding of the diffusion step (Vaswani et al.; as in DDPM): (N,) -> (N, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10_000.0) * torch.arange(half, dtype=torch.float32, device=k.device) / half)
    angles = k.float()[:, None] * freqs[None, :]                   # (N, half)
    return torch.cat([angles.sin(), angles.cos()], dim=1)           # (N, dim)


class Conv1dBlock(nn.Sequential):
    """Conv1d -> GroupNorm -> Mish over (B, channels, T); padding k // 2 keeps the length T (k odd)."""

    def __init__(self, in_channels, out_channels, kernel_size, n_groups):
        super().__init__(nn.Conv1d(in_channels, out_channels, kernel_size, padding=kernel_size // 2),
                         nn.GroupNorm(n_groups, out_channels),
                         nn.Mish())


class ConditionalResidualBlock(nn.Module):
    """Two Conv1dBlocks with FiLM between them, plus a residual path (1 x 1 conv if the width changes).

    FiLM (Perez et al.), per channel: h <- scale * h + bias, with (scale, bias) = film(Mish(cond)) and
    cond = [step features, observation features]. The block owns its linear map `film` but receives its
    result: ConditionalUnet1D splits every block's map into a step part and an observation part and
    computes them at different times (see there).
    """

    def __init__(self, in_channels, out_channels, cond_dim, kernel_size, n_groups):
        super().__init__()
        self.conv1 = Conv1dBlock(in_channels, out_channels, kernel_size, n_groups)
        self.film = nn.Linear(cond_dim, 2 * out_channels)            # -> (scale, bias), out_channels each
        self.conv2 = Conv1dBlock(out_channels, out_channels, kernel_size, n_groups)
        self.residual = (nn.Conv1d(in_channels, out_channels, 1) if in_channels != out_channels
                         else nn.Identity())

    def forward(self, x, film):
        """x (B, in_channels, T), film (B, 2 * out_channels) = self.film(Mish(cond)) -> (B, out_channels, T)."""
        h = self.conv1(x)                                            # (B, out, T)
        scale, bias = film[:, :, None].chunk(2, dim=1)               # (B, out, 1) each
        h = scale * h + bias
        return self.conv2(h) + self.residual(x)                      # (B, out, T)


class FiLMNetwork(nn.Module):
    """What every epsilon network here shares: FiLM conditioning on [step features, observation features].

    Every residual block's FiLM is film(Mish([step features, obs features])). Splitting the weight
    W = [W_s | W_o] along its input gives film = (W_s Mish(step) + b) + W_o Mish(obs): step_table() computes
    the first term for all K steps at once, obs_terms() the second once per sampling call (the observation
    encoder included), and forward(a, film) takes their sum, all blocks' (scale, bias) in one row (film_size wide).
    A subclass builds its blocks between _init_step_features() and _init_film(), and lists them in
    residual_blocks() in the order its forward() uses them.
    """

    def _init_step_features(self, cfg):
        dsed = cfg.step_embed_dim
        self.K, self.step_embed_dim = cfg.K, dsed
        # Step features: sinusoidal embedding -> Linear(dsed, 4 dsed) -> Mish -> Linear(4 dsed, dsed) (Chi et al.).
        self.step_encoder = nn.Sequential(nn.Linear(dsed, 4 * dsed), nn.Mish(), nn.Linear(4 * dsed, dsed))
        return dsed + cfg.cond_input_dim                             # FiLM input: [step features, obs features]

    def _init_film(self, cfg):
        self.film_sizes = [b.film.out_features for b in self.residual_blocks()]
        self.film_size = sum(self.film_sizes)
        # built last, so an encoder with weights leaves the others' initialisation as without it
        self.obs_encoder = OBS_ENCODERS[cfg.obs_encoder](**cfg.obs_encoder_args)

    def residual_blocks(self):
        raise NotImplementedError

    def film_weights(self):
        """All blocks' FiLM maps stacked and split along the input: (W_s (F, dsed), W_o (F, obs features),
        b (F,)), F = film_size."""
        weight = torch.cat([b.film.weight for b in self.residual_blocks()])   # (F, dsed + obs features)
        bias = torch.cat([b.film.bias for b in self.residual_blocks()])       # (F,)
        return weight[:, :self.step_embed_dim], weight[:, self.step_embed_dim:], bias

    def obs_features(self, obs_norm):
        """normalize_obs's output (B, ...) -> (B, cond_input_dim): the observation encoder's (OBS_ENCODERS)."""
        return self.obs_encoder(obs_norm)

    def obs_terms(self, obs_norm):
        """(B, F): the observation part W_o Mish(obs features) of every block's FiLM."""
        _, w_obs, _ = self.film_weights()
        return nn.functional.mish(self.obs_features(obs_norm)) @ w_obs.T      # (B, F)

    def step_features(self, k):
        """(N,) long diffusion steps -> (N, dsed) step features."""
        return self.step_encoder(step_embedding(k, self.step_embed_dim))

    def step_table(self):
        """(K, F): the step part W_s Mish(step features) + b of every block's FiLM, for all K steps at once."""
        w_step, _, bias = self.film_weights()
        k = torch.arange(self.K, device=bias.device)
        return nn.functional.linear(nn.functional.mish(self.step_features(k)), w_step, bias)   # (K, F)

class ConditionalUnet1D(FiLMNetwork):
    """eps_theta(a_k, k | o): the noisy chunk (B, H, dof) in, the predicted noise (B, H, dof) out.

    With down_dims (c_0, .., c_L) (L + 1 levels) and T = H:
      encoder, level l:  two residual blocks to width c_l at length T / 2^l, keep the result as a skip,
                         then a stride-2 Conv1d (kernel 3) halves the length (not after the deepest level);
      middle:            two residual blocks at width c_L, length T / 2^L;
      decoder, L steps:  concatenate the skip of the same length (the width doubles), two residual blocks
                         to the next shallower width, ConvTranspose1d (kernel 4, stride 2) doubles the length.
    As in Chi et al.'s network the decoder has one level fewer than the encoder: its skips come from levels
    L, L-1, .., 1, and its last upsampling restores the length T, so the shallowest skip goes unused.
    Output: a Conv1dBlock and a 1 x 1 Conv1d back to dof channels.

    Conditioning: FiLMNetwork's (every block gets film(Mish([step features, obs features]))).
    """

    def __init__(self, cfg):
        super().__init__()
        dims = cfg.down_dims
        cond_dim = self._init_step_features(cfg)                     # [step features, obs features]

        def block(in_channels, out_channels):
            return ConditionalResidualBlock(in_channels, out_channels, cond_dim, cfg.kernel_size, cfg.n_groups)

        self.down = nn.ModuleList()
        for level, (c_in, c_out) in enumerate(zip((cfg.dof,) + dims[:-1], dims)):
            deepest = level == len(dims) - 1
            downsample = nn.Identity() if deepest else nn.Conv1d(c_out, c_out, 3, stride=2, padding=1)
            self.down.append(nn.ModuleList([block(c_in, c_out), block(c_out, c_out), downsample]))
        self.mid = nn.ModuleList([block(dims[-1], dims[-1]), block(dims[-1], dims[-1])])
        self.up = nn.ModuleList()
        for c_deep, c_out in zip(dims[:0:-1], dims[-2::-1]):          # (c_L, c_L-1), .., (c_1, c_0)
            upsample = nn.ConvTranspose1d(c_out, c_out, 4, stride=2, padding=1)
            self.up.append(nn.ModuleList([block(2 * c_deep, c_out), block(c_out, c_out), upsample]))
        self.final = nn.Sequential(Conv1dBlock(dims[0], dims[0], cfg.kernel_size, cfg.n_groups),
                                   nn.Conv1d(dims[0], cfg.dof, 1))
        # Zero-init output: the untrained net predicts eps = 0, so training starts at loss ~1 (stable).
        nn.init.zeros_(self.final[-1].weight)
        nn.init.zeros_(self.final[-1].bias)
        self._init_film(cfg)

    def residual_blocks(self):
        """All ConditionalResidualBlocks in the order forward() uses them: the layout of the FiLM vector."""
        for first, second, _ in self.down:
            yield from (first, second)
        yield from self.mid
        for first, second, _ in self.up:
            yield from (first, second)

    def forward(self, a, film):
        """a (B, H, dof) noisy normalized chunk, film (B, F) = obs_terms + step_table[k] -> eps (B, H, dof)."""
        x = a.transpose(1, 2)                                        # (B, dof, H): channels first
        films = iter(film.split(self.film_sizes, dim=1))             # (B, 2 * out_channels) per block
        skips = []
        for first, second, downsample in self.down:                  # level l = 0 .. L, T_l = H / 2^l
            x = second(first(x, next(films)), next(films))           # (B, c_l, T_l)
            skips.append(x)
            x = downsample(x)                                        # (B, c_l, T_l / 2); deepest: unchanged
        for block in self.mid:
            x = block(x, next(films))                                # (B, c_L, T_L)
        for first, second, upsample in self.up:                      # level l = L .. 1
            x = torch.cat([x, skips.pop()], dim=1)                   # (B, 2 c_l, T_l): level l's skip
            x = second(first(x, next(films)), next(films))           # (B, c_l-1, T_l)
            x = upsample(x)                                          # (B, c_l-1, T_l-1 = 2 T_l)
        return self.final(x).transpose(1, 2)                         # (B, dof, H) -> (B, H, dof)


class MLPResidualBlock(nn.Module):
    """x + fc2(Mish(FiLM(fc1(Mish(LayerNorm(x)))))): a pre-norm residual block with the U-Net block's FiLM."""

    def __init__(self, width, cond_dim):
        super().__init__()
        self.norm = nn.LayerNorm(width)
        self.fc1 = nn.Linear(width, width)
        self.film = nn.Linear(cond_dim, 2 * width)                   # -> (scale, bias), width each
        self.fc2 = nn.Linear(width, width)

    def forward(self, x, film):
        """x (B, width), film (B, 2 * width) -> (B, width)."""
        h = self.fc1(nn.functional.mish(self.norm(x)))
        scale, bias = film.chunk(2, dim=1)                           # (B, width) each
        return x + self.fc2(nn.functional.mish(scale * h + bias))


class ResidualMLP(FiLMNetwork):
    """eps_theta(a_k, k | o) as a residual MLP over the flattened chunk (PolicyConfig.network='mlp'; not the
    authors' network): Linear(H dof -> width), mlp_blocks MLPResidualBlocks with FiLM, LayerNorm, Mish,
    Linear(width -> H dof). The same conditioning and interface as ConditionalUnet1D (FiLMNetwork), so the
    policy, its sampler and partial denoising do not know which one they hold. On one CPU thread it trains
    on ~8x more samples per CPU second than the (32, 64, 128) U-Net and samples ~10x faster
    (benchmarks/bench_diffusion.py): the CPU profiles' choice, measured in benchmarks/README.md; the paper
    profile keeps the U-Net.
    """

    def __init__(self, cfg):
        super().__init__()
        cond_dim = self._init_step_features(cfg)
        self.horizon, self.dof = cfg.horizon, cfg.dof
        self.inp = nn.Linear(cfg.horizon * cfg.dof, cfg.mlp_width)
        self.blocks = nn.ModuleList([MLPResidualBlock(cfg.mlp_width, cond_dim) for _ in range(cfg.mlp_blocks)])
        self.final = nn.Sequential(nn.LayerNorm(cfg.mlp_width), nn.Mish(),
                                   nn.Linear(cfg.mlp_width, cfg.horizon * cfg.dof))
        nn.init.zeros_(self.final[-1].weight)                        # as the U-Net: starts predicting eps = 0
        nn.init.zeros_(self.final[-1].bias)
        self._init_film(cfg)

    def residual_blocks(self):
        yield from self.blocks

    def forward(self, a, film):
        """a (B, H, dof) noisy normalized chunk, film (B, F) = obs_terms + step_table[k] -> eps (B, H, dof)."""
        x = self.inp(a.flatten(1))                                   # (B, width)
        for block, f in zip(self.blocks, film.split(self.film_sizes, dim=1)):
            x = block(x, f)                                          # (B, width)
        return self.final(x).reshape(-1, self.horizon, self.dof)     # (B, H, dof)


NETWORKS = {"unet": ConditionalUnet1D, "mlp": ResidualMLP}


# ----------------------------------------------------------------------------------------------
# Observation encoders: how the network reads the observation (PolicyConfig.obs_encoder)
#
# The observation is one flat vector. An encoder may own the last entries of it (`sizes`: how many, and how many
# features it gives in their place): normalize_obs min-max normalizes the entries before them and hands its own
# entries on as they are, at the end of its output (after the velocity, joint_obs); the encoder's forward maps
# that whole row to the FiLM network's observation features (cond_input_dim of them). Being part of FiLM's
# observation term, it runs once per sampling call, not once per diffusion step. The paper's path reads the
# observation as numbers ('flat'); a research variant registers its own encoder here when its module is imported
# (experiment/image_obs.py: 'image_cnn', a CNN over a camera image at the observation's end).


class FlatObservation(nn.Module):
    """OBS_ENCODERS['flat']: the normalized observation (and velocity) are the observation features as they are."""

    @staticmethod
    def sizes():
        """(entries at the observation's end this encoder owns, features it gives for them): none."""
        return 0, 0

    def forward(self, obs_norm):
        return obs_norm


OBS_ENCODERS = {"flat": FlatObservation}


# ----------------------------------------------------------------------------------------------
# Normalization to [-1, 1] (DiffusionPolicy.fit_normalizer)
#
# With PolicyConfig.joint_obs (the authors' relative actions, PAPER_SETUP.md §1) the observation starts with
# (q_t, q_{t-1}) and
#   - the chunk is normalized relative to the current joint position, (a - q_t - center) / half: a chunk
#     moves about H * max_step (1 rad planar) while the joints range over 2 pi, so normalized over the
#     joint range the motion would be a small fraction of [-1, 1], resolved only by the last diffusion steps;
#   - the velocity q_t - q_{t-1}, min-max normalized, is appended to the network's observation input (as
#     the difference of two inputs of range 2 pi it would be a tiny signal for the first layer to find).


def _register_normalizer(policy):
    """DiffusionPolicy's min-max normalizer (center, half range) -> [-1, 1]: buffers, so part of state_dict and
    saved with the weights; identity until fit_normalizer."""
    cfg = policy.cfg
    policy.register_buffer("obs_center", torch.zeros(cfg.obs_dim))
    policy.register_buffer("obs_half", torch.ones(cfg.obs_dim))
    policy.register_buffer("vel_center", torch.zeros(cfg.dof))    # used with joint_obs only
    policy.register_buffer("vel_half", torch.ones(cfg.dof))
    policy.register_buffer("act_center", torch.zeros(cfg.dof))
    policy.register_buffer("act_half", torch.ones(cfg.dof))
    policy.register_buffer("normalizer_fitted", torch.zeros((), dtype=torch.bool))


def _normalize_obs(policy, obs):
    """DiffusionPolicy.normalize_obs: raw observations (B, obs_dim) -> the network's observation input: the
    normalized low-dimensional observation, then the normalized velocity (dof) if joint_obs, then the entries
    the observation encoder owns, as they are (their normalizer stays the identity: the encoder reads them,
    FiLMNetwork.obs_features). With the 'flat' encoder: (B, cfg.cond_input_dim)."""
    cfg = policy.cfg
    o = (obs - policy.obs_center) / policy.obs_half
    if not cfg.joint_obs:
        return o
    d, low = cfg.dof, cfg.low_dim
    velocity = (obs[:, :d] - obs[:, d:2 * d] - policy.vel_center) / policy.vel_half
    return torch.cat([o[:, :low], velocity, o[:, low:]], dim=1)       # the encoder's entries stay at the end


def _action_origin(policy, obs):
    """(B, 1, dof): what chunks are measured from -- q_t with joint_obs, else nothing (zero)."""
    if not policy.cfg.joint_obs:
        return torch.zeros((), device=policy.device)
    if obs is None:
        raise ValueError("with joint_obs, normalize_actions / unnormalize_actions need the raw obs")
    return obs[:, None, :policy.cfg.dof]


def _fit_min_max(policy, obs, actions):
    """DiffusionPolicy.fit_normalizer: min-max (center, half range) of the observations, the velocities
    (joint_obs) and the actions (relative to q_t with joint_obs) into the policy's buffers. Without joint_obs
    the actions may also be any (M, dof) set of actions."""
    cfg = policy.cfg
    obs = check_array("obs", obs, (None, cfg.obs_dim))[:, :cfg.low_dim]  # the encoder's entries are not fitted
    obs = np.asarray(obs.cpu() if torch.is_tensor(obs) else obs, dtype=np.float64)
    actions = np.asarray(actions, dtype=np.float64)
    if actions.ndim == 3 or cfg.joint_obs:
        check_array("actions", actions, (len(obs) if cfg.joint_obs else None, cfg.horizon, cfg.dof))
    else:
        check_array("actions", actions, (None, cfg.dof))
    if len(obs) == 0 or len(actions) == 0:
        raise ValueError("fit_normalizer needs at least one observation and one action")
    parts = {"obs": obs}
    if cfg.joint_obs:
        q, q_prev = obs[:, :cfg.dof], obs[:, cfg.dof:2 * cfg.dof]
        parts["vel"] = q - q_prev
        actions = actions - q[:, None, :]                          # (N, H, dof) motion from q_t
    parts["act"] = actions.reshape(-1, cfg.dof)
    for prefix, x in parts.items():
        lo, hi = x.min(axis=0), x.max(axis=0)
        half = (hi - lo) / 2
        # A constant dimension would divide by zero: give it half range 1 so it maps to 0.
        half = np.where(half > 1e-6, half, 1.0)
        n = x.shape[1]
        getattr(policy, f"{prefix}_center")[:n].copy_(torch.as_tensor((hi + lo) / 2))
        getattr(policy, f"{prefix}_half")[:n].copy_(torch.as_tensor(half))
    policy.normalizer_fitted.fill_(True)


# ----------------------------------------------------------------------------------------------
# The per-row indexing of the schedule (q_sample, p_sample)


def _per_row(coef, k, like):
    """coef[k] shaped to broadcast against `like` (B, ...). k: int or (B,) long tensor."""
    if not torch.is_tensor(k):
        k = torch.tensor(k, device=coef.device)
    k = k.to(coef.device).long()
    if k.numel() and (int(k.min()) < 0 or int(k.max()) >= coef.shape[0]):
        raise ValueError(f"diffusion step k must be in 0..{coef.shape[0] - 1}, got {k.tolist()}")
    value = coef[k]
    return value.reshape(value.shape + (1,) * (like.dim() - value.dim()))


# ----------------------------------------------------------------------------------------------
# The noise draws of one reverse process (DiffusionPolicy.draw_noise)


def _draw_noise_rows(policy, B, generator=None):
    """All Gaussian draws of one reverse process, (B, K + 1, H, dof): [:, 0] is the starting noise, [:, 1 + k]
    is the z of the reverse step at code level k. Drawn row after row (one randn call each: torch's CPU
    normal sampler fills blocks of 16 numbers, so one big call would not split into the same per-row
    numbers), a row's draws do not depend on how the batch is split: sampling a batch equals sampling its
    rows one by one from the same generator."""
    shape = (B, policy.cfg.K + 1, policy.cfg.horizon, policy.cfg.dof)
    gdev = generator.device if generator is not None else torch.device("cpu")
    rows = [torch.randn(shape[1:], generator=generator, device=gdev) for _ in range(B)]
    return torch.stack(rows).to(policy.device) if rows else torch.empty(shape, device=policy.device)


# ----------------------------------------------------------------------------------------------
# The masked DDPM loss (DiffusionPolicy.loss(mask=...))
#
# A servo label (relabel.servo_return_chunk, PAPER_SETUP.md §6) holds its last position once it is back on
# the expert's path; those held steps are not the expert's and are left out of the loss.


def _masked_mse(eps_pred, eps, mask, device):
    """Mean of (eps_pred - eps)^2 over the unmasked (row, step, dof) entries; mask (B, H) bool, True = in the
    loss (all dof of a step share it)."""
    weight = torch.as_tensor(mask, device=device).to(eps.dtype)[:, :, None]  # (B, H, 1)
    squared = (eps_pred - eps) ** 2 * weight                       # (B, H, dof), masked steps -> 0
    return squared.sum() / (weight.sum() * eps.shape[-1]).clamp(min=1.0)


# ----------------------------------------------------------------------------------------------
# train()'s learning-rate schedule (the authors': warmup + cosine), EMA (ours) and progress lines


def lr_at(step, cfg):
    """Linear warmup to cfg.lr over warmup_steps, then cosine decay to 0 at cfg.schedule_steps (0: cfg.steps);
    with cfg.constant_lr, cfg.lr at every step."""
    if cfg.constant_lr:
        return cfg.lr
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    end = cfg.schedule_steps or cfg.steps
    progress = (step - cfg.warmup_steps) / max(1, end - cfg.warmup_steps)
    return cfg.lr * 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))


@torch.no_grad()
def update_ema(policy, step, decay):
    """policy.ema_net (the weights used for sampling) <- the EMA of policy.net after optimizer step `step`."""
    # Warm-up of the decay ((1 + t) / (10 + t), as in common EMA implementations) so that the EMA is not
    # dominated by the random initial weights during a short run.
    d = min(decay, (1.0 + step) / (10.0 + step))
    torch._foreach_lerp_(list(policy.ema_net.parameters()), list(policy.net.parameters()), 1.0 - d)


class _Progress:
    """train()'s progress lines: mean loss, rate and time left, every cfg.log_every optimizer steps and at
    least every cfg.log_seconds (wall clock); silent when log_every = 0."""

    def __init__(self, cfg, step, log):
        self.cfg, self.log = cfg, log
        self.t0, self.losses, self.last_step = time.time(), [], step

    def update(self, step, loss):
        """After optimizer step `step` with loss value `loss` (a float)."""
        cfg = self.cfg
        self.losses.append(loss)
        if cfg.log_every and (step % cfg.log_every == 0 or step == cfg.steps
                              or time.time() - self.t0 >= cfg.log_seconds):
            rate = (step - self.last_step) / max(time.time() - self.t0, 1e-9)
            self.log(f"step {step}/{cfg.steps} | loss {np.mean(self.losses):.4f} | {rate:.0f} steps/s | "
                     f"{(cfg.steps - step) / max(rate, 1e-9):.0f} s left")
            self.t0, self.losses, self.last_step = time.time(), [], step


# ----------------------------------------------------------------------------------------------
# Checkpoint files and train()'s resume plumbing


# v1 held the earlier residual-MLP epsilon network; v2 holds the U-Net. A v1 file cannot be loaded.
CHECKPOINT_FORMAT = "diffusion-policy-v2"


def _write_checkpoint(policy, path, extra=None):
    """DiffusionPolicy.save: written to path.tmp, then renamed, so that path never holds a half-written file."""
    payload = {"format": CHECKPOINT_FORMAT, "config": asdict(policy.cfg),
               "state_dict": {k: v.detach().cpu() for k, v in policy.state_dict().items()}}
    if extra is not None:
        payload["train_state"] = extra
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.tmp"
    torch.save(payload, tmp)
    os.replace(tmp, path)


class CheckpointDamagedError(ValueError):
    """A checkpoint file that cannot be read: truncated (a run killed while copying it), overwritten, or not
    a torch file at all."""


def _read_checkpoint(path):
    """The payload dict of a file written by DiffusionPolicy.save. FileNotFoundError if there is no file,
    CheckpointDamagedError if it cannot be read, ValueError if it is another format."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no policy checkpoint at {path!r}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except OSError:                                                    # unreadable (permissions, disk): not damage
        raise
    except Exception as err:                                           # EOFError, zip RuntimeError, UnpicklingError, ...
        raise CheckpointDamagedError(f"checkpoint {path} is damaged (truncated or not a checkpoint; torch.load "
                                     f"raised {type(err).__name__}): delete it and run again to re-make it") from None
    if not isinstance(payload, dict):
        raise CheckpointDamagedError(f"checkpoint {path} is damaged (it holds a {type(payload).__name__}, not a "
                                     f"checkpoint): delete it and run again to re-make it")
    if payload.get("format") == "diffusion-policy-v1":
        raise ValueError(f"{path!r} is a diffusion-policy-v1 checkpoint (the earlier residual-MLP network); "
                         f"this code reads {CHECKPOINT_FORMAT} (the U-Net): retrain the policy")
    if payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path!r} is not a {CHECKPOINT_FORMAT} checkpoint")
    return payload


# PolicyConfig fields that a checkpoint of an earlier version holds, with the one value this code reads it at: the
# camera-image observations moved to a research variant (experiment/image_obs.py: obs_encoder 'image_cnn').
RETIRED_POLICY_FIELDS = {"image_shape": (), "image_features": 64}


def _load_policy(cls, path, device="cpu"):
    """DiffusionPolicy.load: the policy saved at path. FileNotFoundError if there is none;
    CheckpointDamagedError (a ValueError) if the file is truncated or not a checkpoint of this code. Its network
    is rebuilt from its config: a variant's obs_encoder must be registered (its module imported) first."""
    payload = _read_checkpoint(path)
    config = dict(payload["config"])
    # a checkpoint written before PolicyConfig.schedule was deleted names it: only the authors' schedule remains
    if config.pop("schedule", "squaredcos") != "squaredcos":
        raise ValueError(f"{path!r} was trained with the linear noise schedule, deleted since (the squared-cosine "
                         f"schedule is the only one): retrain the policy")
    for name, value in RETIRED_POLICY_FIELDS.items():
        stored = config.pop(name, value)
        if (tuple(stored) if isinstance(stored, list) else stored) != value:
            raise ValueError(f"{path!r} is a policy of an earlier version with {name}={stored!r}: its image encoder "
                             f"is now the research variant experiment/image_obs.py (obs_encoder 'image_cnn', "
                             f"python dagger.py --env engine3d_image): retrain the policy")
    policy = cls(PolicyConfig(**config), device=device)
    policy.load_state_dict(payload["state_dict"])
    return policy


def _as_torch(x):
    """numpy arrays -> tensors inside nested dicts / lists (checkpoints are read with weights_only=True)."""
    if isinstance(x, dict):
        return {k: _as_torch(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_as_torch(v) for v in x]
    return torch.from_numpy(np.ascontiguousarray(x)) if isinstance(x, np.ndarray) else x


def _as_numpy(x):
    """The inverse of _as_torch."""
    if isinstance(x, dict):
        return {k: _as_numpy(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_as_numpy(v) for v in x]
    return x.numpy() if torch.is_tensor(x) else x


def _checkpoint_path(cfg, step):
    return cfg.checkpoint_path.replace("{step}", str(step))


def _save_training_checkpoint(policy, cfg, step, optimizer, rng, gen, sampler):
    """train()'s checkpoint after `step` steps: the policy plus everything a resumed run needs to continue
    with the same numbers (optimizer, both random streams, the sampler's state if it has one)."""
    policy.save(_checkpoint_path(cfg, step), extra={
        "step": step, "optimizer": optimizer.state_dict(),
        "numpy_rng": json.dumps(rng.bit_generator.state), "torch_rng": gen.get_state(),
        "train_config": json.dumps(asdict(cfg)),
        "sampler": _as_torch(sampler.state_dict()) if hasattr(sampler, "state_dict") else None})


def _resume_training(path, policy, optimizer, rng, gen, sampler):
    """Restore what _save_training_checkpoint wrote into policy, optimizer, rng and gen (and a sampler with
    load_state_dict(), e.g. a pool of generated pairs); returns the step to continue from. The resumed
    train() run ends with the same numbers as an uninterrupted one."""
    payload = _read_checkpoint(path)
    if "train_state" not in payload:
        raise ValueError(f"{path!r} holds no training state (was it written by policy.save?)")
    policy.load_state_dict(payload["state_dict"])
    state = payload["train_state"]
    optimizer.load_state_dict(state["optimizer"])
    rng.bit_generator.state = json.loads(state["numpy_rng"])
    gen.set_state(state["torch_rng"])
    if state.get("sampler") is not None and hasattr(sampler, "load_state_dict"):
        sampler.load_state_dict(_as_numpy(state["sampler"]))
    return int(state["step"])


def _continue_training(path, policy, optimizer, cfg):
    """train(continue_from=path): the weights, AdamW state and step count of a checkpoint written by train();
    returns the step to continue from. The random streams stay the new run's (its own data, its own seed)."""
    payload = _read_checkpoint(path)
    if "train_state" not in payload:
        raise ValueError(f"continue_from={path!r} holds no training state (the optimizer): save pi_0 with "
                         f"train()'s checkpoint_steps including its last step")
    state = payload["train_state"]
    step = int(state["step"])
    if step >= cfg.steps:
        raise ValueError(f"continue_from={path!r} is at step {step}; TrainConfig.steps={cfg.steps} counts the "
                         f"total, so it must be larger to train on")
    policy.load_state_dict(payload["state_dict"])
    optimizer.load_state_dict(state["optimizer"])
    return step


# ----------------------------------------------------------------------------------------------
# Demo data: a 2-D toy task with two modes (go up-right or down-left); the policy must keep both.


def toy_two_mode_data(n, H=4, seed=0):
    """obs ~ U[-1, 1]^2; chunk = obs + t * v for t = 1..H, v = +(0.5, 0.5) or -(0.5, 0.5) at random."""
    rng = np.random.default_rng(seed)
    obs = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    sign = rng.choice([-1.0, 1.0], size=(n, 1, 1))
    steps = np.arange(1, H + 1, dtype=np.float32)[None, :, None] / H   # (1, H, 1)
    chunks = obs[:, None, :] + sign * 0.5 * steps                      # (n, H, 2)
    return obs, chunks.astype(np.float32)


if __name__ == "__main__":
    obs, chunks = toy_two_mode_data(4000, H=4)
    policy = DiffusionPolicy(PolicyConfig(obs_dim=2, dof=2, horizon=4, n_act=2, down_dims=(32, 64)))
    train(policy, obs, chunks, TrainConfig(steps=3000, warmup_steps=200, log_every=500))
    test_obs = np.zeros((200, 2), dtype=np.float32)
    samples = policy.sample(test_obs, generator=torch.Generator().manual_seed(0))
    last = samples[:, -1, :]                                           # (200, 2) end of each chunk
    up = last.sum(axis=1) > 0
    print(f"from the origin: {up.mean():.0%} of chunks end up-right, {1 - up.mean():.0%} down-left")
    print(f"mean end point of each mode: {last[up].mean(0).round(3)} and {last[~up].mean(0).round(3)} "
          "(data: [0.5 0.5] and [-0.5 -0.5])")
