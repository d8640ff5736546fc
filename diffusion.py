"""A DDPM diffusion policy over action chunks, written from the DDPM equations (Ho et al. 2020).

Paper map (the paper, Sec. IV-B "Partial Denoising as a Learned Action Interpolator", Sec. IV-C):
  - noise schedule beta_k, alpha_k = 1 - beta_k, alphabar_k (defined with Eqs. 5-6) .. make_schedule, Schedule
  - forward process, Eq. (5), in closed form ............................. q_sample
  - reverse process, Eq. (6), one step ................................... p_sample
  - epsilon network eps_theta(a_k, k | o) over a chunk (the authors') .... ConditionalUnet1D (NETWORKS)
  - the policy pi_theta(a_{t:t+H} | o_t): normalizer, DDPM loss, sampling  DiffusionPolicy
  - action chunks of horizon H; the label rule (Sec. IV-C) ............... expert_runs, label_mask, chunk_dataset
  - BC, co-training, fine-tuning (Sec. IV-A steps 1, 4, 6) ............... train (lr schedule, EMA)

Index convention (used everywhere): the paper numbers the diffusion steps k = 1..K, alphabar_k = prod_{s<=k}
alpha_s, alphabar_0 = 1 (the clean chunk a_0); the code indexes its arrays k = 0..K-1, so code index k <-> paper
step k + 1: betas[k] = beta_{k+1}, alphas_cumprod[k] = alphabar_{k+1}, alphas_cumprod_prev[k] = alphabar_k.
A chunk "at level k" is q_sample(schedule, a0, k, eps) = sqrt(alphabar_{k+1}) a0 + sqrt(1 - alphabar_{k+1}) eps,
the network is told that k, and p_sample(..., a_k, k) returns the chunk at level k - 1; from level 0 the clean
chunk (the posterior variance at k = 0 is zero). Pure noise N(0, I) stands in for level K - 1.

The network is the authors' (benchmarks/SETUP.md §2: LeRobot's diffusion policy, the CNN variant of Chi et al. 2023);
on a CPU it is the expensive part of the project (benchmarks/bench_train_step.py). It is written with torch's own
layers, eps_theta in one function (FiLMNetwork.forward); experiment/cpu_kernels.py computes the same network with
its FiLM maps split (the step part of all K steps once per sampling call) and its Linear and Mish faster where that
was measured to pay.
"""

import copy
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn as nn


# ---- Config ------------------------------------------------------------------------------------------------------
@dataclass
class PolicyConfig:
    # the paper (Sec. IV-B/C) and the authors' setup (benchmarks/SETUP.md §1-2); dagger.Config holds H, n_act, K
    obs_dim: int                 # length of the flat observation o_t; it starts with (q_t, q_{t-1}) (envs.py)
    dof: int                     # joints per action, d (3 planar, 6 UR5)
    horizon: int                 # H: actions per predicted chunk (steps)
    n_act: int                   # actions of a chunk executed before re-planning (steps; used by the rollout loop)
    K: int                       # diffusion steps (the authors': 100)
    network: str = "unet"        # a NETWORKS name: 'unet' (the authors'), 'mlp' (~8x the samples per CPU second)
    down_dims: tuple = (64, 128, 256)  # U-Net channels per level (the authors: (128, 256, 512))
    mlp_width: int = 256         # network='mlp': width of the hidden layers
    mlp_blocks: int = 3          # network='mlp': FiLM-conditioned residual blocks
    kernel_size: int = 5         # temporal convolution kernel (steps; odd: padding k // 2 keeps the length)
    n_groups: int = 8            # GroupNorm groups; every down_dim must be a multiple
    step_embed_dim: int = 128    # size of the sinusoidal diffusion-step embedding and of the step features
    obs_encoder: str = "FlatObservation"  # the class the network reads the observation with, by name (FlatObservation:
                                 # as numbers; a variant's env hands in its own class, dagger.make_policy records it)
    obs_encoder_args: dict = field(default_factory=dict)   # its keyword arguments (a variant's env gives them)
    obs_encoder_sizes: tuple = (0, 0)  # its sizes(**args): (observation entries at the end it reads, features it gives)
    seed: int = 0                # seed of the weight initialisation

    def __post_init__(self):
        """ValueError naming every rule a field breaks and what would be valid; down_dims becomes an int tuple."""
        self.down_dims = tuple(int(d) for d in self.down_dims)         # a list from a JSON config, numpy ints
        sizes = ("obs_dim", "dof", "horizon", "n_act", "K", "kernel_size", "n_groups", "step_embed_dim", "mlp_width",
                 "mlp_blocks")
        halvings = len(self.down_dims) - 1
        self.obs_encoder_sizes = tuple(int(n) for n in self.obs_encoder_sizes)
        rules = {f"network must be one of {', '.join(NETWORKS)}": self.network in NETWORKS,
                 f"{', '.join(sizes)} must be positive ints":
                     all(isinstance(getattr(self, n), (int, np.integer)) and getattr(self, n) >= 1 for n in sizes),
                 f"down_dims must be non-empty, multiples of n_groups={self.n_groups} (GroupNorm)": bool(self.down_dims)
                     and self.n_groups >= 1 and all(d >= 1 and d % self.n_groups == 0 for d in self.down_dims),
                 f"horizon must be divisible by 2**(len(down_dims) - 1) = {2 ** halvings} (the U-Net halves the "
                 f"chunk {halvings} times)": self.network != "unet" or self.horizon % 2 ** halvings == 0,
                 "kernel_size must be odd (padding k // 2 keeps the length)": self.kernel_size % 2 == 1,
                 "step_embed_dim must be even": self.step_embed_dim % 2 == 0,
                 "n_act must be <= horizon": self.n_act <= self.horizon}
        broken = [rule for rule, holds in rules.items() if not holds]
        if broken:
            raise ValueError(f"PolicyConfig: {'; '.join(broken)}; got {self}")
        if self.low_dim < 2 * self.dof:
            raise ValueError(f"PolicyConfig.obs_dim={self.obs_dim} must be longer: the observation starts with "
                             f"(q_t, q_t-1), 2 * dof = {2 * self.dof} numbers, before the {self.encoder_sizes[0]} "
                             f"entries the obs_encoder reads")

    @property
    def encoder_sizes(self):     # (observation entries at its end the encoder reads, features it gives for them)
        return self.obs_encoder_sizes

    @property
    def low_dim(self):           # entries of the observation min-max normalized: all before the encoder's
        return self.obs_dim - self.encoder_sizes[0]

    @property
    def cond_input_dim(self):    # observation features for FiLM: low-dim obs, velocity, the encoder's
        return self.low_dim + self.dof + self.encoder_sizes[1]


