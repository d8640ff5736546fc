"""The epsilon-network computed faster: its FiLM maps split (the FiLM table), and CPU kernels for its Linear and Mish
where they pay (none of the paper).

The FiLM table (FiLMTable) computes diffusion.FiLMNetwork's eps_theta with every block's FiLM map split along its
input: the observation's part once per batch of observations, the step part for all K steps at once, where the plain
network computes the whole map at each of a sampling call's K reverse steps. use_kernels swaps it into every policy
the run makes (dagger.make_policy, a loaded checkpoint), on any device: the committed numbers are its.

diffusion.py's networks are written with torch's nn.Linear, nn.Mish and nn.functional.linear. On some CPUs two
kernels compute the same functions faster (benchmarks/HISTORY.md, "The training step at the machine's speed"):
  - linear(x, W, b) = x W^T + b through oneDNN, which torch ships for its compiler (the internal op
    torch.ops.mkldnn._linear_pointwise): torch's own CPU product calls MKL, which on an AMD CPU takes its AVX2 code,
    where oneDNN uses AVX-512 if the CPU has it. Forward and both gradients one oneDNN call each;
  - mish(x) = x tanh(softplus(x)) (Misra 2019) in closed form, its derivative written out.
Both equal torch's to float32 rounding, not to the bit (tests/test_cpu_kernels.py): a run with the kernels and
one without differ in their last bits, and a run with them is deterministic, as one without.

use_kernels(policy) swaps them into a policy in place, each kernel on its own: policy.net (it trains) where it pays
for training on this CPU, policy.ema_net (it samples) where it pays for sampling (MEASURED). The parameters stay the
same objects and the state_dict keys nn.Linear's, so a checkpoint written with the kernels loads without them.
The environment variable PCD_CPU_KERNELS=on|off|linear|mish|auto (default auto: MEASURED) overrides the table.
"""

import os
import sys

import torch
import torch.nn as nn

import diffusion

# oneDNN's matrix product as torch's inductor calls it: a torch without it keeps its own product
ONEDNN = torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")

KERNELS = ("linear", "mish")

# Which kernels pay on a CPU kind, for training (diffusion.train) and for sampling (DiffusionPolicy.sample)?
# (vendor, family, model) as /proc/cpuinfo names them, model None: every model of the family. Measured with
# benchmarks/bench_train_step.py, its rows of each kernel alone and both against torch's own (benchmarks/README.md,
# "Speed"; the measurements in benchmarks/HISTORY.md). A CPU kind not in the table was not measured: torch's own.
MEASURED = {
    # Zen 5 EPYC, both together: train() 1.54x, sample 1.85x (each alone not measured there)
    ("AuthenticAMD", 26, None): {"training": KERNELS, "sampling": KERNELS},
    # Zen 4 EPYC, both together: train() 1.08x, sample 0.91x (each alone not measured there)
    ("AuthenticAMD", 25, 17): {"training": (), "sampling": ()},
    # Zen 3 EPYC (AVX2): the closed-form Mish alone pays, oneDNN's product does not
    ("AuthenticAMD", 25, 1): {"training": ("mish",), "sampling": ("mish",)},
}


def cpu_kind(cpuinfo):
    """(vendor, family, model) of the first processor in a /proc/cpuinfo text; None if it names none of them."""
    fields = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    try:
        return fields["vendor_id"], int(fields["cpu family"]), int(fields["model"])
    except (KeyError, ValueError):
        return None


def measured_to_pay(kind, use):
    """MEASURED's kernels (a tuple of KERNELS' names) for a cpu_kind() and a use ('training' or 'sampling'); none
    for a kind not measured."""
    if kind is None:
        return ()
    vendor, family, model = kind
    row = MEASURED.get((vendor, family, model), MEASURED.get((vendor, family, None), {}))
    return tuple(row.get(use, ()))


