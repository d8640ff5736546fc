"""Where one training step of a profile's policy spends its time, on a CPU or a GPU; and what sampling costs.

For `--profile NAME` (default `quick`: the residual MLP, K = 20, batch 256) this script times
  - diffusion.train itself at the profile's batch (and at 256, if that differs);
  - the same step taken apart (batch indexing, loss forward, backward, AdamW, EMA, the loss.item() that train's
    progress line reads), synchronized after each part on a GPU;
  - forward and backward in GFLOP/s: the FLOPs are those of the matrix products and convolutions (2 per
    multiply-add, counted by torch.utils.flop_counter.FlopCounterMode on one step; the elementwise work, norms and
    activations are not counted), against this core's matrix-product rate (a 256 x 256 x 256 product through
    torch's default path, and through oneDNN where torch has it);
  - DiffusionPolicy.sample at the evaluation's batch (eval_scenarios x eval_repeats chunks from pure noise, the
    largest call dagger.evaluate makes: all episodes in lockstep);
  - with --ops, torch.profiler's per-op table of diffusion.train.
On a CPU the working tree's policy is timed four times: with torch's own Linear and Mish, and with each CPU kernel
of experiment/cpu_kernels.py swapped in alone and both together (forced, whatever its MEASURED table says: this
script is how a row of that table is measured). With --baseline REV, diffusion.py of git revision REV is loaded beside them. Every
measurement alternates between the variants (--repeats rounds, medians): on a shared machine only ratios within
one run are trustworthy. Data are random (N = 20,000 rows of the env's shapes): only the cost is measured.

Usage:  python benchmarks/bench_train_step.py [--profile quick] [--threads 1] [--baseline 7e18ba9] [--ops]
        python benchmarks/bench_train_step.py --profile paper --device cuda --steps 1000
"""
import argparse
import importlib.util
import os
import subprocess
import sys
import time
from dataclasses import asdict

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import dagger      # noqa: E402
import diffusion   # noqa: E402
from experiment import cpu_kernels, environments, profiles  # noqa: E402

PARTS = ("index", "forward", "backward", "adamw", "ema", "item")
N_ROWS = 20_000    # random training rows: the quick profile's D0 is ~20k chunks


def sync(device):
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def diffusion_at(rev):
    """diffusion.py as it was at git revision `rev`, imported as a module of its own (the working tree's: None)."""
    if rev is None:
        return diffusion
    source = subprocess.run(["git", "-C", ROOT, "show", f"{rev}:diffusion.py"], check=True, capture_output=True,
                            text=True).stdout
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(f"diffusion_{rev}", loader=None))
    exec(compile(source, f"diffusion.py@{rev}", "exec"), module.__dict__)
    return module


class Variant:
    """What is timed: diffusion.py as `module` holds it, with these CPU kernels swapped in (names of
    cpu_kernels.KERNELS; none: torch's own)."""

    def __init__(self, module, kernels=()):
        self.module, self.kernels = module, kernels


def make_policy(variant, cfg, env):
    """dagger.make_policy's policy, built by the variant's module (the same config and seed for every variant)."""
    pc = dagger.make_policy(cfg, env).cfg
    module = variant.module
    policy = module.DiffusionPolicy(module.PolicyConfig(**asdict(pc)), device=cfg.device)
    cpu_kernels.swap_in(policy.net, variant.kernels)
    cpu_kernels.swap_in(policy.ema_net, variant.kernels)
    return policy


def train_config(module, cfg, policy, steps, batch):
    return module.TrainConfig(steps=steps, batch_size=batch, lr=cfg.lr, log_every=0,
                              obs_noise=dagger.observation_noise(policy.cfg))


def train_ms(variant, cfg, env, data, batch, steps, warm):
    """ms per step of the module's train over `steps` steps (a fresh optimizer from step 0), after a warm-up run."""
    module, policy = variant.module, make_policy(variant, cfg, env)
    module.train(policy, *data, train_config(module, cfg, policy, warm, batch))
    sync(cfg.device)
    t = time.perf_counter()
    module.train(policy, *data, train_config(module, cfg, policy, steps, batch))
    sync(cfg.device)
    return 1000 * (time.perf_counter() - t) / steps


def make_optimizer(module, policy, lr):
    """train()'s AdamW: module.make_optimizer where the module has one, else the foreach AdamW it built inline."""
    if hasattr(module, "make_optimizer"):
        return module.make_optimizer(policy.net, module.TrainConfig(lr=lr))
    return torch.optim.AdamW(policy.net.parameters(), lr=lr, weight_decay=1e-6, foreach=True)


