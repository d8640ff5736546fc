"""A research variant: the UR5's policy sees a camera image instead of the obstacle list (the paper's policy sees
images, Sec. V). Run it with `python dagger.py --env engine3d_image` (any profile).

It brings its own functions, which the harness hands to the loop (experiment/environments.py):
    EngineReach3DImage  EngineReach3D with the camera image at the end of the observation, where the obstacle
                        slots were: the env factory's 'engine3d_image'
    ImageEncoder        the small CNN the policy reads that image with: the env names it (env.obs_encoder,
                        env.obs_encoder_args), dagger.make_policy hands it to the policy, and the harness's
                        checkpoint loader rebuilds it from the name the policy's config records. Noised
states reuse the recorded image of the state they were drawn around (EngineReach3DImage.make_obs_near, the
paper's approximation), and the run draws a figure of what the policy sees (fig5_policy_view.png). No function
of the core knows about images.

The observation stays one flat float32 vector, obs_dim = 15 + 3 S^2 (3,087 at S = 32):
    [0:15]    q, q_prev, goal     as EngineReach3D's
    [15:]     image               render_image(q): RGB (S, S, 3) from the fixed camera engine3d.ENGINE_CAMERA(_AUTHORS)
                                  with pybullet's TinyRenderer, stored channel-first (3, S, S), flattened, in [0, 1]
so every consumer (datasets, rollouts, the augmentation) handles it unchanged. The clutter is then seen only in
the image; the lever's position stays given as coordinates.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn

from experiment import engine3d


@dataclass
class EngineImageConfig(engine3d.EngineConfig):
    # pixels of the square camera image. Observations are float32 vectors kept for every step of every episode:
    # 32 x 32 x 3 is 12 kB a step (64 x 64: 48 kB)
    image_size: int = 32


class EngineReach3DImage(engine3d.EngineReach3D):
    """EngineReach3D whose observation ends with the camera image instead of the obstacle slots (module
    docstring); reset and step also put the image in info['image']."""


    def __init__(self, config: EngineImageConfig | None = None):
        cfg = config or EngineImageConfig()
        if not isinstance(cfg.image_size, (int, np.integer)) or cfg.image_size < 8:
            raise ValueError(f"EngineImageConfig.image_size must be an int >= 8 pixels, got {cfg.image_size!r}")
        super().__init__(cfg)
        size = int(cfg.image_size)
        self.image_shape = (3, size, size)  # channel-first, as in the observation
        self.obs_dim = 2 * self.dof + self.dim + 3 * size * size
        self.obs_encoder, self.obs_encoder_args = ImageEncoder, {"shape": self.image_shape}  # how a policy reads it

    def reset(self, seed=None):
        obs, info = super().reset(seed)
        info["image"] = self.obs_image(obs)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        info["image"] = self.obs_image(obs)
        return obs, reward, terminated, truncated, info

    def make_obs(self, q, q_prev):
        """Observations (B, obs_dim) float32, the camera image rendered with the arm at each q; (dof,) -> (obs_dim,)."""
        obs, q, single = self._joint_goal_obs(q, q_prev)
        low = 2 * self.dof + self.dim
        for i in range(len(q)):
            obs[i, low:] = self.render_image(q[i]).transpose(2, 0, 1).reshape(-1) / np.float32(255)
        return obs[0] if single else obs

    def make_obs_near(self, q, q_prev, recorded):
        """Observations of noised states (q, q_prev) with the image of the recorded state they were drawn around,
        not a new render (the paper's approximation, Sec. V): recorded (B, obs_dim), or one row (obs_dim,) or
        (1, obs_dim) for all, observations of this env."""
        obs, q, single = self._joint_goal_obs(q, q_prev)
        recorded = np.asarray(recorded, dtype=np.float32)
        if recorded.shape not in ((self.obs_dim,), (1, self.obs_dim), (len(q), self.obs_dim)):
            raise ValueError(f"make_obs_near: recorded must have shape ({self.obs_dim},), (1, {self.obs_dim}) or "
                             f"({len(q)}, {self.obs_dim}) (observations of this env), got {recorded.shape}")
        low = 2 * self.dof + self.dim
        obs[:, low:] = recorded[..., low:]
        return obs[0] if single else obs

    def render_image(self, q=None, size=None):
        """The image observation: RGB (size, size, 3) uint8 with the arm at q (default: current); size defaults
        to cfg.image_size. See EngineReach3D.camera_image."""
        size = int(size or self.cfg.image_size)
        if size < 8:
            raise ValueError(f"render_image: size must be >= 8 pixels, got {size}")
        return self.camera_image(q, size, size)

    def obs_image(self, obs):
        """The camera image in observations: (..., obs_dim) -> (..., S, S, 3) uint8."""
        obs = np.asarray(obs)
        if obs.shape[-1] != self.obs_dim:
            raise ValueError(f"obs_image: observations must end in obs_dim={self.obs_dim}, got {obs.shape}")
        pixels = obs[..., 2 * self.dof + self.dim:].reshape(*obs.shape[:-1], *self.image_shape)
        return np.round(np.moveaxis(pixels, -3, -1) * 255).astype(np.uint8)

    def plot_policy_view(self, episode, path, n_frames=4):
        """What the policy sees: the camera image inside the observations of one demonstration, at a few steps
        from start to goal, beside the same camera at full resolution. Returns True (written)."""
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        steps = np.linspace(0, len(episode["obs"]) - 1, n_frames).round().astype(int)
        fig, axes = plt.subplots(1, n_frames + 1, figsize=(2.6 * (n_frames + 1), 2.8))
        axes[0].imshow(self.camera_image(episode["q"][0], 320, 320))
        axes[0].set_title("camera, 320 x 320")
        size = self.image_shape[1]
        for ax, t in zip(axes[1:], steps):
            ax.imshow(self.obs_image(episode["obs"][t]), interpolation="nearest")
            ax.set_title(f"policy input, step {t}\n{size} x {size}")
        for ax in axes:
            ax.axis("off")
        fig.savefig(path, dpi=110, bbox_inches="tight")
        plt.close(fig)
        return True


class ImageEncoder(nn.Module):
    """The image variant's observation encoder: the observation's last C*H*W entries are a channel-first image in
    [0, 1]; a small CNN replaces them by `features` numbers beside the low-dimensional observation features.

    Three stride-2 convolutions (16, 32, 32 channels; a 32 x 32 image becomes 4 x 4), flattened, one linear
    layer. The paper does not specify its image encoder; this one is ours, small on purpose: it trains with the
    rest of the policy on a CPU (benchmarks/bench_diffusion.py --image-size).
    """

    @staticmethod
    def sizes(shape, features=64):
        """(entries at the observation's end this encoder owns: C*H*W pixels, features it gives for them);
        ValueError on a bad shape or feature count."""
        if (not isinstance(shape, (tuple, list)) or len(shape) != 3 or min(shape) < 1 or min(shape[1:]) < 8
                or not all(isinstance(n, (int, np.integer)) for n in shape)):
            raise ValueError(f"ImageEncoder: shape must be (channels, height, width) with height and width >= 8 "
                             f"(three stride-2 convolutions), got {shape!r}")
        if not isinstance(features, (int, np.integer)) or features < 1:
            raise ValueError(f"ImageEncoder: features must be a positive int, got {features!r}")
        return int(np.prod(shape)), int(features)

    def __init__(self, shape, features=64):
        super().__init__()
        self.n_pixels, _ = self.sizes(shape, features)
        self.shape = tuple(int(n) for n in shape)
        channels, height, width = self.shape
        self.conv = nn.Sequential(nn.Conv2d(channels, 16, 5, stride=2, padding=2), nn.SiLU(),
                                  nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.SiLU(),
                                  nn.Conv2d(32, 32, 3, stride=2, padding=1), nn.SiLU())
        for _ in range(3):  # each convolution above maps a side n to ceil(n / 2)
            height, width = (height + 1) // 2, (width + 1) // 2
        self.fc = nn.Linear(32 * height * width, features)

    def forward(self, obs_norm):
        """normalize_obs's output (B, low-dim features + C*H*W pixels in [0, 1]) -> (B, low-dim features + features)."""
        low = obs_norm.shape[1] - self.n_pixels
        image = ((obs_norm[:, low:] - 0.5) / 0.5).reshape(-1, *self.shape)   # (B, C, H, W) in [-1, 1]
        code = nn.functional.silu(self.fc(self.conv(image).flatten(1)))      # (B, features)
        return torch.cat([obs_norm[:, :low], code], dim=1)

