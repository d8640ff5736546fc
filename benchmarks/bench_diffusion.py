"""Speed of the diffusion policy at the default size: training steps/s, sampling, partial denoising, memory.

Issue 4 targets: BC on ~500 planar demonstrations (~50k chunk labels, obs_dim 48, dof 3, H 16) reaches its
plateau in a few minutes of a 2-core CPU; one decision for 300 parallel episodes (the full K = 100 step
reverse process) takes well under a second.

Usage:  python benchmarks/bench_diffusion.py [--threads 1 2] [--seconds 5] [--width 256 --n-blocks 3]
        python benchmarks/bench_diffusion.py --threads 1 --dof 6 --obs-dim 127 --image-size 32
            (the UR5 policy twice: on the obstacle list, and on 32 x 32 camera images through the CNN)
Prints a markdown table per torch thread count. Wall-clock rates depend on what else runs on the machine;
the CPU-seconds column (time.process_time of this process) is the cost itself.
"""
import argparse
import os
import resource
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from diffusion import DiffusionPolicy, PolicyConfig, TrainConfig, train  # noqa: E402
from partial_denoise import partial_denoise  # noqa: E402


def timed(fn, min_seconds):
    """Run fn until min_seconds of wall time have passed (at least twice, after one warm-up call).
    Returns (wall seconds per call, CPU seconds per call)."""
    fn()
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while n < 2 or time.perf_counter() - t0 < min_seconds:
        fn()
        n += 1
    return (time.perf_counter() - t0) / n, (time.process_time() - c0) / n


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch thread counts to measure")
    parser.add_argument("--seconds", type=float, default=5.0, help="minimum wall time per measurement")
    parser.add_argument("--obs-dim", type=int, default=48, help="observation length (planar env: 48)")
    parser.add_argument("--dof", type=int, default=3)
    parser.add_argument("--width", type=int, default=PolicyConfig.width)
    parser.add_argument("--n-blocks", type=int, default=PolicyConfig.n_blocks)
    parser.add_argument("--batch", type=int, default=256, help="training batch size")
    parser.add_argument("--episodes", type=int, default=300, help="parallel episodes per decision")
    parser.add_argument("--image-size", type=int, default=0,
                        help="also measure a policy whose observation ends with a 3 x S x S image (CNN encoder); "
                             "EngineReach3D's image layout replaces the 112 obstacle numbers with the image")
    args = parser.parse_args()

    policies = {"low-dim": PolicyConfig(obs_dim=args.obs_dim, dof=args.dof, width=args.width, n_blocks=args.n_blocks)}
    if args.image_size:
        S = args.image_size
        policies[f"image {S}x{S}"] = PolicyConfig(obs_dim=2 * args.dof + 3 + 3 * S * S, dof=args.dof,
                                                 width=args.width, n_blocks=args.n_blocks, image_shape=(3, S, S))
    print("| policy | torch threads | measurement | wall time | CPU time | rate (wall) |")
    print("|---|---|---|---|---|---|")
    for name, cfg in policies.items():
        measure(name, cfg, args)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024     # Linux: kilobytes
    print(f"\npeak memory (ru_maxrss): {peak:.0f} MB")
    print("Note: on a machine whose cores are busy with other jobs, torch's OpenMP threads spin-wait for each\n"
          "other; with more than one thread run under OMP_WAIT_POLICY=PASSIVE (or use one thread).")


def measure(name, cfg, args):
    rng = np.random.default_rng(0)
    n_labels = 50_000 if not cfg.image_shape else 10_000      # ~500 planar demonstrations; images are big
    obs = rng.uniform(-1, 1, (n_labels, cfg.obs_dim)).astype(np.float32)
    obs[:, cfg.low_dim:] = rng.uniform(0, 1, (n_labels, cfg.image_dim))   # pixels in [0, 1]
    chunks = rng.uniform(-1, 1, (n_labels, cfg.horizon, cfg.dof)).astype(np.float32)
    policy = DiffusionPolicy(cfg)
    policy.fit_normalizer(obs, chunks)
    n_params = sum(p.numel() for p in policy.net.parameters())
    print(f"| {name} | | residual MLP width {cfg.width}, {cfg.n_blocks} blocks, {n_params / 1e6:.2f} M parameters, "
          f"K = {cfg.K}, H = {cfg.horizon}, dof = {cfg.dof}, obs_dim = {cfg.obs_dim} | | | |")
    test_obs = obs[:args.episodes]
    expert = chunks[:args.episodes]
    for threads in args.threads:
        torch.set_num_threads(threads)
        steps = 50
        tc = TrainConfig(steps=steps, batch_size=args.batch, warmup_steps=10, log_every=0)
        wall, cpu = timed(lambda: train(policy, obs, chunks, tc), args.seconds)
        print(f"| {name} | {threads} | train step, batch {args.batch} | {wall / steps * 1e3:.1f} ms | "
              f"{cpu / steps * 1e3:.1f} ms | {steps / wall:.0f} steps/s |")
        gen = torch.Generator().manual_seed(0)
        wall, cpu = timed(lambda: policy.sample(test_obs, generator=gen), args.seconds)
        print(f"| {name} | {threads} | sample {args.episodes} chunks, K = {cfg.K} steps (one decision) | "
              f"{wall * 1e3:.0f} ms | {cpu * 1e3:.0f} ms | {args.episodes / wall:.0f} chunks/s |")
        wall, cpu = timed(lambda: partial_denoise(policy, test_obs, expert, 0.5, generator=gen), args.seconds)
        print(f"| {name} | {threads} | partial_denoise {args.episodes} chunks, beta = 0.5 | "
              f"{wall * 1e3:.0f} ms | {cpu * 1e3:.0f} ms | {args.episodes / wall:.0f} chunks/s |")


if __name__ == "__main__":
    main()
