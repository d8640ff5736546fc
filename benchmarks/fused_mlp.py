"""Issue 61's fused residual block, measured: does one autograd node with a hand-written backward for the whole
residual MLP make the quick profile's training step cheaper on this CPU?

diffusion.ResidualMLP's forward is ~40 torch ops and as many autograd nodes a step. FusedResidualMLP below computes
the same forward (the same ops, in the same order: LayerNorm, the closed-form Mish of experiment/cpu_kernels.py,
the products, FiLM's scale * h + bias, the residual sums) inside one torch.autograd.Function and writes its backward
out by hand: the products' gradients, the Mish derivative t + x (1 - t^2) sigmoid(x) from the saved exp(x) and t,
torch's own LayerNorm backward, the residual stream's sum. So autograd records one node where it recorded ~40, and
the backward allocates what it writes and nothing it would not.

The script
  1. checks the fused network against diffusion.py's: output and every gradient (parameters and the FiLM vector)
     on random weights, max |difference| and whether they are equal to the bit;
  2. times diffusion.train with the policy's network as it is (torch's ops, with MEASURED's CPU kernels of this
     CPU kind, the run's step) and with its forward swapped for the fused one, the same policy seed and random
     data, alternating --repeats rounds of --steps steps (medians): a ratio measured in one sitting.
`--inplace` writes the fused Mish and its derivative with in-place ops (fewer tensors allocated, the same values).
`--film-bound` times a third policy whose FiLM vector is a constant (no step table, no observation terms, no
gather, no FiLM gradient): not the method, a bound on what any rewrite of the FiLM path could save.

Usage:  taskset -c 0 python benchmarks/fused_mlp.py [--repeats 3] [--steps 200] [--inplace]
"""
import argparse
import copy
import os
import statistics
import sys
import time
import types

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import dagger      # noqa: E402
import diffusion   # noqa: E402
from experiment import cpu_kernels  # noqa: E402

INPLACE = False    # --inplace


def mish_forward(x):
    """mish(x) = x t, t = tanh(softplus(x)) = n / (n + 2), n = e (e + 2), e = exp(x): (value, saved for backward)."""
    if INPLACE:
        e = x.clamp(max=20.0).exp_()
        n = (e + 2.0).mul_(e)
        t = n.div_(n + 2.0)
    else:
        e = torch.exp(x.clamp(max=20.0))
        n = e * (e + 2.0)
        t = n / (n + 2.0)
    return x * t, (x, e, t)


def mish_backward(grad, saved):
    """grad * d mish / dx = grad * (t + x (1 - t^2) sigmoid(x)), sigmoid(x) = e / (e + 1)."""
    x, e, t = saved
    if INPLACE:
        s = e + 1.0
        s = torch.div(e, s, out=s)
        return torch.mul(t, t).neg_().add_(1.0).mul_(x).mul_(s).add_(t).mul_(grad)
    return grad * (t + x * (1.0 - t * t) * (e / (e + 1.0)))


def layer_norm_forward(x, norm):
    return torch.native_layer_norm(x, (x.shape[1],), norm.weight, norm.bias, norm.eps)     # (y, mean, rstd)


def layer_norm_backward(grad, x, mean, rstd, norm):
    return torch.ops.aten.native_layer_norm_backward(grad, x, (x.shape[1],), mean, rstd, norm.weight, norm.bias,
                                                     (True, True, True))                   # (dx, dweight, dbias)


def parameters_of(net):
    """The residual MLP's parameters in the order the Function takes (and returns the gradients of) them."""
    blocks = [p for b in net.blocks for p in (b.norm.weight, b.norm.bias, b.fc1.weight, b.fc1.bias, b.fc2.weight,
                                              b.fc2.bias)]
    norm, _, out = net.final
    return [net.inp.weight, net.inp.bias, *blocks, norm.weight, norm.bias, out.weight, out.bias]


class FusedForward(torch.autograd.Function):
    """ResidualMLP.forward on the flat chunk a (B, H dof) and film (B, F), the parameters passed (parameters_of)."""

    @staticmethod
    def forward(ctx, a, film, net, *params):
        x = torch.addmm(net.inp.bias, a, net.inp.weight.t())                         # (B, width)
        saved = []
        for block, f in zip(net.blocks, film.split(net.film_sizes, dim=1)):
            scale, bias = f.chunk(2, dim=1)
            y, mean, rstd = layer_norm_forward(x, block.norm)
            m1, s1 = mish_forward(y)
            h = torch.addmm(block.fc1.bias, m1, block.fc1.weight.t())
            m2, s2 = mish_forward(torch.addcmul(bias, scale, h))                     # FiLM, then Mish
            saved.append((x, mean, rstd, m1, s1, h, scale, m2, s2))
            x = x + torch.addmm(block.fc2.bias, m2, block.fc2.weight.t())             # the residual sum
        norm, _, out = net.final
        y, mean, rstd = layer_norm_forward(x, norm)
        m, s = mish_forward(y)
        ctx.net, ctx.a, ctx.blocks, ctx.final = net, a, saved, (x, mean, rstd, m, s)
        return torch.addmm(out.bias, m, out.weight.t())                              # (B, H dof)

    @staticmethod
    def backward(ctx, grad):
        net, grads = ctx.net, []                                                     # in reverse parameter order
        norm, _, out = net.final
        x, mean, rstd, m, s = ctx.final
        grads += [grad.sum(0), grad.t() @ m]                  # out.bias, out.weight
        gx, gw, gb = layer_norm_backward(mish_backward(grad @ out.weight, s), x, mean, rstd, norm)
        grads += [gb, gw]
        film_grads = []
        for block, (x, mean, rstd, m1, s1, h, scale, m2, s2) in zip(reversed(net.blocks), reversed(ctx.blocks)):
            grads += [gx.sum(0), gx.t() @ m2]                                         # fc2.bias, fc2.weight
            gu = mish_backward(gx @ block.fc2.weight, s2)                             # d loss / d (scale h + bias)
            gh = gu * scale
            film_grads.append(torch.cat([gu * h, gu], dim=1))                          # d scale, d bias
            grads += [gh.sum(0), gh.t() @ m1]                                         # fc1.bias, fc1.weight
            gy, gw, gb = layer_norm_backward(mish_backward(gh @ block.fc1.weight, s1), x, mean, rstd, block.norm)
            grads += [gb, gw]
            gx = gx + gy                                                              # the residual stream
        grads += [gx.sum(0), gx.t() @ ctx.a]                                          # inp.bias, inp.weight
        film_grad = torch.cat(film_grads[::-1], dim=1)
        return (None, film_grad, None, *grads[::-1])


