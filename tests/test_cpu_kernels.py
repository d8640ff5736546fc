"""Tests of experiment/cpu_kernels.py: its linear and mish equal torch's (values and gradients, on every path they
take), the swap gives a network exactly the numbers of the fast path built into diffusion.py before it moved out,
keeps its parameters, and is used where MEASURED or PCD_CPU_KERNELS says."""

import pytest
import torch
import torch.nn as nn
from torch.overrides import TorchFunctionMode

import diffusion
from experiment import cpu_kernels


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
    ours = values_and_grads(cpu_kernels.linear, (x, weight, b), grad_out)
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
        assert torch.equal(cpu_kernels.linear(*args), nn.functional.linear(*args))


def test_linear_module_keeps_nn_linear_parameters_and_state_dict_keys():
    torch.manual_seed(0)
    ours = cpu_kernels.FastLinear(5, 3)
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
        ours, theirs = cpu_kernels.mish(ours_in), nn.functional.mish(torch_in)
        ours.sum().backward()
        theirs.sum().backward()
        assert torch.isfinite(ours).all() and torch.isfinite(ours_in.grad).all()
        assert torch.allclose(ours, theirs, rtol=1e-5, atol=1e-6)
        assert torch.allclose(ours_in.grad, torch_in.grad, rtol=1e-5, atol=1e-6)
    assert torch.allclose(cpu_kernels.FastMish()(x), nn.Mish()(x), rtol=1e-5, atol=1e-6)


@pytest.mark.skipif(not cpu_kernels.ONEDNN, reason="this torch has no oneDNN product: the fallback is the only path")
def test_the_networks_products_take_the_fast_path_and_others_torchs():
    """Which path a product takes (their values agree, so only the autograd node tells): a contiguous 2-D float32
    input and weight on the CPU go through oneDNN -- the MLP's every layer -- and a 3-D input through torch's
    own. Fails if the dispatch sent the networks' products to the slow path (a speed bug no value test sees)."""
    w = torch.randn(8, 5, requires_grad=True)
    fast = cpu_kernels.linear(torch.randn(4, 5), w)
    assert type(fast.grad_fn).__name__.startswith("_OneDNNLinear")
    slow = cpu_kernels.linear(torch.randn(3, 4, 5), w)
    assert not type(slow.grad_fn).__name__.startswith("_OneDNNLinear")


# ---- the swap: the numbers of the fast path that diffusion.py had built in ------------------------------------
class EveryProductAndMishThroughTheKernels(TorchFunctionMode):
    """The fast path as diffusion.py had it built in (76f5251): every nn.functional.linear and mish call of the
    epsilon-network through cpu_kernels.linear and mish (or only those of the named kernels). (Its
    FlatObservation has no layers, and a block's `film` map is never called as a module: the FiLM table reads its
    weights.)"""

    def __init__(self, kernels=cpu_kernels.KERNELS):
        super().__init__()
        self.kernels = kernels

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func is nn.functional.mish and "mish" in self.kernels:      # nn.Mish passes inplace=False
            return cpu_kernels.mish(args[0])
        if func is nn.functional.linear and "linear" in self.kernels:
            return cpu_kernels.linear(*args, **(kwargs or {}))
        return func(*args, **(kwargs or {}))


def random_policy(network, seed=0, tabled=True):
    """A small policy with random weights (the zero-initialised output layer would hide a missed layer), its
    networks computed through the FiLM table (as use_kernels has them) unless tabled=False."""
    sizes = dict(down_dims=(8, 16), n_groups=4, horizon=4) if network == "unet" else dict(mlp_width=32, mlp_blocks=2,
                                                                                           horizon=5)
    policy = diffusion.DiffusionPolicy(diffusion.PolicyConfig(obs_dim=6, dof=2, n_act=2, K=10, network=network,
                                                              step_embed_dim=16, **sizes))
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in list(policy.net.parameters()) + list(policy.ema_net.parameters()):
            p.copy_(torch.randn(p.shape, generator=gen) * 0.3)
    policy.fit_normalizer(torch.randn(50, 6, generator=gen).numpy(), torch.randn(50, sizes["horizon"], 2,
                                                                                 generator=gen).numpy())
    if tabled:
        for net in (policy.net, policy.ema_net):
            net.__class__ = cpu_kernels.TABLED[type(net)]
    return policy