@dataclass
class TrainConfig:
    # the paper (Sec. IV-A) and the authors' setup (benchmarks/SETUP.md §2)
    steps: int = 10_000              # optimizer steps of this run (the total, also when resuming)
    batch_size: int = 256            # chunks per step (base + augmented)
    lr: float = 1e-3                 # peak AdamW learning rate (after warmup)
    weight_decay: float = 1e-6       # AdamW weight decay (the authors')
    warmup_steps: int = 500          # optimizer steps of linear warmup from 0 to lr, then cosine decay to 0
    schedule_steps: int = 0          # where the cosine reaches 0 (0: steps; pi_0 continued: benchmarks/SETUP.md §2)
    lr_schedule: object = None       # lr_schedule(step, cfg): the learning rate; None: warmup_cosine (the authors')
    aug_fraction: float = 0.0        # fraction of each batch drawn from `sampler` (co-training, Sec. IV-A step 4)
    obs_noise: object = 0.0          # observation noise std in raw units (authors': 0.01 rad, 0.005 m), or (obs_dim,)
    # not in the paper
    ema_decay: float = 0.999         # EMA of the weights used for sampling, over ~1/(1 - decay) steps (authors: none)
    seed: int = 0                    # seeds batch indices (numpy) and diffusion noise (torch)
    log_every: int = 500             # optimizer steps between progress lines (0 = silent)
    log_seconds: float = 10.0        # ... and a line at least this often (seconds, wall clock) unless silent
    checkpoint_steps: tuple = ()     # optimizer steps after which train() hands its state to on_checkpoint

    def __post_init__(self):
        """ValueError on a bad field; obs_noise becomes a float or a tuple of floats."""
        noise = np.asarray(self.obs_noise, dtype=np.float64)
        rules = {"steps >= 0": self.steps >= 0, "batch_size >= 1": self.batch_size >= 1,
                 "warmup_steps >= 0": self.warmup_steps >= 0,
                 "aug_fraction in [0, 1]": 0 <= self.aug_fraction <= 1,
                 "ema_decay in [0, 1)": 0 <= self.ema_decay < 1,
                 "obs_noise a std >= 0 or one per observation entry":
                     noise.ndim <= 1 and np.all(np.isfinite(noise)) and np.all(noise >= 0),
                 "schedule_steps 0 (= steps) or >= steps":
                     self.schedule_steps == 0 or self.schedule_steps >= self.steps,
                 "lr_schedule None or a function (step, cfg) -> lr":
                     self.lr_schedule is None or callable(self.lr_schedule)}
        broken = [rule for rule, holds in rules.items() if not holds]
        if broken:
            raise ValueError(f"TrainConfig needs {'; '.join(broken)}; got {self}")
        self.obs_noise = float(noise) if noise.ndim == 0 else tuple(float(x) for x in noise)
        self.checkpoint_steps = tuple(int(s) for s in self.checkpoint_steps)


def check_array(name, x, shape):
    """x (numpy or torch) must be finite and of the given shape (None = any size on that axis); else ValueError."""
    x = np.asarray(x) if not torch.is_tensor(x) else x
    fits = x.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, x.shape))
    if not (fits and (torch.isfinite(x).all() if torch.is_tensor(x) else np.isfinite(x).all())):
        want = tuple("N" if s is None else s for s in shape)
        raise ValueError(f"{name} must have shape {want} and finite entries, got shape {tuple(x.shape)}")
    return x