def this_cpu_kind():
    """cpu_kind() of this machine (Linux); None elsewhere: no CPU kind is measured on other systems."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        with open("/proc/cpuinfo") as f:
            return cpu_kind(f.read())
    except OSError:
        return None


def kernels_wanted(use):
    """The kernels (a tuple of KERNELS' names) `use` ('training' or 'sampling') gets: PCD_CPU_KERNELS (read here
    only) forces both (on), none (off) or one (linear, mish); auto asks MEASURED about this CPU kind. Never timed
    at run time. The product needs torch's oneDNN op: without it, linear is left out."""
    setting = os.environ.get("PCD_CPU_KERNELS", "auto")
    choices = {"on": KERNELS, "off": (), **{k: (k,) for k in KERNELS}}
    if setting != "auto" and setting not in choices:
        raise ValueError(f"PCD_CPU_KERNELS must be auto, {', '.join(choices)}, got {setting!r}")
    wanted = choices[setting] if setting != "auto" else measured_to_pay(this_cpu_kind(), use)
    return tuple(k for k in wanted if ONEDNN or k != "linear")


# ---- The kernels --------------------------------------------------------------------------------------------------
def _onednn_matmul(x, weight_t, bias=None):
    """x (M, K) @ weight_t.T (K, N) [+ bias (N,)] -> (M, N) through oneDNN; a contiguous tensor or its transpose is
    read as it is."""
    return torch.ops.mkldnn._linear_pointwise(x, weight_t, bias, "none", [], "")


class _OneDNNLinear(torch.autograd.Function):
    """y = x W^T + b, dL/dx = g W, dL/dW = g^T x, dL/db = sum_rows g: each product one oneDNN call."""

    @staticmethod
    def forward(ctx, x, weight, bias):
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        return _onednn_matmul(x, weight, bias)                         # (M, out)

    @staticmethod
    def backward(ctx, grad):                                           # grad (M, out)
        x, weight = ctx.saved_tensors
        grad = grad.contiguous()                                       # e.g. the expanded gradient of a sum
        need_x, need_w, need_b = ctx.needs_input_grad
        grad_x = _onednn_matmul(grad, weight.t()) if need_x else None  # (M, in)
        grad_w = _onednn_matmul(grad.t(), x.t()) if need_w else None   # (out, in)
        grad_b = grad.sum(0) if need_b and ctx.has_bias else None      # (out,)
        return grad_x, grad_w, grad_b


def linear(x, weight, bias=None):
    """nn.functional.linear(x, weight, bias): x (M, in), weight (out, in), bias (out,) or None -> (M, out).
    A contiguous 2-D float32 input and weight on the CPU go through oneDNN; anything else (a GPU, float64, a
    column slice of a weight, which oneDNN reads ~500x slower, a torch without the op) through torch's own."""
    if (ONEDNN and x.dim() == 2 and x.device.type == "cpu" and x.dtype == weight.dtype == torch.float32
            and x.is_contiguous() and weight.is_contiguous()):
        return _OneDNNLinear.apply(x, weight, bias)
    return nn.functional.linear(x, weight, bias)


class _Mish(torch.autograd.Function):
    """mish(x) = x tanh(softplus(x)). With e = exp(x): tanh(log(1 + e)) = ((1 + e)^2 - 1) / ((1 + e)^2 + 1)
    = n / (n + 2), n = e (e + 2). Derivative: tanh(softplus(x)) + x (1 - tanh^2(softplus(x))) sigmoid(x).
    One transcendental function (exp) where torch's own Mish takes three (exp, log1p, tanh)."""

    @staticmethod
    def forward(ctx, x):
        e = torch.exp(x.clamp(max=20.0))    # past x = 20, n / (n + 2) is 1 in float32; e^x itself would overflow
        n = e * (e + 2.0)
        t = n / (n + 2.0)                                              # tanh(softplus(x))
        ctx.save_for_backward(x, e, t)
        return x * t

    @staticmethod
    def backward(ctx, grad):
        x, e, t = ctx.saved_tensors
        sigmoid = e / (e + 1.0)
        return grad * (t + x * (1.0 - t * t) * sigmoid)


def mish(x):
    """nn.functional.mish(x), elementwise over any shape."""
    return _Mish.apply(x)


class FastLinear(nn.Linear):
    """nn.Linear (the same parameters and state_dict keys) whose product is linear() above."""

    def forward(self, x):
        return linear(x, self.weight, self.bias)


class FastMish(nn.Mish):
    """nn.Mish computed by mish() above."""

    def forward(self, x):
        return mish(x)


# ---- The FiLM table: eps_theta's FiLM maps split along their input -------------------------------------------------
class FiLMTerms:
    """FiLMTable.encode's result: the obs terms (B, F) of a batch and the step table (K, F) of every step; its rows
    are picked as an observation's features are (terms[rows])."""

    def __init__(self, obs, table):
        self.obs, self.table = obs, table

    def __getitem__(self, rows):
        return FiLMTerms(self.obs[rows], self.table)