def fused_forward(net, a, film):
    """ResidualMLP.forward through FusedForward: a (B, H, dof), film (B, F) -> eps (B, H, dof)."""
    eps = FusedForward.apply(a.flatten(1), film, net, *parameters_of(net))
    return eps.reshape(-1, net.horizon, net.dof)


def fuse(net):
    """net (a diffusion.ResidualMLP) computing its forward through FusedForward, in place. Returns net."""
    net.forward = fused_forward.__get__(net)
    return net


def check(cfg, env):
    """Max |fused - diffusion.py's| of the output and of every gradient, on random weights; equal to the bit?"""
    ours = dagger.make_policy(cfg, env).net
    with torch.no_grad():
        for p in ours.parameters():                     # the zero-initialised output layer would hide its inputs
            p.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(p.numel()))
    fused = fuse(copy.deepcopy(ours))
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(64, cfg.horizon, env.dof, generator=gen)
    films = [torch.randn(64, ours.film_size, generator=gen).requires_grad_() for _ in range(2)]
    films[1].data.copy_(films[0].data)
    outs = [ours(a, films[0]), fused(a, films[1])]
    g = torch.randn(outs[0].shape, generator=gen)
    for out in outs:
        (out * g).sum().backward()
    pairs = [("output", outs[0], outs[1]), ("film gradient", films[0].grad, films[1].grad)]
    pairs += [(name + " gradient", p.grad, q.grad)
              for (name, p), q in zip(ours.named_parameters(), fused.parameters()) if p.grad is not None]
    worst = max(float((x - y).detach().abs().max()) for _, x, y in pairs)
    bitwise = all(torch.equal(x, y) for _, x, y in pairs)
    return len(pairs), worst, bitwise


def constant_film(policy, a_k_norm, k, obs_norm, use_ema=True, cond=None):
    """DiffusionPolicy.predict_eps with the FiLM vector all ones (--film-bound: a cost bound, not the method)."""
    net = policy.ema_net if use_ema else policy.net
    return net(a_k_norm, torch.ones(a_k_norm.shape[0], net.film_size))


def main():
    global INPLACE
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--inplace", action="store_true", help="the fused Mish with in-place ops")
    parser.add_argument("--film-bound", action="store_true", help="also time a step whose FiLM vector is constant")
    args = parser.parse_args()
    INPLACE = args.inplace
    torch.set_num_threads(1)
    cfg = dagger.PROFILES["quick"]
    env = dagger.make_run_env(cfg)
    kind = cpu_kernels.this_cpu_kind()
    print(f"CPU {kind}, torch {torch.__version__}, 1 thread; MEASURED's kernels for training: "
          f"{cpu_kernels.kernels_wanted('training') or 'none'}; fused Mish in-place: {INPLACE}")
    n, worst, bitwise = check(cfg, env)
    print(f"fused vs diffusion.py's network: output and {n - 1} gradients, max |difference| {worst:.3g}, "
          f"equal to the bit: {bitwise}")

    rng = np.random.default_rng(0)
    obs = rng.normal(size=(20_000, env.obs_dim)).astype(np.float32)
    chunks = (0.1 * rng.normal(size=(20_000, cfg.horizon, env.dof))).astype(np.float32)
    policies = {"diffusion.py's": dagger.make_policy(cfg, env), "fused": dagger.make_policy(cfg, env)}
    fuse(policies["fused"].net)
    if args.film_bound:
        policies["FiLM constant"] = dagger.make_policy(cfg, env)
        policies["FiLM constant"].predict_eps = types.MethodType(constant_film, policies["FiLM constant"])

    def train(policy, steps):
        tc = diffusion.TrainConfig(steps=steps, batch_size=cfg.batch_size, lr=cfg.lr, log_every=0,
                                   obs_noise=dagger.observation_noise(policy.cfg))
        t = time.perf_counter()
        diffusion.train(policy, obs, chunks, tc)
        return 1000 * (time.perf_counter() - t) / steps

    for policy in policies.values():
        train(policy, 30)                                                  # warm-up
    ms = {name: [] for name in policies}
    for r in range(args.repeats):
        for name, policy in policies.items():
            ms[name].append(train(policy, args.steps))
        print(f"round {r + 1}: " + ", ".join(f"{name} {v[-1]:.2f} ms" for name, v in ms.items()))
    med = {name: statistics.median(v) for name, v in ms.items()}
    base = med.pop("diffusion.py's")
    print(f"diffusion.train, ms a step (median of {args.repeats} x {args.steps} steps, batch {cfg.batch_size}): "
          f"diffusion.py's {base:.2f}; " + ", ".join(f"{n} {v:.2f} ({base / v:.3f}x)" for n, v in med.items()))


if __name__ == "__main__":
    main()