# ---- Noise schedule, forward and reverse process (DDPM, Ho et al. 2020; names follow the DDPM paper) -------------
@dataclass
class Schedule:
    """All per-step DDPM coefficients, float32 tensors of shape (K,), indexed k = 0..K-1 = paper k + 1."""
    betas: torch.Tensor                          # beta_{k+1}
    alphas: torch.Tensor                         # alpha = 1 - beta
    alphas_cumprod: torch.Tensor                 # alphabar_{k+1} = prod_{s<=k} alphas[s]
    alphas_cumprod_prev: torch.Tensor            # alphabar_k, with alphabar_0 = 1
    sqrt_alphas_cumprod: torch.Tensor            # Eq. (5) closed form: mean coefficient
    sqrt_one_minus_alphas_cumprod: torch.Tensor  # Eq. (5) closed form: noise coefficient
    sqrt_recip_alphas_cumprod: torch.Tensor      # a0 from eps: a0 = sqrt(1/abar) a_k - sqrt(1/abar - 1) eps
    sqrt_recipm1_alphas_cumprod: torch.Tensor
    posterior_variance: torch.Tensor             # beta~ = beta (1 - abar_prev) / (1 - abar)  ("fixed small")
    posterior_mean_coef1: torch.Tensor           # multiplies the (clipped) predicted clean chunk a0
    posterior_mean_coef2: torch.Tensor           # multiplies the current noisy chunk a_k

    @property
    def K(self):
        return int(self.betas.shape[0])

    def to(self, device):
        return Schedule(**{name: value.to(device) for name, value in self.__dict__.items()})


def make_schedule(K):
    """The DDPM coefficients of the squared-cosine schedule (the authors') for K steps (float64, stored float32)."""
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


def _per_row(coef, k, like):
    """coef[k] shaped to broadcast against `like` (B, ...). k: int or (B,) long tensor."""
    k = torch.as_tensor(k, device=coef.device).long()
    if k.numel() and (int(k.min()) < 0 or int(k.max()) >= coef.shape[0]):
        raise ValueError(f"diffusion step k must be in 0..{coef.shape[0] - 1}, got {k.tolist()}")
    value = coef[k]
    return value.reshape(value.shape + (1,) * (like.dim() - value.dim()))


def q_sample(schedule, a0, k, eps):
    """Forward process: the chunk a0 diffused to code level k (paper step k + 1) with noise eps. Eq. (5) applied
    k + 1 times, a_k = sqrt(alpha_k) a_{k-1} + sqrt(1 - alpha_k) eps_k, collapses (a sum of independent Gaussians
    is Gaussian) to a_k = sqrt(alphabar_k) a_0 + sqrt(1 - alphabar_k) eps, eps ~ N(0, I)."""
    # >>> exercise 1: the noise schedule and q_sample (Eq. 5)
    # Eq. (5), closed form over k + 1 steps.
    return (_per_row(schedule.sqrt_alphas_cumprod, k, a0) * a0
            + _per_row(schedule.sqrt_one_minus_alphas_cumprod, k, a0) * eps)
    # <<< exercise 1


def p_sample(schedule, eps_pred, a_k, k, generator=None, noise=None, clip=True):
    """Reverse process: one step from code level k to k - 1 (from k = 0: the clean chunk), through the predicted
    clean chunk as in DDPM's code and diffusion policy:
        a0_hat = (a_k - sqrt(1 - alphabar_k) eps_pred) / sqrt(alphabar_k), clipped to [-1, 1]
        a_{k-1} = posterior_mean_coef1 a0_hat + posterior_mean_coef2 a_k + sqrt(posterior_variance) z
    Unclipped, the mean is (a_k - beta_k / sqrt(1 - alphabar_k) eps_pred) / sqrt(alpha_k): Eq. (6) with sigma_k^2 =
    the posterior variance (tested). The clip keeps the chunk in the normalized action box of the data (diffusion
    policy's clip_sample). noise: the z to use (B, H, dof); drawn from `generator` when None."""
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


# ---- eps_theta(a_k, k | o): Chi et al.'s 1-D temporal U-Net, FiLM-conditioned on (k, o) (benchmarks/SETUP.md §2)
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
    """Two Conv1dBlocks with FiLM (Perez et al.) between them, h <- scale * h + bias per channel, plus a residual
    path (1 x 1 conv if the width changes). It owns its map `film` but receives film(Mish(cond)) (FiLMNetwork)."""

    def __init__(self, in_channels, out_channels, cond_dim, kernel_size, n_groups):
        super().__init__()
        self.conv1 = Conv1dBlock(in_channels, out_channels, kernel_size, n_groups)
        self.film = nn.Linear(cond_dim, 2 * out_channels)            # -> (scale, bias), out_channels each
        self.conv2 = Conv1dBlock(out_channels, out_channels, kernel_size, n_groups)
        self.residual = (nn.Conv1d(in_channels, out_channels, 1) if in_channels != out_channels
                         else nn.Identity())

    def forward(self, x, film):
        """x (B, in_channels, T), film (B, 2 * out_channels) -> (B, out_channels, T)."""
        h = self.conv1(x)                                            # (B, out, T)
        scale, bias = film[:, :, None].chunk(2, dim=1)               # (B, out, 1) each
        h = torch.addcmul(bias, scale, h)                            # scale * h + bias
        return self.conv2(h) + self.residual(x)                      # (B, out, T)