def parts_ms(variant, cfg, env, data, steps, warm):
    """train()'s step at the profile's batch, rewritten here so that it can be taken apart (without the observation
    noise's one randn and add, and without co-training rows): the ms per step of each part, synchronized."""
    obs, chunks = data
    module, policy = variant.module, make_policy(variant, cfg, env)
    policy.fit_normalizer(obs, chunks)
    dev, rng = policy.device, np.random.default_rng(0)
    obs_t = torch.as_tensor(obs, device=dev)
    chunks_n = policy.normalize_actions(torch.as_tensor(chunks, device=dev), obs_t)
    opt = make_optimizer(module, policy, cfg.lr)
    gen = torch.Generator(device=dev).manual_seed(0)
    seconds = dict.fromkeys(PARTS, 0.0)
    policy.train()

    def mark(name, t):
        sync(cfg.device)
        now = time.perf_counter()
        seconds[name] += now - t
        return now

    for i in range(warm + steps):
        if i == warm:
            seconds = dict.fromkeys(PARTS, 0.0)
        t = time.perf_counter()
        idx = torch.as_tensor(rng.integers(0, len(obs), cfg.batch_size), device=dev)
        with torch.no_grad():
            o, a = policy.normalize_obs(obs_t[idx]), chunks_n[idx]
        t = mark("index", t)
        loss = policy.loss(o, a, generator=gen)
        t = mark("forward", t)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        t = mark("backward", t)
        opt.step()
        t = mark("adamw", t)
        module.update_ema(policy, i, 0.999)
        t = mark("ema", t)
        loss.item()
        mark("item", t)
    return {k: 1000 * v / steps for k, v in seconds.items()}


def sample_ms(variant, cfg, env, obs, batch, repeats):
    """ms per DiffusionPolicy.sample call at `batch` rows (the evaluation's lockstep batch), best of `repeats`."""
    policy = make_policy(variant, cfg, env)
    policy.fit_normalizer(obs, np.zeros((len(obs), cfg.horizon, env.dof), np.float32))
    gen = torch.Generator(device=policy.device).manual_seed(0)
    policy.sample(obs[:batch], generator=gen)                        # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        policy.sample(obs[:batch], generator=gen)
        times.append(time.perf_counter() - t)
    return 1000 * min(times)


def step_flops(cfg, env, data):
    """(forward, backward) FLOPs of one step at the profile's batch: matrix products and convolutions only."""
    policy = make_policy(Variant(diffusion), cfg, env)                 # torch's own products: FlopCounterMode counts them
    policy.fit_normalizer(*data)
    o = policy.normalize_obs(torch.as_tensor(data[0][:cfg.batch_size], device=policy.device))
    a = policy.normalize_actions(torch.as_tensor(data[1][:cfg.batch_size], device=policy.device),
                                 torch.as_tensor(data[0][:cfg.batch_size], device=policy.device))
    with FlopCounterMode(display=False) as forward:
        loss = policy.loss(o, a, generator=torch.Generator(device=policy.device).manual_seed(0))
    with FlopCounterMode(display=False) as backward:
        loss.backward()
    return forward.get_total_flops(), backward.get_total_flops()


def matmul_rates(n=256, repeats=200):
    """GFLOP/s of an (n, n) x (n, n) fp32 product on this thread: {path: rate} (torch's default; oneDNN)."""
    x, w = torch.randn(n, n), torch.randn(n, n)
    paths = {"torch.mm (MKL on x86)": lambda: torch.mm(x, w)}
    if hasattr(torch.ops, "mkldnn") and torch.backends.mkldnn.is_available():
        paths["oneDNN (torch.ops.mkldnn._linear_pointwise)"] = lambda: torch.ops.mkldnn._linear_pointwise(
            x, w, None, "none", [], "")
    rates = {}
    for name, fn in paths.items():
        try:
            for _ in range(10):
                fn()
            t = time.perf_counter()
            for _ in range(repeats):
                fn()
            rates[name] = 2 * n ** 3 * repeats / (time.perf_counter() - t) / 1e9
        except RuntimeError:                                         # a torch without that op
            pass
    return rates


def op_table(variant, cfg, env, data, steps, rows=25):
    """torch.profiler's table of the module's train over `steps` steps: the ops by their own CPU time."""
    from torch.profiler import ProfilerActivity, profile
    module, policy = variant.module, make_policy(variant, cfg, env)
    tc = train_config(module, cfg, policy, 50, cfg.batch_size)
    module.train(policy, *data, tc)
    tc.steps = steps
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        module.train(policy, *data, tc)
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)


