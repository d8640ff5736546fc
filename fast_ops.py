"""nn.Linear and Mish as diffusion.py's epsilon-networks use them, computed the faster way this CPU allows.

The same functions as torch's, to float32 rounding (tests/test_fast_ops.py); only the way they are computed differs.
Measured on the 2-core AMD EPYC (torch 2.13 CPU, one thread; benchmarks/README.md, "The training step at the
machine's speed (issue 54)"):
  - linear(x, W, b) = x W^T + b. torch's CPU matrix product calls MKL, which on an AMD CPU takes its AVX2 path:
    ~100 GFLOP/s for a 256 x 256 x 256 product. oneDNN, which torch also ships, runs it with AVX-512 at ~220 GFLOP/s.
    A contiguous 2-D float32 input and weight on the CPU go through oneDNN, forward and both gradients; anything
    else (a GPU, float64, a slice of a weight, a torch built without oneDNN) through nn.functional.linear: oneDNN
    reads a weight with a row stride other than its width ~500x slower (measured: 150 ms for a 256 x 17 x 1536
    product).
  - mish(x) = x tanh(softplus(x)) (Misra 2019, the activation of Chi et al.'s U-Net) in closed form, with its
    derivative written out: forward and backward ~2.5x faster than torch's mish kernel on a (256, 256) input.
"""

import torch
import torch.nn as nn

# oneDNN's matrix product as torch's inductor calls it (an internal op: a torch without it falls back to torch's own)
ONEDNN = torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")


def _onednn_matmul(x, weight_t):
    """x (M, K) @ weight_t.T (K, N) -> (M, N) through oneDNN; a contiguous tensor or its transpose is read as it is."""
    return torch.ops.mkldnn._linear_pointwise(x, weight_t, None, "none", [], "")


class _OneDNNLinear(torch.autograd.Function):
    """y = x W^T + b, dL/dx = g W, dL/dW = g^T x, dL/db = sum_rows g: each product one oneDNN call."""

    @staticmethod
    def forward(ctx, x, weight, bias):
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "none", [], "")     # (M, out)

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
    """nn.functional.linear(x, weight, bias): x (M, in), weight (out, in), bias (out,) or None -> (M, out)."""
    if (ONEDNN and x.dim() == 2 and x.device.type == "cpu" and x.dtype == weight.dtype == torch.float32
            and x.is_contiguous() and weight.is_contiguous()):
        return _OneDNNLinear.apply(x, weight, bias)
    return nn.functional.linear(x, weight, bias)


class Linear(nn.Linear):
    """nn.Linear (the same parameters and state_dict keys) whose product is linear() above."""

    def forward(self, x):
        return linear(x, self.weight, self.bias)


class _Mish(torch.autograd.Function):
    """mish(x) = x tanh(softplus(x)). With e = exp(x): tanh(log(1 + e)) = ((1 + e)^2 - 1) / ((1 + e)^2 + 1)
    = n / (n + 2), n = e (e + 2). Derivative: tanh(softplus(x)) + x (1 - tanh^2(softplus(x))) sigmoid(x)."""

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


class Mish(nn.Module):
    """nn.Mish computed by mish() above."""

    def forward(self, x):
        return mish(x)