class FiLMNetwork(nn.Module):
    """What both epsilon networks share, eps_theta(a_k, k | o) = body(a_k, film): every residual block's FiLM
    (scale, bias) is its map `film` of Mish([step features of k, observation features]) (Chi et al.). A subclass
    builds its blocks and its output layer `final` in build(), lists the blocks in residual_blocks() in the order
    its body(a, film) uses them, and body reads all blocks' (scale, bias) from one row. experiment/cpu_kernels.py
    computes the same FiLM with the map split along its input (FiLMTable: the step part of all K steps at once)."""

    def __init__(self, cfg, obs_encoder=None):
        super().__init__()
        dsed = cfg.step_embed_dim
        self.K, self.step_embed_dim = cfg.K, dsed
        # Step features: sinusoidal embedding -> Linear(dsed, 4 dsed) -> Mish -> Linear(4 dsed, dsed) (Chi et al.).
        self.step_encoder = nn.Sequential(nn.Linear(dsed, 4 * dsed), nn.Mish(), nn.Linear(4 * dsed, dsed))
        self.cond_mish = nn.Mish()                                     # every FiLM map reads Mish(condition)
        self.build(cfg, dsed + cfg.cond_input_dim)                    # FiLM input: [step features, obs features]
        # Zero-init output: the untrained net predicts eps = 0, so training starts at loss ~1 (stable).
        nn.init.zeros_(self.final[-1].weight)
        nn.init.zeros_(self.final[-1].bias)
        self.film_sizes = [b.film.out_features for b in self.residual_blocks()]
        self.film_size = sum(self.film_sizes)
        # built last, so an encoder with weights leaves the others' initialisation as without it
        self.obs_encoder = (obs_encoder or FlatObservation)(**cfg.obs_encoder_args)

    def step_features(self, k):
        """(N,) long diffusion steps -> (N, dsed) step features."""
        return self.step_encoder(step_embedding(k, self.step_embed_dim))

    def encode(self, obs_norm):
        """The observation's features (B, .) of normalize_obs's output: what eps_theta reads of o, computed once
        for all the reverse steps of a sampling call (its rows can be picked: features[rows])."""
        return self.obs_encoder(obs_norm)

    def forward(self, a, k, features):
        """eps_theta(a_k, k | o): a (B, H, dof) noisy normalized chunk, k (B,) long code levels, features =
        encode(o) -> the predicted noise (B, H, dof)."""
        cond = self.cond_mish(torch.cat([self.step_features(k), features], dim=1))       # (B, dsed + features)
        film = torch.cat([block.film(cond) for block in self.residual_blocks()], dim=1)  # (B, F): every block's
        return self.body(a, film)


class ConditionalUnet1D(FiLMNetwork):
    """eps_theta(a_k, k | o): the noisy chunk (B, H, dof) in, the predicted noise (B, H, dof) out.

    With down_dims (c_0, .., c_L) and T = H:
      encoder, level l:  two residual blocks to width c_l at length T / 2^l, kept as a skip, then a stride-2
                         Conv1d halves the length (not after the deepest level);
      middle:            two residual blocks at width c_L;
      decoder, L steps:  concatenate the skip of the same length, two residual blocks to the next shallower
                         width, a ConvTranspose1d doubles the length (as in Chi et al.'s, c_0's skip goes unused);
      output:            a Conv1dBlock and a 1 x 1 Conv1d back to dof channels.
    """

    def build(self, cfg, cond_dim):
        dims = cfg.down_dims

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

    def residual_blocks(self):
        """All ConditionalResidualBlocks in the order forward() uses them: the layout of the FiLM vector."""
        for first, second, _ in self.down:
            yield from (first, second)
        yield from self.mid
        for first, second, _ in self.up:
            yield from (first, second)

    def body(self, a, film):
        """a (B, H, dof) noisy normalized chunk, film (B, F) every block's (scale, bias) -> eps (B, H, dof)."""
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
        self.film = nn.Linear(cond_dim, 2 * width)                   # -> (scale, bias), width each (film_weights)
        self.fc2 = nn.Linear(width, width)
        self.mish = nn.Mish()

    def forward(self, x, film):
        """x (B, width), film (B, 2 * width) -> (B, width)."""
        h = self.fc1(self.mish(self.norm(x)))                        # (B, width)
        scale, bias = film.chunk(2, dim=1)                           # (B, width) each
        return x + self.fc2(self.mish(torch.addcmul(bias, scale, h)))  # FiLM: scale * h + bias


