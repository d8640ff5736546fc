"""Tests of diffusion.py's fast path (its last section): linear and mish equal torch's, values and gradients, on every path they take."""

import pytest
import torch
import torch.nn as nn

import diffusion


def values_and_grads(fn, inputs, grad_out):
    """fn(*inputs) and the gradients of <fn(*inputs), grad_out> with respect to the inputs that require them."""
    out = fn(*inputs)
    wanted = [x for x in inputs if x is not None and x.requires_grad]
    return [out.detach()] + list(torch.autograd.grad(out, wanted, grad_out))


@pytest.mark.parametrize("bias", [True, False])
@pytest.mark.parametrize("input_grad", [True, False])   # the network's first layer: its input needs no gradient
def test_linear_equals_torch_values_and_gradients(bias, input_grad):
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(37, 23, generator=gen).requires_grad_(input_grad)
    weight = torch.randn(64, 23, generator=gen, requires_grad=True)
    b = torch.randn(64, generator=gen, requires_grad=True) if bias else None
    grad_out = torch.randn(37, 64, generator=gen)
    ours = values_and_grads(diffusion.linear, (x, weight, b), grad_out)
    torch_s = values_and_grads(nn.functional.linear, (x, weight, b), grad_out)
    assert len(ours) == len(torch_s) == 1 + input_grad + 1 + bias
    for a, c in zip(ours, torch_s):
        assert torch.allclose(a, c, rtol=1e-5, atol=1e-5)


def test_linear_falls_back_to_torch_where_onednn_would_not_pay():
    """A column slice of a weight (film_weights' W_o), a 3-D input and float64 take torch's own product: equal bits."""
    gen = torch.Generator().manual_seed(1)
    stacked = torch.randn(48, 40, generator=gen)
    x = torch.randn(8, 30, generator=gen)
    for args in ((x, stacked[:, 10:]), (x.reshape(2, 4, 30), stacked[:, :30]), (x.double(), stacked[:, :30].double())):
        assert torch.equal(diffusion.linear(*args), nn.functional.linear(*args))


def test_linear_module_keeps_nn_linear_parameters_and_state_dict_keys():
    torch.manual_seed(0)
    ours = diffusion.Linear(5, 3)
    torch.manual_seed(0)
    theirs = nn.Linear(5, 3)
    assert ours.state_dict().keys() == theirs.state_dict().keys()
    assert all(torch.equal(a, b) for a, b in zip(ours.state_dict().values(), theirs.state_dict().values()))
    x = torch.randn(4, 5)
    with torch.inference_mode():                                       # sampling
        assert torch.allclose(ours(x), theirs(x), atol=1e-6)


def test_mish_equals_torch_values_and_gradients_over_a_wide_range():
    """Including the far tails (e^x overflows past 88 unclamped) and a 3-D input (the U-Net's (B, C, T))."""
    x = torch.cat([torch.linspace(-100, 100, 20_000), torch.tensor([-1e4, -30.0, 0.0, 30.0, 1e4])])
    for shape in ((-1,), (5, 1, -1)):
        ours_in = x.reshape(shape).clone().requires_grad_()
        torch_in = x.reshape(shape).clone().requires_grad_()
        ours, theirs = diffusion.mish(ours_in), nn.functional.mish(torch_in)
        ours.sum().backward()
        theirs.sum().backward()
        assert torch.isfinite(ours).all() and torch.isfinite(ours_in.grad).all()
        assert torch.allclose(ours, theirs, rtol=1e-5, atol=1e-6)
        assert torch.allclose(ours_in.grad, torch_in.grad, rtol=1e-5, atol=1e-6)
    assert torch.allclose(diffusion.Mish()(x), nn.Mish()(x), rtol=1e-5, atol=1e-6)


@pytest.mark.skipif(not diffusion.ONEDNN, reason="this torch has no oneDNN product: the fallback is the only path")
def test_the_networks_products_take_the_fast_path_and_others_torchs():
    """Which path a product takes (their values agree, so only the autograd node tells): a contiguous 2-D float32
    input and weight on the CPU go through oneDNN -- the MLP's every layer -- and a 3-D input through torch's
    own. Fails if the dispatch sent the networks' products to the slow path (a speed bug no value test sees)."""
    w = torch.randn(8, 5, requires_grad=True)
    fast = diffusion.linear(torch.randn(4, 5), w)
    assert type(fast.grad_fn).__name__.startswith("_OneDNNLinear")
    slow = diffusion.linear(torch.randn(3, 4, 5), w)
    assert not type(slow.grad_fn).__name__.startswith("_OneDNNLinear")
