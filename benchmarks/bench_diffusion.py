"""Cost of the diffusion policy's epsilon network on a CPU: training step, one decision (full reverse process), size.

The paper's network (Chi et al.'s 1-D conv U-Net; the authors' down_dims (128, 256, 512)) is the expensive
part of this project: BC and every method's fine-tuning train it, and every decision of every evaluation
episode runs all K = 100 reverse steps. This script measures, per U-Net width (PolicyConfig.down_dims):
  - one training step of diffusion.train at batch 64 and 256 (loss, backward, AdamW, EMA);
  - sampling 300 chunks (300 parallel episodes, one decision) with all K reverse steps;
  - the number of weights (one copy; the EMA copy doubles it in memory);
and the same for the residual MLP (PolicyConfig.network='mlp', the CPU profiles' network) per --mlp width x
blocks, whose row shows how many training samples per CPU second each network buys.
Defaults: the planar task's observation (obs_dim 14), dof 3, H = 20 (10 Hz, 2 s chunks) and H = 16.

Usage:  python benchmarks/bench_diffusion.py [--seconds 3] [--horizons 20 16] [--threads 1]
                                            [--down-dims 32,64,128 64,128,256 128,256,512] [--full-sample] [--K 100]
        python benchmarks/bench_diffusion.py --horizons 20 --mlp 256x3 --down-dims 32,64,128 --full-sample
            (the quick and mid profiles' MLP beside the U-Net they replace)
        python benchmarks/bench_diffusion.py --film both --horizons 20 --down-dims 64,128,256 --full-sample
            (the run's FiLM table, experiment/cpu_kernels.py, beside the plain network it computes)
        python benchmarks/bench_diffusion.py --image-size 32 --dof 6 --down-dims 64,128,256
            (also a policy whose observation ends with a 3 x 32 x 32 image, encoded by the CNN of the image
             variant, experiment/image_obs.py: its ImageEncoder)
Times are CPU seconds of this process (time.process_time): with one torch thread that is the cost itself,
also on a machine whose cores are shared; the last column, wall / CPU, shows how loaded the machine was.
Every reverse step costs the same, so by default the sampling column is measured on a few reverse steps
(reverse_process from a lower level) and scaled to K steps; --full-sample times whole policy.sample calls.
"""
import argparse
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from experiment.image_obs import ImageEncoder  # noqa: E402 (the image variant's encoder)
from diffusion import DiffusionPolicy, PolicyConfig, TrainConfig, train  # noqa: E402
from experiment import cpu_kernels  # noqa: E402


def cost(fn):
    """(CPU seconds, wall seconds) of one call of fn."""
    c0, w0 = time.process_time(), time.perf_counter()
    fn()
    return time.process_time() - c0, time.perf_counter() - w0


def per_unit(fn, min_seconds, max_n=None):
    """fn(n) does n units of work after a fixed setup. Returns (CPU, wall) seconds per unit: the difference
    between n units and one unit over n - 1, with n grown until n units take min_seconds of CPU (at most max_n)."""
    fn(1)                                                        # warm-up (allocator, oneDNN kernels)
    one = cost(lambda: fn(1))
    n = max(2, int(min_seconds / max(one[0], 1e-4)) + 1)
    n = min(n, max_n) if max_n else n
    many = cost(lambda: fn(n))
    return tuple(max(m - o, 1e-9) / (n - 1) for m, o in zip(many, one))