class ResidualMLP(FiLMNetwork):
    """eps_theta(a_k, k | o) over the flattened chunk (network='mlp'; the CPU profiles', not the authors'):
    Linear(H dof -> width), mlp_blocks MLPResidualBlocks, LayerNorm, Mish, Linear(width -> H dof). The same
    FiLM interface as ConditionalUnet1D, so nothing else knows which one it holds. Measured: benchmarks/HISTORY.md."""

    def build(self, cfg, cond_dim):
        self.horizon, self.dof = cfg.horizon, cfg.dof
        self.inp = nn.Linear(cfg.horizon * cfg.dof, cfg.mlp_width)
        self.blocks = nn.ModuleList([MLPResidualBlock(cfg.mlp_width, cond_dim) for _ in range(cfg.mlp_blocks)])
        self.final = nn.Sequential(nn.LayerNorm(cfg.mlp_width), nn.Mish(),
                                   nn.Linear(cfg.mlp_width, cfg.horizon * cfg.dof))

    def residual_blocks(self):
        yield from self.blocks

    def body(self, a, film):
        """a (B, H, dof) noisy normalized chunk, film (B, F) every block's (scale, bias) -> eps (B, H, dof)."""
        x = self.inp(a.flatten(1))                                   # (B, width)
        for block, f in zip(self.blocks, film.split(self.film_sizes, dim=1)):
            x = block(x, f)                                          # (B, width)
        return self.final(x).reshape(-1, self.horizon, self.dof)     # (B, H, dof)


NETWORKS = {"unet": ConditionalUnet1D, "mlp": ResidualMLP}


class FlatObservation(nn.Module):
    """The policy's observation encoder: the normalized observation and velocity are the features as they are. A
    variant's encoder may own the observation's last entries (sizes(): how many, and the features it gives for
    them); normalize_obs hands those on unnormalized, at the end (experiment/image_obs.py's ImageEncoder)."""

    @staticmethod
    def sizes():
        return 0, 0

    def forward(self, obs_norm):
        return obs_norm