@pytest.mark.parametrize("network", ["unet", "mlp"])
def test_film_table_is_the_plain_networks_eps_theta(network):
    """The FiLM table's eps_theta (the map split along its input, the step part of all K steps at once) equals the
    plain network's to float rounding, training (the loss and every gradient) and sampling, and one row of the
    table is the row of its own step. Fails if the split takes W_s and W_o from the wrong columns, drops the
    bias, adds the table's row of another step, or picks rows of the obs terms apart from the chunks'."""
    tabled, plain = random_policy(network), random_policy(network, tabled=False)
    assert type(tabled.net) is cpu_kernels.TABLED[type(plain.net)]
    for got, want in zip(loss_grads_and_samples(tabled), loss_grads_and_samples(plain)):
        assert torch.allclose(got, want, atol=1e-5, rtol=1e-4)
    net, gen = tabled.net, torch.Generator().manual_seed(2)
    obs_norm = tabled.normalize_obs(torch.randn(6, 6, generator=gen))
    a, k = torch.randn(6, tabled.cfg.horizon, 2, generator=gen), torch.tensor([0, 3, 9, 7, 7, 1])
    rows = torch.tensor([4, 0, 2])
    got = net(a[rows], k[rows], net.encode(obs_norm)[rows])          # the reverse process's active rows
    want = plain.net(a[rows], k[rows], plain.net.encode(obs_norm[rows]))
    assert torch.allclose(got, want, atol=1e-5, rtol=1e-4)


def loss_grads_and_samples(policy):
    """One training step's loss and parameter gradients (policy.net) and a sample (policy.ema_net)."""
    gen = torch.Generator().manual_seed(1)
    obs = torch.randn(12, 6, generator=gen)
    chunks = torch.randn(12, policy.cfg.horizon, 2, generator=gen)
    loss = policy.loss(policy.normalize_obs(obs), policy.normalize_actions(chunks, obs), generator=gen)
    loss.backward()
    grads = [p.grad for p in policy.net.parameters()]
    return [loss.detach()] + grads + [torch.as_tensor(policy.sample(obs[:5].numpy(), generator=gen))]


@pytest.mark.parametrize("kernels", [cpu_kernels.KERNELS, ("mish",), ("linear",)])
@pytest.mark.parametrize("network", ["unet", "mlp"])
def test_swapped_network_gives_the_built_in_fast_paths_numbers_bit_for_bit(network, kernels):
    """Loss, every parameter's gradient and a sample equal to the bit those of the network with every product and
    Mish through the kernels (the fast path diffusion.py had built in), or with only one kind through its kernel.
    Fails if the swap leaves a Linear, a Mish module or the FiLM table's products (film_linear) to torch's own, for
    training (net) or sampling (ema_net), or swaps in a kernel it was not asked for."""
    swapped = random_policy(network)                                 # both through the FiLM table
    cpu_kernels.swap_in(swapped.net, kernels)
    cpu_kernels.swap_in(swapped.ema_net, kernels)
    reference = random_policy(network)
    with EveryProductAndMishThroughTheKernels(kernels):
        expected = loss_grads_and_samples(reference)
    got = loss_grads_and_samples(swapped)
    assert len(got) == len(expected)
    assert all(torch.equal(a, b) for a, b in zip(got, expected))
    plain = loss_grads_and_samples(random_policy(network))          # the check can fail where torch's own differ
    if all(torch.equal(a, b) for a, b in zip(plain, expected)):     # (Intel Xeon, AVX-512/AMX: the linear kernel)
        pytest.skip(f"on this CPU torch's own {network} equals the {kernels} kernels' to the bit: a swap that left "
                    "torch's own in place could not be told apart here")


def test_swap_keeps_parameters_state_dict_and_torchs_own_where_it_was():
    """The same Parameter objects and state_dict keys (a checkpoint loads either way); the blocks' `film` maps and
    an observation encoder's layers stay torch's nn.Linear, as they were before the fast path moved. Fails if the
    swap copies a parameter (AdamW and the EMA would update a stale one), renames a key or takes in a layer the
    built-in fast path did not."""
    from experiment.image_obs import ImageEncoder
    cfg = diffusion.PolicyConfig(obs_dim=70, dof=2, horizon=4, n_act=2, K=10, down_dims=(8, 16), n_groups=4,
                                 obs_encoder="ImageEncoder", obs_encoder_args={"shape": (1, 8, 8), "features": 16},
                                 obs_encoder_sizes=(64, 16))
    plain, swapped = (diffusion.DiffusionPolicy(cfg, obs_encoder=ImageEncoder) for _ in range(2))
    parameters = list(swapped.net.parameters())
    cpu_kernels.swap_in(swapped.net)
    assert [id(p) for p in swapped.net.parameters()] == [id(p) for p in parameters]
    assert swapped.state_dict().keys() == plain.state_dict().keys()
    plain.load_state_dict(swapped.state_dict())
    swapped.load_state_dict(plain.state_dict())
    kinds = {name: type(m) for name, m in swapped.net.named_modules()}
    assert kinds["step_encoder.0"] is cpu_kernels.FastLinear and kinds["cond_mish"] is cpu_kernels.FastMish
    assert all(kinds[f"{name}.film"] is nn.Linear for name, kind in kinds.items() if f"{name}.film" in kinds)
    encoder = [kind for name, kind in kinds.items() if name.startswith("obs_encoder")]
    assert nn.Linear in encoder and cpu_kernels.FastLinear not in encoder and cpu_kernels.FastMish not in encoder