class FiLMTable:
    """diffusion.FiLMNetwork's eps_theta with every block's FiLM map W = [W_s | W_o] split along its input:
    film = (W_s Mish(step features) + b) + W_o Mish(obs features). encode() computes the obs terms once per batch of
    observations and the step terms of all K steps at once (the step table), all blocks' maps stacked in one product
    each; forward() adds the table's row k. The plain network computes the whole map at each of the K reverse steps.
    Equal to it to float rounding (tests/test_cpu_kernels.py), not to the bit: every run of this reference computes
    eps_theta so (use_kernels), its committed numbers too."""
    film_linear = staticmethod(nn.functional.linear)   # the FiLM products (swap_in: the oneDNN linear where it pays)

    def film_weights(self):
        """All blocks' FiLM maps stacked and split along the input: (W_s (F, dsed), W_o (F, obs features), b (F,)),
        each stacked whole (oneDNN reads a contiguous weight faster than a column slice)."""
        films, d = [b.film for b in self.residual_blocks()], self.step_embed_dim
        w_step = torch.cat([film.weight[:, :d] for film in films])             # (F, dsed)
        w_obs = torch.cat([film.weight[:, d:] for film in films])              # (F, obs features)
        return w_step, w_obs, torch.cat([film.bias for film in films])         # ..., (F,)

    def encode(self, obs_norm):
        """FiLMTerms: W_o Mish(obs features) (B, F) and W_s Mish(step features) + b (K, F) for all K steps."""
        w_step, w_obs, bias = self.film_weights()
        obs_terms = self.film_linear(self.cond_mish(self.obs_encoder(obs_norm)), w_obs)           # (B, F)
        k = torch.arange(self.K, device=bias.device)
        return FiLMTerms(obs_terms, self.film_linear(self.cond_mish(self.step_features(k)), w_step, bias))

    def forward(self, a, k, terms):
        """eps_theta(a_k, k | o) from encode(o)'s FiLMTerms: film = obs terms + the step table's row k."""
        return self.body(a, terms.obs + terms.table.index_select(0, k))


class TabledUnet1D(FiLMTable, diffusion.ConditionalUnet1D):
    """diffusion.ConditionalUnet1D computed through the FiLM table (the same parameters and state_dict keys)."""


class TabledMLP(FiLMTable, diffusion.ResidualMLP):
    """diffusion.ResidualMLP computed through the FiLM table (the same parameters and state_dict keys)."""


TABLED = {diffusion.ConditionalUnet1D: TabledUnet1D, diffusion.ResidualMLP: TabledMLP}


# ---- The swap -----------------------------------------------------------------------------------------------------
def swap_in(net, kernels=KERNELS):
    """An epsilon-network (diffusion.FiLMNetwork) computed by the named kernels, in place: with 'linear' its nn.Linear
    modules become FastLinear and a FiLM table's products (film_linear) use linear(); with 'mish' its nn.Mish modules
    become FastMish (the same Parameters). Left as they are: the observation encoder's layers and the blocks' `film`
    maps (the FiLM table reads their weights, stacked; a plain network's own is torch's). Returns net."""
    swaps = {nn.Linear: FastLinear if "linear" in kernels else None, nn.Mish: FastMish if "mish" in kernels else None}
    for name, module in net.named_modules():
        if name.startswith("obs_encoder") or name.endswith("film"):
            continue
        if swaps.get(type(module)) is not None:
            module.__class__ = swaps[type(module)]
    if "linear" in kernels and isinstance(net, FiLMTable):
        net.film_linear = linear
    return net


def use_kernels(policy):
    """policy (a diffusion.DiffusionPolicy) with both networks computed through the FiLM table (on any device), and
    on the CPU with the kernels kernels_wanted() names: policy.net's for training, policy.ema_net's for sampling.
    A network class TABLED does not know (a variant's) stays plain. Returns policy."""
    for net, use in ((policy.net, "training"), (policy.ema_net, "sampling")):
        net.__class__ = TABLED.get(type(net), type(net))
        if policy.device.type == "cpu":
            swap_in(net, kernels_wanted(use))
    return policy