# ---- The policy: normalizer, the DDPM loss, sampling by the reverse process --------------------------------------
class DiffusionPolicy(nn.Module):
    """pi_theta(a_{t:t+H} | o_t): DDPM over action chunks, with an EMA copy of eps_theta for sampling.

    The observation starts with (q_t, q_{t-1}). Chunks are learned relative to q_t and the network also sees the
    velocity q_t - q_{t-1} (more precise first actions than absolute chunks: benchmarks/HISTORY.md).
    Observations, velocities and relative chunks are min-max normalized to [-1, 1] (fitted on the dataset, saved
    with the weights); the interface stays in joint units: sample() returns chunks of joint positions.
    """

    def __init__(self, cfg, device="cpu", obs_encoder=None):
        super().__init__()
        self.cfg = cfg
        with torch.random.fork_rng(devices=[]):                       # init from cfg.seed; caller's RNG untouched
            torch.manual_seed(cfg.seed)
            self.net = NETWORKS[cfg.network](cfg, obs_encoder)         # eps_theta (obs_encoder: the env's class)
        self.ema_net = copy.deepcopy(self.net).requires_grad_(False)
        # the min-max normalizer (center, half range): buffers, saved with the weights; identity until fitted
        for prefix, n in (("obs", cfg.obs_dim), ("vel", cfg.dof), ("act", cfg.dof)):
            self.register_buffer(f"{prefix}_center", torch.zeros(n))
            self.register_buffer(f"{prefix}_half", torch.ones(n))
        self.register_buffer("normalizer_fitted", torch.zeros((), dtype=torch.bool))
        self.schedule = make_schedule(cfg.K)
        self.to(device)

    @property
    def device(self):
        return self.obs_center.device

    def _apply(self, fn, *args, **kwargs):     # .to(device): the schedule (derived, not a buffer) follows
        super()._apply(fn, *args, **kwargs)
        self.schedule = make_schedule(self.cfg.K).to(self.obs_center.device)
        return self

    def fit_normalizer(self, obs, actions):
        """Min-max (center, half range) of the observations (N, obs_dim) (the encoder's entries excepted), the
        velocities and the chunks (N, H, dof) relative to q_t, in joint units."""
        cfg = self.cfg
        obs = np.asarray(obs.cpu() if torch.is_tensor(obs) else obs, dtype=np.float64)[:, :cfg.low_dim]
        actions = check_array("actions", np.asarray(actions, dtype=np.float64), (len(obs), cfg.horizon, cfg.dof))
        q, q_prev = obs[:, :cfg.dof], obs[:, cfg.dof:2 * cfg.dof]
        parts = {"obs": obs, "vel": q - q_prev, "act": (actions - q[:, None, :]).reshape(-1, cfg.dof)}
        for prefix, x in parts.items():
            lo, hi = x.min(axis=0), x.max(axis=0)
            half = (hi - lo) / 2
            half = np.where(half > 1e-6, half, 1.0)                    # a constant dimension maps to 0
            n = x.shape[1]
            getattr(self, f"{prefix}_center")[:n].copy_(torch.as_tensor((hi + lo) / 2))
            getattr(self, f"{prefix}_half")[:n].copy_(torch.as_tensor(half))
        self.normalizer_fitted.fill_(True)

    def normalize_obs(self, obs):
        """Raw (B, obs_dim) -> the network's observation input (B, cond_input_dim with 'flat'): the normalized
        low-dim observation, the normalized velocity (dof), the encoder's entries as they are."""
        d, low = self.cfg.dof, self.cfg.low_dim
        o = (obs - self.obs_center) / self.obs_half
        velocity = (obs[:, :d] - obs[:, d:2 * d] - self.vel_center) / self.vel_half
        return torch.cat([o[:, :low], velocity, o[:, low:]], dim=1)       # the encoder's entries stay at the end

    def normalize_actions(self, a, obs):       # chunks (B, H, dof), joint units -> [-1, 1] relative to q_t; obs raw
        return (a - obs[:, None, :self.cfg.dof] - self.act_center) / self.act_half

    def unnormalize_actions(self, a, obs):     # the inverse of normalize_actions
        return a * self.act_half + self.act_center + obs[:, None, :self.cfg.dof]

    def encode(self, obs_norm, use_ema=True):  # the network's observation features (FiLMNetwork.encode)
        return (self.ema_net if use_ema else self.net).encode(obs_norm)

    def predict_eps(self, a_k_norm, k, features, use_ema=True):
        """eps_theta(a_k, k | o): a_k_norm (B, H, dof), k (B,) long or an int, features = self.encode(obs_norm,
        use_ema) of o = normalize_obs(obs) -> (B, H, dof)."""
        B = a_k_norm.shape[0]
        k = k.to(self.device).long() if torch.is_tensor(k) else torch.full((B,), int(k), device=self.device)
        return (self.ema_net if use_ema else self.net)(a_k_norm, k, features)   # (B, H, dof)

    def loss(self, obs_norm, chunk_norm, generator=None, mask=None):
        """DDPM's simple loss: || eps - eps_theta(q_sample(a0, k, eps), k | o) ||^2, k ~ U{0..K-1}. mask: optional
        (B, H) bool, True = the chunk step is in the loss (a servo label's held steps not: benchmarks/SETUP.md §6)."""
        B = chunk_norm.shape[0]
        gdev = generator.device if generator is not None else self.device
        k = torch.randint(0, self.cfg.K, (B,), generator=generator, device=gdev).to(self.device)
        eps = torch.randn(chunk_norm.shape, generator=generator, device=gdev).to(self.device)
        a_k = q_sample(self.schedule, chunk_norm, k, eps)              # Eq. (5)
        eps_pred = self.predict_eps(a_k, k, self.encode(obs_norm, use_ema=False), use_ema=False)  # (B, H, dof)
        if mask is None:
            return nn.functional.mse_loss(eps_pred, eps)
        weight = torch.as_tensor(mask, device=self.device).to(eps.dtype)[:, :, None]   # (B, H, 1)
        squared = (eps_pred - eps) ** 2 * weight                       # (B, H, dof), masked steps -> 0
        return squared.sum() / (weight.sum() * eps.shape[-1]).clamp(min=1.0)

    @torch.inference_mode()
    def reverse_process(self, a_k, k_start, obs_norm, z, use_ema=True):
        """Eq. (6) from per-row code level k_start (B,) down to the clean chunk. a_k (B, H, dof) normalized, row i
        at level k_start[i] (-1: already clean, returned unchanged); z (B, K, H, dof), z[:, k] the noise at level k."""
        features = self.encode(obs_norm, use_ema)                     # once for the K steps
        a = a_k.clone()
        top = int(k_start.max()) if len(k_start) else -1
        for k in range(top, -1, -1):
            active = k_start >= k                                      # the rows that have reached level k
            if bool(active.all()):                                     # every row (from pure noise): no gather
                eps = self.predict_eps(a, k, features, use_ema)
                a = p_sample(self.schedule, eps, a, k, noise=z[:, k])  # Eq. (6)
                continue
            rows = active.nonzero().squeeze(1)
            eps = self.predict_eps(a[rows], k, features[rows], use_ema)
            a[rows] = p_sample(self.schedule, eps, a[rows], k, noise=z[rows, k])   # Eq. (6)
        return a

    def draw_noise(self, B, generator=None):
        """All Gaussian draws of one reverse process, (B, K + 1, H, dof): [:, 0] the starting noise, [:, 1 + k]
        the z of the step at level k. One randn call per row: a batch samples as its rows one by one would."""
        shape = (B, self.cfg.K + 1, self.cfg.horizon, self.cfg.dof)
        gdev = generator.device if generator is not None else torch.device("cpu")
        rows = [torch.randn(shape[1:], generator=generator, device=gdev) for _ in range(B)]
        return torch.stack(rows).to(self.device) if rows else torch.empty(shape, device=self.device)

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


# ---- Chunk dataset (Sec. IV-C: a chunk is a label only if the expert drove all of its H steps) --------------------
def expert_runs(expert, H):
    """The paper's label rule, part 1 (Sec. IV-C): the maximal runs [start, end) of expert-driven steps that label
    chunks of H steps: at least H steps long, or the whole episode (a demonstration, padded at its end however
    short). A shorter intervention is discarded, also at the episode's end. Every other module's labels use this."""
    expert = np.asarray(expert, dtype=bool)
    T = len(expert)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], expert.astype(np.int8), [0]])))  # run starts, ends
    runs = [(int(s), int(e)) for s, e in zip(edges[::2], edges[1::2])]
    return [(s, e) for s, e in runs if e - s >= H or (s == 0 and e == T)]


def label_mask(expert, H):
    """The label rule, part 2: (T,) bool, True where the chunk starting at t is a label: t lies in a run of
    expert_runs and t + H <= its end, or the run ends the episode (the chunk is then padded with the last action)."""
    expert = np.asarray(expert, dtype=bool)
    T = len(expert)
    mask = np.zeros(T, dtype=bool)
    for start, end in expert_runs(expert, H):
        mask[start:(end if end == T else end - H + 1)] = True
    return mask