def cpu_name():
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return "an unknown CPU"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--profile", default="quick", help=f"one of {', '.join(profiles.PROFILES)}")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (1: as dagger's worker processes train; experiment/workers.py)")
    parser.add_argument("--steps", type=int, default=300, help="timed steps per measurement")
    parser.add_argument("--warm", type=int, default=30, help="warm-up steps before each measurement")
    parser.add_argument("--repeats", type=int, default=3, help="rounds of every measurement (medians reported)")
    parser.add_argument("--baseline", default=None, help="a git revision whose diffusion.py to time alongside")
    parser.add_argument("--ops", action="store_true", help="also print torch.profiler's per-op table")
    args = parser.parse_args()
    if args.profile not in profiles.PROFILES:
        raise SystemExit(f"--profile must be one of {', '.join(profiles.PROFILES)}, got {args.profile!r}")
    if args.device not in ("cpu", "cuda") or (args.device == "cuda" and not torch.cuda.is_available()):
        raise SystemExit(f"--device must be cpu or cuda (cuda only where torch sees a GPU), got {args.device!r}")
    if min(args.steps, args.warm, args.repeats, args.threads) < 1:
        raise SystemExit("--steps, --warm, --repeats and --threads must be >= 1")
    torch.set_num_threads(args.threads)
    cfg = profiles.PROFILES[args.profile]
    cfg.device = args.device
    env = environments.make_env(cfg.env)
    rng = np.random.default_rng(0)
    data = (rng.normal(size=(N_ROWS, env.obs_dim)).astype(np.float32),
            rng.normal(size=(N_ROWS, cfg.horizon, env.dof)).astype(np.float32))
    eval_batch = cfg.eval_scenarios * cfg.eval_repeats
    where = (torch.cuda.get_device_name() if args.device == "cuda"
             else f"{cpu_name()}, torch CPU capability {torch.backends.cpu.get_cpu_capability()}")
    print(f"{args.profile} profile on {where}, {torch.get_num_threads()} thread(s), torch {torch.__version__}: "
          f"network {cfg.network} ({f'width {cfg.mlp_width}, {cfg.mlp_blocks} blocks' if cfg.network == 'mlp' else f'U-Net {cfg.down_dims}'}),"
          f" K {cfg.K}, batch {cfg.batch_size}, H {cfg.horizon}, obs_dim {env.obs_dim}, dof {env.dof}")

    variants = {"torch's own": Variant(diffusion)}
    if args.device == "cpu":
        variants.update({f"{k} kernel": Variant(diffusion, kernels=(k,)) for k in cpu_kernels.KERNELS})
        variants["both kernels"] = Variant(diffusion, kernels=cpu_kernels.KERNELS)
    if args.baseline:
        variants = {args.baseline: Variant(diffusion_at(args.baseline)), **variants}
    batches = sorted({cfg.batch_size, 256})
    results = {v: {"parts": [], "sample": [], **{f"train {b}": [] for b in batches}} for v in variants}
    for r in range(args.repeats):                                    # interleaved: each round times every variant
        for name, variant in variants.items():
            res = results[name]
            res["parts"].append(list(parts_ms(variant, cfg, env, data, args.steps, args.warm).values()))
            for b in batches:
                res[f"train {b}"].append(train_ms(variant, cfg, env, data, b, args.steps, args.warm))
            res["sample"].append(sample_ms(variant, cfg, env, data[0], eval_batch, 3))
        print(f"  round {r + 1}/{args.repeats} done", flush=True)

    forward_flops, backward_flops = step_flops(cfg, env, data)
    print(f"\nFLOPs per step at batch {cfg.batch_size} (matrix products only, FlopCounterMode): forward "
          f"{forward_flops / 1e9:.3f} G, backward {backward_flops / 1e9:.3f} G")
    if args.device == "cpu":
        rates = matmul_rates()
        print("this core's 256^3 fp32 matrix product: " + ", ".join(f"{k} {v:.0f} GFLOP/s" for k, v in rates.items()))
    print(f"\nmedians of {args.repeats} interleaved rounds, {args.steps} steps each (ms per step):")
    header = f"{'':>16}" + "".join(f"{p:>9}" for p in PARTS + ("sum",)) + "".join(
        f"{'train ' + str(b):>11}" for b in batches) + f"{'sample ' + str(eval_batch):>12}" + "  fwd GF/s  bwd GF/s"
    print(header)
    medians = {}
    for name in variants:
        res = results[name]
        parts = np.median(np.array(res["parts"]), axis=0)
        row = dict(zip(PARTS, parts), sum=parts.sum(), **{f"train {b}": np.median(res[f"train {b}"]) for b in batches},
                   sample=np.median(res["sample"]))
        medians[name] = row
        print(f"{name[:16]:>16}" + "".join(f"{row[p]:9.2f}" for p in PARTS + ("sum",))
              + "".join(f"{row[f'train {b}']:11.2f}" for b in batches) + f"{row['sample']:12.1f}"
              + f"{forward_flops / row['forward'] / 1e6:10.0f}{backward_flops / row['backward'] / 1e6:10.0f}")
    kernel_rows = [name for name, variant in variants.items() if variant.kernels]
    pairs = [(old, new) for old in (args.baseline, "torch's own") if old for new in kernel_rows]
    for old, new in pairs + ([(args.baseline, "torch's own")] if args.baseline else []):
        short = {"torch's own": "own", "linear kernel": "linear", "mish kernel": "mish", "both kernels": "both"}
        print(f"{short.get(old, old) + '/' + short[new]:>16}"
              + "".join(f"{medians[old][p] / medians[new][p]:9.2f}" for p in PARTS + ("sum",))
              + "".join(f"{medians[old][f'train {b}'] / medians[new][f'train {b}']:11.2f}" for b in batches)
              + f"{medians[old]['sample'] / medians[new]['sample']:12.2f}")
    if args.ops:
        print(f"\ntorch.profiler, diffusion.train of the working tree as the run has it, 100 steps at batch {cfg.batch_size}:")
        run_kernels = cpu_kernels.kernels_wanted("training") if args.device == "cpu" else ()
        print(op_table(Variant(diffusion, kernels=run_kernels),
                       cfg, env, data, 100))


if __name__ == "__main__":
    main()
