"""Where one training step of the `paper` profile's policy spends its time, on a CPU or a GPU.

The `paper` profile (the authors' U-Net (128, 256, 512), K = 100, batch 32) is meant for a GPU; on one H100 it
trains at ~40 steps/s, which projects one lineage to hours. This script says why: it times
  - diffusion.train itself at batch 32 and 256 (if the rate barely drops with 8x the rows, the step is bound by
    launching its kernels, not by arithmetic);
  - the same step taken apart (batch indexing, loss forward, backward, AdamW, EMA, the loss.item() that train's
    progress line reads), with the device synchronized after each part;
  - the step as train() takes it, and without its per-step loss.item() (a sync that a GPU could overlap).
Data are random (N = 20,000 rows of the planar env's shapes): only the cost is measured.

Usage:  python benchmarks/bench_train_step.py --device cuda [--steps 1000]
        python benchmarks/bench_train_step.py --device cpu --steps 20     (slow: ~65 M weights at batch 32)
"""
import argparse
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import dagger      # noqa: E402
import diffusion   # noqa: E402

PARTS = ("index", "forward", "backward", "adamw", "ema", "item")


def sync(device):
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def train_rate(cfg, env, obs, chunks, batch, steps, warm):
    """Steps/s of diffusion.train over warm + steps steps, after a separate warm-up run of `warm` steps."""
    policy = dagger.make_policy(cfg, env)
    tc = diffusion.TrainConfig(steps=warm, batch_size=batch, lr=cfg.lr, log_every=0,
                               obs_noise=dagger.observation_noise(policy.cfg))
    diffusion.train(policy, obs, chunks, tc)
    tc.steps = warm + steps                    # a fresh optimizer from step 0: the same work per step
    sync(cfg.device)
    t = time.perf_counter()
    diffusion.train(policy, obs, chunks, tc)
    sync(cfg.device)
    return tc.steps / (time.perf_counter() - t)


def replica(cfg, env, obs, chunks, steps, warm):
    """train()'s step at the profile's batch, rewritten here so that it can be taken apart (without the
    observation noise's one randn and add, and without co-training rows): {label: steps/s} and the ms per step of
    each part (synchronized)."""
    policy = dagger.make_policy(cfg, env)
    policy.fit_normalizer(obs, chunks)
    dev, rng = policy.device, np.random.default_rng(0)
    obs_t = torch.as_tensor(obs, device=dev)
    chunks_n = policy.normalize_actions(torch.as_tensor(chunks, device=dev), obs_t)
    opt = torch.optim.AdamW(policy.net.parameters(), lr=cfg.lr, weight_decay=1e-6, foreach=True)
    gen = torch.Generator(device=dev).manual_seed(0)
    seconds = dict.fromkeys(PARTS, 0.0)

    def step(i, split, read_loss):
        def mark(name, t):
            if split:
                sync(cfg.device)
                seconds[name] += time.perf_counter() - t
            return time.perf_counter()
        t = time.perf_counter()
        idx = torch.as_tensor(rng.integers(0, len(obs), cfg.batch_size), device=dev)
        o, a = policy.normalize_obs(obs_t[idx]), chunks_n[idx]
        t = mark("index", t)
        loss = policy.loss(o, a, generator=gen)
        t = mark("forward", t)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        t = mark("backward", t)
        opt.step()
        t = mark("adamw", t)
        diffusion.update_ema(policy, i, 0.999)
        t = mark("ema", t)
        if read_loss:
            loss.item()
        mark("item", t)

    for i in range(warm):
        step(i, False, True)
    rates = {}
    for split, read_loss, label in ((True, True, "taken apart (synchronized after each part)"),
                                    (False, True, "as train() takes it (loss.item() every step)"),
                                    (False, False, "without the per-step loss.item()")):
        sync(cfg.device)
        t = time.perf_counter()
        for i in range(steps):
            step(i, split, read_loss)
        sync(cfg.device)
        rates[label] = steps / (time.perf_counter() - t)
    return rates, {k: 1000 * v / steps for k, v in seconds.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="cpu or cuda")
    parser.add_argument("--steps", type=int, default=1000, help="timed steps per measurement")
    parser.add_argument("--warm", type=int, default=200, help="warm-up steps before each measurement")
    args = parser.parse_args()
    if args.device not in ("cpu", "cuda") or (args.device == "cuda" and not torch.cuda.is_available()):
        raise SystemExit(f"--device must be cpu or cuda (cuda only where torch sees a GPU), got {args.device!r}")
    if args.steps < 1 or args.warm < 1:
        raise SystemExit(f"--steps and --warm must be >= 1, got {args.steps} and {args.warm}")
    cfg = dagger.PROFILES["paper"]
    cfg.device = args.device
    env = dagger.make_run_env(cfg)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(20_000, env.obs_dim)).astype(np.float32)
    chunks = rng.normal(size=(20_000, cfg.horizon, env.dof)).astype(np.float32)
    name = torch.cuda.get_device_name() if args.device == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    print(f"paper profile on {name} (torch {torch.__version__}): U-Net {cfg.down_dims}, K {cfg.K}, "
          f"batch {cfg.batch_size}, H {cfg.horizon}, obs_dim {env.obs_dim}, dof {env.dof}")
    for batch in (cfg.batch_size, 256):
        print(f"diffusion.train at batch {batch}: {train_rate(cfg, env, obs, chunks, batch, args.steps, args.warm):.1f}"
              " steps/s")
    rates, ms = replica(cfg, env, obs, chunks, args.steps, args.warm)
    for label, rate in rates.items():
        print(f"the step at batch {cfg.batch_size}, {label}: {rate:.1f} steps/s")
    print("ms per step by part: " + ", ".join(f"{k} {v:.2f}" for k, v in ms.items())
          + f" (sum {sum(ms.values()):.1f})")


if __name__ == "__main__":
    main()