def chunk_dataset(episodes, H):
    """(obs (N, obs_dim) float32, chunks (N, H, dof) float32) over all valid label starts of all episodes.
    A chunk is action[t : t + H]; past the episode end it repeats the last action."""
    obs_list, chunk_list = [], []
    for ep in episodes:
        obs, action, expert = np.asarray(ep["obs"]), np.asarray(ep["action"]), np.asarray(ep["expert"])
        T = len(action)
        assert len(obs) == len(expert) == T and action.ndim == 2, "an episode's arrays share the length T"
        starts = np.nonzero(label_mask(expert, H))[0]                  # (n,)
        steps = starts[:, None] + np.arange(H)[None, :]                # (n, H)
        obs_list.append(obs[starts].astype(np.float32))
        chunk_list.append(action[np.minimum(steps, T - 1)].astype(np.float32))  # (n, H, dof), padded at the end
    return np.concatenate(obs_list), np.concatenate(chunk_list)


# ---- Training: AdamW on the DDPM loss, the co-training hook (Sec. IV-A steps 1, 4, 6) -----------------------------
def train(policy, obs, chunks, cfg, sampler=None, start=None, on_checkpoint=None, log=print):
    """Train (or fine-tune) `policy` in place on (obs (N, obs_dim), chunks (N, H, dof)) in joint units; the
    normalizer is fitted on them unless the policy has one (a loaded checkpoint keeps its own).
    - sampler(n, rng) -> (obs (n, obs_dim), chunks (n, H, dof)[, mask (n, H) bool]): co-training pairs for
      round(cfg.aug_fraction * batch_size) rows of every batch (Sec. IV-A step 4); a mask's False steps are not in
      the loss.
    - start: None (step 0, a fresh AdamW) or a state on_checkpoint handed over: from its 'step' and 'optimizer'
      along cfg's lr schedule (fine-tuning continues pi_0 so, benchmarks/SETUP.md §2), and with its 'numpy_rng' and
      'torch_rng' where it has them (a resumed run: its weights and the sampler's pool are the caller's to restore).
    - on_checkpoint(state): after every step of cfg.checkpoint_steps, {'step', 'optimizer', 'numpy_rng', 'torch_rng'}.
    """
    pc = policy.cfg
    obs = check_array("obs", obs, (None, pc.obs_dim))
    chunks = check_array("chunks", chunks, (None, pc.horizon, pc.dof))
    n_aug = int(round(cfg.aug_fraction * cfg.batch_size))            # augmented rows per batch
    n_base = cfg.batch_size - n_aug                                    # rows from (obs, chunks)
    assert len(obs) == len(chunks) > 0 and (sampler is not None or not n_aug), "obs and chunks pair; a sampler"
    if not bool(policy.normalizer_fitted):
        policy.fit_normalizer(obs, chunks)
    dev = policy.device
    with torch.no_grad():
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=dev)     # raw: the noise is in raw units
        chunks_n = policy.normalize_actions(torch.as_tensor(chunks, dtype=torch.float32, device=dev), obs_t)
    noise_std = torch.as_tensor(np.broadcast_to(np.asarray(cfg.obs_noise, dtype=np.float32), (pc.obs_dim,)).copy(),
                                device=dev)                            # (obs_dim,)
    noisy = bool((noise_std > 0).any())

    optimizer = make_optimizer(policy.net, cfg)
    rng = np.random.default_rng(cfg.seed)                              # batch indices, sampler
    gen = torch.Generator(device=dev).manual_seed(cfg.seed)            # diffusion steps, noise
    step = 0
    if start is not None:                                              # a checkpoint's state, going on
        step = int(start["step"])
        assert step < cfg.steps, f"start is at step {step}; TrainConfig.steps={cfg.steps} counts the total"
        optimizer.load_state_dict(start["optimizer"])
        if "numpy_rng" in start:                                       # resumed: the random streams too
            rng.bit_generator.state = start["numpy_rng"]
            gen.set_state(start["torch_rng"])

    policy.train()
    t0, losses, last_step = time.time(), [], step                      # progress lines: mean loss, rate, time left
    while step < cfg.steps:
        for group in optimizer.param_groups:
            group["lr"] = lr_at(step, cfg)                             # warmup + cosine
        idx = torch.as_tensor(rng.integers(0, len(obs_t), n_base), device=dev)
        o, a = obs_t[idx], chunks_n[idx]                               # raw (B, obs_dim), normalized (B, H, dof)
        mask = None                                                    # None: every step is in the loss
        if n_aug:                                                      # co-training (Sec. IV-A step 4)
            o, a, mask = _append_augmented(policy, sampler, n_aug, rng, o, a)
        with torch.no_grad():
            if noisy:   # Sec. V, benchmarks/SETUP.md §2: labels unchanged: the policy learns from a wrong reading
                o = o + noise_std * torch.randn(o.shape, generator=gen, device=dev)
            o = policy.normalize_obs(o)                                # (B, cond input)
        loss = policy.loss(o, a, generator=gen, mask=mask)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        update_ema(policy, step, cfg.ema_decay)                        # EMA copy for sampling
        step += 1
        losses.append(loss.item())
        if cfg.log_every and (step % cfg.log_every == 0 or step == cfg.steps or time.time() - t0 >= cfg.log_seconds):
            rate = (step - last_step) / max(time.time() - t0, 1e-9)
            log(f"step {step}/{cfg.steps} | loss {np.mean(losses):.4f} | {rate:.0f} steps/s | "
                f"{(cfg.steps - step) / max(rate, 1e-9):.0f} s left")
            t0, losses, last_step = time.time(), [], step
        if step in cfg.checkpoint_steps and on_checkpoint is not None:  # all a resumed run needs besides weights
            on_checkpoint({"step": step, "optimizer": optimizer.state_dict(), "numpy_rng": rng.bit_generator.state,
                           "torch_rng": gen.get_state()})
    policy.eval()
    return policy