# ---- where the kernels are used -------------------------------------------------------------------------------
def cpuinfo(vendor, family, model):
    return (f"processor\t: 0\nvendor_id\t: {vendor}\ncpu family\t: {family}\nmodel\t\t: {model}\n"
            f"model name\t: a CPU\n\nprocessor\t: 1\nvendor_id\t: {vendor}\n")


BOTH = cpu_kernels.KERNELS


@pytest.mark.parametrize("text,training,sampling", [
    (cpuinfo("AuthenticAMD", 26, 2), BOTH, BOTH),                      # Zen 5: every model of the family
    (cpuinfo("AuthenticAMD", 25, 17), (), ()),                         # Zen 4: sampling (and training) slower
    (cpuinfo("AuthenticAMD", 25, 1), ("mish",), ("mish",)),            # Zen 3: the Mish alone pays
    (cpuinfo("GenuineIntel", 6, 143), (), ()),                         # not measured
    ("processor\t: 0\nCPU implementer\t: 0x41\n", (), ()),             # an ARM's cpuinfo: no kind
])
def test_measured_table_decides_per_cpu_kind_and_use(text, training, sampling):
    """Fails if a CPU kind that was not measured (or measured slower) gets a kernel, Zen 5 loses one, or Zen 3
    gets the product it was measured not to pay with."""
    kind = cpu_kernels.cpu_kind(text)
    assert (cpu_kernels.measured_to_pay(kind, "training"), cpu_kernels.measured_to_pay(kind, "sampling")) == (
        training, sampling)


def test_switch_forces_the_kernels_on_or_off_and_names_a_bad_value(monkeypatch):
    """PCD_CPU_KERNELS=on swaps both nets, off neither, mish only the Mish, auto follows MEASURED; another value
    is a ValueError. Fails if the switch is ignored, or a policy on torch's own is touched."""
    monkeypatch.setenv("PCD_CPU_KERNELS", "on")
    on = cpu_kernels.use_kernels(random_policy("mlp"))
    assert type(on.net.inp) is type(on.ema_net.inp) is cpu_kernels.FastLinear
    assert on.net.film_linear is on.ema_net.film_linear is cpu_kernels.linear
    monkeypatch.setenv("PCD_CPU_KERNELS", "off")
    off = cpu_kernels.use_kernels(random_policy("mlp"))
    assert type(off.net.inp) is type(off.ema_net.inp) is nn.Linear
    assert off.net.film_linear is nn.functional.linear and type(off.net.cond_mish) is nn.Mish
    monkeypatch.setenv("PCD_CPU_KERNELS", "mish")
    mish = cpu_kernels.use_kernels(random_policy("mlp"))
    assert type(mish.net.inp) is type(mish.ema_net.inp) is nn.Linear and mish.net.film_linear is nn.functional.linear
    assert type(mish.net.cond_mish) is type(mish.ema_net.cond_mish) is cpu_kernels.FastMish
    monkeypatch.setenv("PCD_CPU_KERNELS", "auto")
    monkeypatch.setattr(cpu_kernels, "this_cpu_kind", lambda: ("AuthenticAMD", 25, 17))
    assert cpu_kernels.kernels_wanted("sampling") == ()
    monkeypatch.setattr(cpu_kernels, "this_cpu_kind", lambda: ("AuthenticAMD", 26, 2))
    assert cpu_kernels.kernels_wanted("sampling") == (BOTH if cpu_kernels.ONEDNN else ("mish",))
    monkeypatch.setenv("PCD_CPU_KERNELS", "fast")
    with pytest.raises(ValueError, match="PCD_CPU_KERNELS.*'fast'"):
        cpu_kernels.use_kernels(random_policy("mlp"))