def measure(cfg, args, film):
    """One table row: the costs of the policy built from cfg."""
    rng = np.random.default_rng(0)
    n_labels = 5_000
    obs = rng.uniform(-1, 1, (n_labels, cfg.obs_dim)).astype(np.float32)
    obs[:, cfg.low_dim:] = rng.uniform(0, 1, (n_labels, cfg.obs_dim - cfg.low_dim))   # an encoder's pixels: [0, 1]
    chunks = rng.uniform(-1, 1, (n_labels, cfg.horizon, cfg.dof)).astype(np.float32)
    encoder = ImageEncoder if cfg.obs_encoder == "ImageEncoder" else None             # the env hands its class over
    policy = cpu_kernels.use_kernels(DiffusionPolicy(cfg, obs_encoder=encoder))        # as the run has it on this CPU
    if film == "plain":                                                # eps_theta as diffusion.py writes it
        for net in (policy.net, policy.ema_net):
            net.__class__ = next(c for c in type(net).__mro__ if c in cpu_kernels.TABLED)
    policy.fit_normalizer(obs, chunks)
    row = {"parameters": sum(p.numel() for p in policy.net.parameters())}
    for batch in (64, 256):
        def train_steps(n, batch=batch):
            train(policy, obs, chunks, TrainConfig(steps=n, batch_size=batch, warmup_steps=1, log_every=0))
        row[f"train {batch}"] = per_unit(train_steps, args.seconds)

    test_obs = torch.as_tensor(obs[:args.episodes])
    gen = torch.Generator().manual_seed(0)
    if args.full_sample:
        policy.sample(test_obs.numpy(), generator=gen)
        row["sample"] = cost(lambda: policy.sample(test_obs.numpy(), generator=gen))
    else:
        with torch.inference_mode():
            obs_norm = policy.normalize_obs(test_obs)
            noise = policy.draw_noise(args.episodes, gen)             # (B, K + 1, H, dof)

            def reverse_steps(n):                                      # n reverse steps: levels n - 1 .. 0
                k_start = torch.full((args.episodes,), n - 1)
                policy.reverse_process(noise[:, 0], k_start, obs_norm, noise[:, 1:])
            step = per_unit(reverse_steps, args.seconds, max_n=cfg.K)   # at most K levels
            first = cost(lambda: reverse_steps(1))                    # the FiLM terms and one step
            draw = cost(lambda: policy.draw_noise(args.episodes, gen))
        row["sample"] = tuple(d + f + (cfg.K - 1) * s for d, f, s in zip(draw, first, step))
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="CPU seconds per measurement (about)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--down-dims", nargs="+", default=["32,64,128", "64,128,256", "128,256,512"],
                        help="U-Net widths to measure, comma-separated per U-Net")
    parser.add_argument("--mlp", nargs="*", default=["256x3"],
                        help="residual-MLP networks to measure, WIDTHxBLOCKS each (none: --mlp with no value)")
    parser.add_argument("--horizons", type=int, nargs="+", default=[20, 16], help="chunk lengths H")
    parser.add_argument("--obs-dim", type=int, default=14, help="observation length (planar env: 14)")
    parser.add_argument("--dof", type=int, default=3)
    parser.add_argument("--K", type=int, default=100, help="diffusion steps (the authors': 100)")
    parser.add_argument("--episodes", type=int, default=300, help="parallel episodes per decision")
    parser.add_argument("--full-sample", action="store_true", help="time whole policy.sample calls")
    parser.add_argument("--film", choices=("table", "plain", "both"), default="table",
                        help="eps_theta through the FiLM table (the run's), as diffusion.py writes it, or both rows")
    parser.add_argument("--image-size", type=int, default=0,
                        help="measure policies whose observation ends with a 3 x S x S image instead")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    print(f"torch threads: {args.threads}, K = {args.K}, dof = {args.dof}, "
          f"{args.episodes} chunks per decision; CPU ms (wall / CPU)")
    print("| network | FiLM | H | obs | parameters | train step, batch 64 | train step, batch 256 | "
          f"samples / CPU s at 256 | sample {args.episodes} chunks, K = {args.K} | wall / CPU |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    networks = [("unet", {"down_dims": tuple(int(d) for d in dims.split(","))}) for dims in args.down_dims]
    networks += [("mlp", {"mlp_width": int(spec.split("x")[0]), "mlp_blocks": int(spec.split("x")[1])})
                 for spec in args.mlp]
    for horizon in args.horizons:
        for network, shape in networks:
            if args.image_size:
                S = args.image_size
                cfg = PolicyConfig(obs_dim=2 * args.dof + 3 + 3 * S * S, dof=args.dof, horizon=horizon,
                                   n_act=horizon // 2, K=args.K, network=network, obs_encoder="ImageEncoder",
                                   obs_encoder_args={"shape": (3, S, S)}, obs_encoder_sizes=(3 * S * S, 64), **shape)
                obs_name = f"image {S}x{S}"
            else:
                cfg = PolicyConfig(obs_dim=args.obs_dim, dof=args.dof, horizon=horizon, n_act=horizon // 2,
                                   K=args.K, network=network, **shape)
                obs_name = f"{args.obs_dim} numbers"
            name = (f"U-Net {cfg.down_dims}" if network == "unet"
                    else f"MLP {cfg.mlp_width} x {cfg.mlp_blocks} blocks")
            for film in (("table", "plain") if args.film == "both" else (args.film,)):
                row = measure(cfg, args, film)
                cpu = [row[key][0] for key in ("train 64", "train 256", "sample")]
                wall = [row[key][1] for key in ("train 64", "train 256", "sample")]
                print(f"| {name} | {film} | {horizon} | {obs_name} | {row['parameters'] / 1e6:.2f} M | "
                      f"{cpu[0] * 1e3:.0f} ms | {cpu[1] * 1e3:.0f} ms | {256 / cpu[1]:,.0f} | {cpu[2]:.1f} s | "
                      f"{sum(wall) / sum(cpu):.2f} |", flush=True)


if __name__ == "__main__":
    main()