def _append_augmented(policy, sampler, n_aug, rng, o, a):
    """train()'s co-training rows: n_aug pairs from the sampler appended to the base rows o (raw, (n_base, obs_dim))
    and a (normalized, (n_base, H, dof)) -> (o, a, mask (B, H) bool with the base rows True, or None: no mask)."""
    pc, dev = policy.cfg, policy.device
    drawn = sampler(n_aug, rng)
    m_aug = np.asarray(drawn[2]) if len(drawn) == 3 else None         # (n_aug, H) bool or None
    with torch.no_grad():
        o_aug = torch.as_tensor(np.asarray(drawn[0]), dtype=torch.float32, device=dev)   # (n_aug, obs_dim)
        a_aug = torch.as_tensor(np.asarray(drawn[1]), dtype=torch.float32, device=dev)   # (n_aug, H, dof)
        o, a = torch.cat([o, o_aug]), torch.cat([a, policy.normalize_actions(a_aug, o_aug)])
    if m_aug is None:
        return o, a, None
    base = torch.ones(len(o) - n_aug, pc.horizon, dtype=torch.bool, device=dev)   # base rows: every step
    return o, a, torch.cat([base, torch.as_tensor(m_aug, device=dev)])            # (B, H)


def make_optimizer(net, cfg):
    """train()'s AdamW (the authors' optimizer), fused: one kernel updates every parameter (faster on a CPU)."""
    return torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)


def lr_at(step, cfg):
    """The learning rate of optimizer step `step`: cfg.lr_schedule's (None: the authors' warmup_cosine)."""
    return (cfg.lr_schedule or warmup_cosine)(step, cfg)


def warmup_cosine(step, cfg):
    """Linear warmup to cfg.lr over warmup_steps, then cosine decay to 0 at cfg.schedule_steps (0: cfg.steps)."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    end = cfg.schedule_steps or cfg.steps
    progress = (step - cfg.warmup_steps) / max(1, end - cfg.warmup_steps)
    return cfg.lr * 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))



@torch.no_grad()
def update_ema(policy, step, decay):
    """policy.ema_net (the weights used for sampling) <- the EMA of policy.net after optimizer step `step`.
    The decay warms up as (1 + t) / (10 + t), so that a short run's EMA is not its random initial weights."""
    d = min(decay, (1.0 + step) / (10.0 + step))
    torch._foreach_lerp_(list(policy.ema_net.parameters()), list(policy.net.parameters()), 1.0 - d)


# ---- Demo: a toy task with two modes (go up-right or down-left); the policy must keep both ------------------------
def toy_two_mode_data(n, H=4, seed=0):
    """A 2-joint arm at rest at q ~ U[-1, 1]^2: obs = (q_t, q_{t-1}) = (q, q), (n, 4); chunk = q + t * v for
    t = 1..H (n, H, 2), v = +(0.5, 0.5) / H or -(0.5, 0.5) / H at random."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    sign = rng.choice([-1.0, 1.0], size=(n, 1, 1))
    steps = np.arange(1, H + 1, dtype=np.float32)[None, :, None] / H   # (1, H, 1)
    chunks = q[:, None, :] + sign * 0.5 * steps                        # (n, H, 2)
    return np.concatenate([q, q], axis=1), chunks.astype(np.float32)


if __name__ == "__main__":
    obs, chunks = toy_two_mode_data(4000, H=4)
    policy = DiffusionPolicy(PolicyConfig(obs_dim=4, dof=2, horizon=4, n_act=2, K=100, down_dims=(32, 64)))
    train(policy, obs, chunks, TrainConfig(steps=3000, warmup_steps=200, log_every=500))
    samples = policy.sample(np.zeros((200, 4), dtype=np.float32), generator=torch.Generator().manual_seed(0))
    last = samples[:, -1, :]                                           # (200, 2) end of each chunk
    up = last.sum(axis=1) > 0
    print(f"from the origin: {up.mean():.0%} of chunks end up-right, {1 - up.mean():.0%} down-left")
    print(f"mean end point of each mode: {last[up].mean(0).round(3)} and {last[~up].mean(0).round(3)} "
          "(data: [0.5 0.5] and [-0.5 -0.5])")
