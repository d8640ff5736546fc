"""Tests of diffusion.py: the DDPM equations against closed forms, the policy, the dataset, training."""

import copy
import math
import re

import numpy as np
import pytest
import torch
import torch.nn as nn

from diffusion import (DiffusionPolicy, PolicyConfig, TrainConfig, chunk_dataset, expert_runs, label_mask, lr_at,
                       make_schedule, p_sample, q_sample, step_embedding, toy_two_mode_data, train)
from experiment import checkpoints, cpu_kernels


# A two-level U-Net (one downsampling) small enough for tests: one torch thread, a few seconds of training.
TINY_NET = dict(down_dims=(16, 32), n_groups=4, step_embed_dim=32)


def tiny_policy(**overrides):
    kwargs = dict(obs_dim=4, dof=2, horizon=4, n_act=2, K=50, **TINY_NET)   # obs: (q_t, q_t-1) of 2 joints
    kwargs.update(overrides)
    return DiffusionPolicy(PolicyConfig(**kwargs))


@pytest.fixture(scope="module")
def toy_trained():
    """A small policy trained on the two-mode toy task (a few seconds of CPU), shared by several tests."""
    obs, chunks = toy_two_mode_data(2000, H=4, seed=0)
    policy = tiny_policy()
    train(policy, obs, chunks, TrainConfig(steps=400, batch_size=128, lr=1e-2, warmup_steps=50,
                                           log_every=0, seed=0))
    return policy


# ---------------------------------------------------------------------------------------------- schedule

def cosine_alphabar(t, s=0.008):
    f = lambda u: math.cos((u + s) / (1 + s) * math.pi / 2) ** 2
    return f(t) / f(0.0)


def test_squaredcos_schedule_matches_closed_form():
    K = 100
    sch = make_schedule(K)
    abar = sch.alphas_cumprod.double().numpy()
    # Before the cap, alphabar_{k+1} = f((k+1)/K) / f(0) (code index k = paper step k + 1).
    for k in (0, 10, 50, 90, 97):
        assert abar[k] == pytest.approx(cosine_alphabar((k + 1) / K), rel=1e-5)
    assert np.all(np.diff(abar) < 0), "alphabar must decrease strictly"
    assert sch.betas.max().item() == pytest.approx(0.999), "the last beta is capped at 0.999"
    assert np.all(sch.betas.numpy() <= 0.999 + 1e-7)
    assert abar[-1] < 1e-6, "the last level must be (almost) pure noise"
    assert sch.alphas_cumprod_prev[0].item() == 1.0
    assert torch.allclose(sch.alphas_cumprod_prev[1:], sch.alphas_cumprod[:-1])
    assert torch.allclose(sch.alphas, 1 - sch.betas)
    assert np.allclose(np.cumprod(sch.alphas.double().numpy()), abar, rtol=1e-5)


@pytest.mark.parametrize("K", [0, -3, 2.5])
def test_bad_schedule_raises(K):
    with pytest.raises(ValueError, match="K must be a positive int"):
        make_schedule(K)


# ---------------------------------------------------------------------------------------------- Eq. (5)

def test_q_sample_equals_iterating_eq5():
    sch = make_schedule(100)
    gen = torch.Generator().manual_seed(0)
    n, k = 200_000, 30                                  # code level 30 = paper step 31
    a0 = torch.tensor([0.7, -0.4])
    a = a0.expand(n, 2).double()
    for j in range(k + 1):                              # Eq. (5), one step at a time
        alpha = sch.alphas[j].double()
        a = alpha.sqrt() * a + (1 - alpha).sqrt() * torch.randn(n, 2, generator=gen, dtype=torch.float64)
    closed = q_sample(sch, a0.expand(n, 2), torch.full((n,), k), torch.randn(n, 2, generator=gen))
    abar = sch.alphas_cumprod[k].item()
    for samples in (a.float(), closed):
        assert torch.allclose(samples.mean(0), math.sqrt(abar) * a0, atol=0.01)
        assert torch.allclose(samples.var(0), torch.full((2,), 1 - abar), rtol=0.02)
    assert torch.allclose(a.float().mean(0), closed.mean(0), atol=0.01)
    assert torch.allclose(a.float().var(0), closed.var(0), rtol=0.02)


# ---------------------------------------------------------------------------------------------- Eq. (6)

def test_posterior_matches_gaussian_product():
    """q(a_{k-1} | a_k, a_0) ∝ q(a_k | a_{k-1}) q(a_{k-1} | a_0): multiply the two Gaussians directly."""
    sch = make_schedule(100)
    b, al = sch.betas.double(), sch.alphas.double()
    abar_prev = sch.alphas_cumprod_prev.double()
    for k in range(1, 100):
        # In a_{k-1}: q(a_k | a_{k-1}) has precision alpha/beta and mean a_k / sqrt(alpha);
        # q(a_{k-1} | a_0) has precision 1 / (1 - abar_prev) and mean sqrt(abar_prev) a_0.
        precision = al[k] / b[k] + 1 / (1 - abar_prev[k])
        assert sch.posterior_variance[k].item() == pytest.approx(1 / precision.item(), rel=1e-4)
        coef_a0 = abar_prev[k].sqrt() / (1 - abar_prev[k]) / precision
        coef_ak = al[k].sqrt() / b[k] / precision
        assert sch.posterior_mean_coef1[k].item() == pytest.approx(coef_a0.item(), rel=1e-4)
        assert sch.posterior_mean_coef2[k].item() == pytest.approx(coef_ak.item(), rel=1e-4)
    # code k = 0 (paper step 1): a_0 is known exactly once a_1 and a_0 are given.
    assert sch.posterior_variance[0].item() == 0.0
    assert sch.posterior_mean_coef1[0].item() == pytest.approx(1.0)
    assert sch.posterior_mean_coef2[0].item() == pytest.approx(0.0, abs=1e-7)


def test_p_sample_without_clip_is_eq6():
    sch = make_schedule(100)
    gen = torch.Generator().manual_seed(1)
    a_k, eps, z = (torch.randn(64, 4, 2, generator=gen) for _ in range(3))
    k = torch.randint(1, 100, (64,), generator=gen)
    out = p_sample(sch, eps, a_k, k, noise=z, clip=False)
    r = lambda c: c[k].view(-1, 1, 1)
    # Eq. (6): a_{k-1} = (a_k - beta / sqrt(1 - abar) eps) / sqrt(alpha) + sigma z
    eq6 = (a_k - r(sch.betas) / r(1 - sch.alphas_cumprod).sqrt() * eps) / r(sch.alphas).sqrt() \
        + r(sch.posterior_variance).sqrt() * z
    assert torch.allclose(out, eq6, atol=1e-4)
    clipped = p_sample(sch, eps, a_k, torch.zeros(64, dtype=torch.long), noise=z)   # last step: x0 clipped
    assert clipped.abs().max().item() <= 1.0
    with pytest.raises(ValueError):
        p_sample(sch, eps, a_k, torch.full((64,), 100), noise=z)


# ---------------------------------------------------------------------------------------------- the U-Net

@pytest.mark.parametrize("B,H,dof,down_dims", [(3, 4, 2, (8, 16)), (5, 20, 3, (8, 16, 32)),
                                               (2, 16, 6, (8, 16, 32)), (1, 7, 1, (8,))])
def test_unet_output_has_the_chunk_shape(B, H, dof, down_dims):
    """H = 20 with two halvings (20 -> 10 -> 5) and H = 7 with none (one level) are fine."""
    policy = DiffusionPolicy(PolicyConfig(obs_dim=2 * dof + 1, dof=dof, horizon=H, n_act=1, K=10,
                                          down_dims=down_dims, n_groups=4, step_embed_dim=8))
    nn.init.normal_(policy.net.final[-1].weight)                      # not the zero output
    a = torch.randn(B, H, dof)
    eps = policy.predict_eps(a, torch.arange(B) % 10, torch.randn(B, policy.cfg.cond_input_dim), use_ema=False)
    assert eps.shape == (B, H, dof) and torch.isfinite(eps).all() and eps.abs().max() > 0


@pytest.mark.parametrize("network", [dict(down_dims=(8, 16, 32), horizon=8),
                                     dict(network="mlp", horizon=7, mlp_width=32, mlp_blocks=2)])
def test_eps_theta_is_film_of_the_step_and_observation_features(network):
    """eps_theta(a_k, k | o) = body(a_k, every block's film(Mish([step features of k, encode(o)]))), both networks
    (the MLP has no divisibility rule on H); the step and the observation both enter. Fails if forward drops or
    swaps a part of the condition, or hands the blocks another layout of the FiLM row."""
    policy = tiny_policy(K=20, **network)
    net, H = policy.net, policy.cfg.horizon
    gen = torch.Generator().manual_seed(0)
    for p in net.parameters():                                        # the zero output would hide a mistake
        p.data = torch.randn(p.shape, generator=gen) * 0.3
    obs_norm = policy.normalize_obs(torch.randn(6, 4, generator=gen))
    k = torch.tensor([0, 3, 19, 7, 7, 12])
    cond = nn.functional.mish(torch.cat([net.step_features(k), obs_norm], dim=1))   # 'flat': the features as they are
    film = torch.cat([block.film(cond) for block in net.residual_blocks()], dim=1)
    assert film.shape == (6, net.film_size)
    a = torch.randn(6, H, 2, generator=gen)
    eps = policy.predict_eps(a, k, policy.encode(obs_norm, use_ema=False), use_ema=False)
    assert eps.shape == (6, H, 2) and torch.equal(eps, net.body(a, film))
    # the step and the observation enter: another step, another observation, another prediction
    assert not torch.allclose(eps, policy.predict_eps(a, (k + 1) % 20, obs_norm, use_ema=False))
    assert not torch.allclose(eps, policy.predict_eps(a, k, obs_norm.flip(0), use_ema=False))


def test_step_embedding_is_the_sinusoid_of_k_at_geometric_frequencies():
    """step_embedding(k, dim) = [sin(k w_i), cos(k w_i)], w_i = 10000^(-i / (dim / 2)) (Vaswani et al.), by hand.
    Fails if the angle divides by the frequency, or sin and cos swap halves."""
    k, dim = torch.tensor([0, 1, 7, 99]), 8
    w = 10_000.0 ** (-np.arange(dim // 2) / (dim // 2))
    angles = k.numpy()[:, None] * w[None, :]
    want = np.concatenate([np.sin(angles), np.cos(angles)], axis=1)
    np.testing.assert_allclose(step_embedding(k, dim).numpy(), want, atol=1e-5)


@pytest.mark.parametrize("network,blocks", [("unet", 8), ("mlp", 2)])
def test_untrained_net_predicts_zero_noise(network, blocks):
    policy = tiny_policy(obs_dim=5, network=network, mlp_width=32, mlp_blocks=2)
    assert type(policy.net).__name__ == {"unet": "ConditionalUnet1D", "mlp": "ResidualMLP"}[network]
    assert len(list(policy.net.residual_blocks())) == blocks          # U-Net (16, 32): 2 x 2 down, 2 mid, 2 up
    eps = policy.predict_eps(torch.randn(16, 4, 2), torch.randint(0, 50, (16,)), torch.randn(16, 5 + 2))
    assert torch.equal(eps, torch.zeros(16, 4, 2))                    # zero output layer: a stable start


@pytest.mark.parametrize("overrides,match", [
    (dict(down_dims=(12, 24)), "multiples of n_groups=8"),            # GroupNorm(8, 12) is impossible
    (dict(down_dims=()), "non-empty"),
    (dict(down_dims=(64, 128, 256), horizon=18), re.escape("divisible by 2**(len(down_dims) - 1) = 4")),
    (dict(kernel_size=4), "kernel_size must be odd"),
    (dict(n_groups=0), "n_groups, .* must be positive ints"),
    (dict(step_embed_dim=7), "step_embed_dim must be even"),
    (dict(n_act=17), "n_act must be <= horizon"),
    (dict(obs_dim=3), re.escape("(q_t, q_t-1), 2 * dof = 4")),     # no room for the two joint readings
    (dict(network="transformer"), "network must be one of"),
    (dict(network="mlp", mlp_width=0), "mlp_width, mlp_blocks must be positive ints"),
])
def test_bad_configs_raise(overrides, match):
    with pytest.raises(ValueError, match=match):
        PolicyConfig(**{"obs_dim": 4, "dof": 2, "horizon": 16, "n_act": 2, "K": 10, **overrides})


# ---------------------------------------------------------------------------------------------- policy

@pytest.mark.slow
def test_two_mode_toy_policy_keeps_both_modes(toy_trained):
    obs = np.zeros((400, 4), dtype=np.float32)                        # at rest at the origin
    chunks = toy_trained.sample(obs, generator=torch.Generator().manual_seed(0))
    assert chunks.shape == (400, 4, 2) and chunks.dtype == np.float64
    # From the origin the data chunks are ±(0.5, 0.5) * t / H for t = 1..H.
    mode = 0.5 * np.arange(1, 5)[:, None] / 4 * np.ones((1, 2))          # (H, 2)
    up = chunks[:, -1].sum(1) > 0
    assert 0.3 < up.mean() < 0.7, f"both modes must be sampled, got {up.mean():.2f} up-right"
    err = np.where(up[:, None, None], chunks - mode, chunks + mode)
    worst = np.abs(err).max(axis=(1, 2))                              # (400,) each sample's largest error
    # the typical sample (the mean hangs on the few between the modes, and so on the last bits of the training)
    assert np.median(worst) < 0.03, f"samples must stay near the data modes, median error {np.median(worst):.3f}"


@pytest.mark.slow
def test_batched_sampling_equals_looped(toy_trained):
    obs = np.random.default_rng(1).uniform(-1, 1, (3, 4)).astype(np.float32)
    batched = toy_trained.sample(obs, generator=torch.Generator().manual_seed(5))
    gen = torch.Generator().manual_seed(5)
    looped = np.concatenate([toy_trained.sample(obs[i:i + 1], generator=gen) for i in range(3)])
    assert np.allclose(batched, looped, atol=1e-5)


def test_normalizer_round_trip_and_constant_dims():
    policy = tiny_policy(obs_dim=5)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(100, 5)).astype(np.float32)
    obs[:, 4] = 5.0                                                       # a constant dimension
    acts = rng.uniform(-2, 3, size=(100, 4, 2))
    policy.fit_normalizer(obs, acts)
    o = policy.normalize_obs(torch.as_tensor(obs))
    assert torch.isfinite(o).all() and torch.all(o[:, 4] == 0)
    assert o[:, 0].min().item() == pytest.approx(-1, abs=1e-5) and o[:, 0].max().item() == pytest.approx(1, abs=1e-5)
    a, o_raw = torch.as_tensor(acts, dtype=torch.float32), torch.as_tensor(obs)
    an = policy.normalize_actions(a, o_raw)
    assert an.min().item() == pytest.approx(-1, abs=1e-5) and an.max().item() == pytest.approx(1, abs=1e-5)
    assert torch.allclose(policy.unnormalize_actions(an, o_raw), a, atol=1e-5)


def constant_velocity_data(n, H=4, seed=0):
    """obs = (q_t, q_{t-1}) for a 2-joint arm; the chunk keeps the velocity: a_{t+j} = q_t + (j + 1) v."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-3, 3, (n, 2))
    v = rng.uniform(-0.05, 0.05, (n, 2))
    obs = np.concatenate([q, q - v], axis=1).astype(np.float32)
    chunks = q[:, None, :] + np.arange(1, H + 1)[None, :, None] * v[:, None, :]
    return obs, chunks.astype(np.float32)


def test_normalizer_is_relative_to_q_and_adds_velocity():
    policy = tiny_policy()
    obs, chunks = constant_velocity_data(200)
    policy.fit_normalizer(obs, chunks)
    o, a = torch.as_tensor(obs), torch.as_tensor(chunks)
    an = policy.normalize_actions(a, o)
    # The motion from q_t spans at most 4 * 0.05 rad: it fills [-1, 1], not a sliver of the 6 rad joint range.
    assert an.min().item() == pytest.approx(-1, abs=1e-4) and an.max().item() == pytest.approx(1, abs=1e-4)
    assert torch.allclose(policy.unnormalize_actions(an, o), a, atol=1e-5)
    feats = policy.normalize_obs(o)
    assert feats.shape == (200, policy.cfg.cond_input_dim) == (200, 6)
    v = o[:, :2] - o[:, 2:]
    assert torch.allclose(feats[:, 4:], (v - policy.vel_center) / policy.vel_half, atol=1e-6)
    with pytest.raises(ValueError):
        policy.fit_normalizer(obs, chunks.reshape(-1, 2))                # chunks must pair with obs


@pytest.mark.slow
def test_policy_continues_the_velocity_precisely():
    """The velocity is an input and the chunk is learned relative to q_t: after a short training run the
    sampled chunk keeps the velocity to a small fraction of a step (velocities are up to 0.05 rad per step;
    measured 0.004 rad; absolute chunks, deleted, were ~70x less precise: 0.27 rad)."""
    obs, chunks = constant_velocity_data(2000, seed=1)
    test_obs, test_chunks = constant_velocity_data(200, seed=2)
    policy = tiny_policy()
    train(policy, obs, chunks, TrainConfig(steps=300, batch_size=128, lr=1e-2, warmup_steps=50, log_every=0))
    samples = policy.sample(test_obs, generator=torch.Generator().manual_seed(0))
    error = np.abs(samples - test_chunks).mean()
    assert error < 0.01, f"mean error {error:.4f} rad"


@pytest.mark.parametrize("bad", [np.zeros((4, 3)), np.zeros(4), np.full((4, 4), np.nan), np.full((4, 4), np.inf)])
def test_sample_rejects_bad_obs(bad):
    with pytest.raises(ValueError):
        tiny_policy().sample(bad)


def test_bad_inputs_raise():
    policy = tiny_policy()
    with pytest.raises(ValueError):
        policy.fit_normalizer(np.zeros((5, 4)), np.zeros((5, 3, 2)))     # wrong horizon
    with pytest.raises(ValueError):
        policy.fit_normalizer(np.zeros((5, 4)), np.full((5, 4, 2), np.nan))
    with pytest.raises(ValueError, match=re.escape("aug_fraction in [0, 1]")):
        TrainConfig(aug_fraction=1.5)
    for bad, rule in ((dict(steps=-1), "needs steps >= 0"), (dict(batch_size=0), "batch_size >= 1"),
                      (dict(warmup_steps=-1), "warmup_steps >= 0"), (dict(ema_decay=1.0), "ema_decay in")):
        with pytest.raises(ValueError, match=re.escape(rule)):
            TrainConfig(**bad)


# ---------------------------------------------------------------------------------------------- dataset

def test_chunk_dataset_label_rule():
    T, H = 10, 3
    expert = np.array([1, 1, 1, 1, 0, 1, 1, 1, 1, 1], dtype=bool)
    action = np.arange(T, dtype=np.float64)[:, None] * np.array([[1.0, -1.0]])   # (T, 2)
    ep = {"obs": np.arange(T, dtype=np.float32)[:, None], "q": action, "action": action,
          "expert": expert, "seed": 0}
    # Valid starts: 0, 1 (steps 0..3 expert), then 5, 6, 7 (full), 8, 9 (end of episode, padded).
    assert np.array_equal(np.nonzero(label_mask(expert, H))[0], [0, 1, 5, 6, 7, 8, 9])
    obs, chunks = chunk_dataset([ep, ep], H)
    assert obs.shape == (14, 1) and chunks.shape == (14, H, 2)
    assert obs.dtype == np.float32 and chunks.dtype == np.float32
    assert np.array_equal(obs[:7, 0], [0, 1, 5, 6, 7, 8, 9])
    assert np.array_equal(chunks[2, :, 0], [5, 6, 7])
    assert np.array_equal(chunks[5, :, 0], [8, 9, 9]), "past the end the last action repeats"
    assert np.array_equal(chunks[6, :, 1], [-9, -9, -9])
    # An episode ending with a non-expert step has no padded labels there.
    ep2 = dict(ep, expert=np.array([1] * 9 + [0], dtype=bool))
    assert np.array_equal(np.nonzero(label_mask(ep2["expert"], H))[0], [0, 1, 2, 3, 4, 5, 6])


@pytest.mark.parametrize("length,kept", [(2, []), (3, [(2, 5)]), (4, [(2, 6)])])
def test_an_intervention_of_exactly_H_steps_labels_one_chunk_and_one_step_shorter_none(length, kept):
    """Sec. IV-C at its boundary, H = 3, inside an episode: an intervention of H - 1 steps is discarded, one of H
    steps is a run with one label (its start), H + 1 steps two. Fails if the rule drops the run of exactly H (> H
    for >= H) or keeps a run one step short."""
    H = 3
    expert = np.zeros(10, dtype=bool)
    expert[2:2 + length] = True
    assert expert_runs(expert, H) == kept
    assert np.array_equal(np.flatnonzero(label_mask(expert, H)), np.arange(2, 2 + max(0, length - H + 1)))


def test_every_consumer_of_the_label_rule_agrees_on_random_masks():
    """One rule (diffusion.expert_runs / label_mask); calibrate, relabel and dagger derive from it."""
    import calibrate
    import dagger
    import relabel
    rng = np.random.default_rng(0)
    for _ in range(300):
        T, H = int(rng.integers(1, 40)), int(rng.integers(1, 8))
        expert = rng.random(T) < rng.choice([0.5, 0.8, 0.95])
        if rng.random() < 0.1:
            expert[:] = True                                   # a (possibly short) demonstration
        runs = expert_runs(expert, H)
        mask = label_mask(expert, H)
        # the rule itself, step by step: t is a label iff it lies in a run that teaches (>= H steps, or the
        # whole episode) and its chunk stays in the run or the run ends the episode
        for t in range(T):
            inside = [(s, e) for s, e in runs if s <= t < e]
            assert mask[t] == bool(inside and (t + H <= inside[0][1] or inside[0][1] == T)), (expert, H, t)
        t, seg_end = relabel.paper_label_steps(expert, H)
        assert np.array_equal(t, np.flatnonzero(mask))
        assert all(any(s <= ti < e == se for s, e in runs) for ti, se in zip(t, seg_end))
        kept = np.zeros(T, dtype=bool)                         # what the collection keeps: the runs themselves
        for s, e in expert_runs(expert, H):  # the loop's label_rule by default (dagger.collect_interventions)
            kept[s:e] = True
        assert np.array_equal(np.flatnonzero(kept), [i for s, e in runs for i in range(s, e)])
        assert np.array_equal(label_mask(kept, H), mask)       # dropping first changes no label
    # a short run that ends the episode is discarded (it is not the whole episode) ...
    assert not label_mask(np.array([1, 1, 1, 1, 0, 1, 1], bool), 3)[5:].any()
    # ... and a demonstration shorter than H is kept, padded
    assert label_mask(np.ones(2, bool), 3).all()


# ---------------------------------------------------------------------------------------------- training

def test_lr_schedule_warmup_and_cosine():
    cfg = TrainConfig(steps=1000, lr=1e-3, warmup_steps=100)
    assert lr_at(0, cfg) == pytest.approx(1e-5)
    assert lr_at(99, cfg) == pytest.approx(1e-3)
    assert lr_at(550, cfg) == pytest.approx(0.5e-3)
    assert lr_at(1000, cfg) == pytest.approx(0.0, abs=1e-12)


def random_rows(n, rng):
    """A co-training sampler: n rows drawn from the training stream rng (obs (n, 4), chunks (n, 4, 2))."""
    obs = rng.uniform(-1, 1, (n, 4)).astype(np.float32)
    return obs, np.repeat(obs[:, None, :2], 4, axis=1)


@pytest.mark.parametrize("kernels", [False, True])
@pytest.mark.parametrize("network", ["mlp", "unet"])
def test_the_same_seed_trains_bit_identical_losses_and_weights(network, kernels):
    """Two train() runs of one config: every step's loss and every weight (EMA too) equal to the bit, with torch's
    own layers and with experiment/cpu_kernels.py's (the run's on most CPUs): the fused AdamW and the kernels are
    deterministic on one thread. torch.compile is not used (its compile time would cost more than it saves in
    python dagger.py: benchmarks/HISTORY.md)."""
    obs, chunks = toy_two_mode_data(300, H=4, seed=5)
    cfg = TrainConfig(steps=25, batch_size=48, warmup_steps=5, log_every=0, seed=3, aug_fraction=0.25,
                      obs_noise=0.05)

    def run(seed):
        policy = tiny_policy(network=network, mlp_width=64, mlp_blocks=2)
        for net in (policy.net, policy.ema_net) if kernels else ():
            cpu_kernels.swap_in(net)
        losses, loss = [], policy.loss
        policy.loss = lambda *args, **kwargs: losses.append(loss(*args, **kwargs)) or losses[-1]
        train(policy, obs, chunks, TrainConfig(**{**cfg.__dict__, "seed": seed}), sampler=random_rows)
        return torch.stack(losses).detach(), policy.state_dict()

    losses, weights = run(3)
    losses_again, weights_again = run(3)
    assert len(losses) == cfg.steps and torch.equal(losses, losses_again)
    assert weights.keys() == weights_again.keys()
    assert all(torch.equal(weights[key], weights_again[key]) for key in weights)
    other_losses, _ = run(4)                                        # the check can fail: another seed differs
    assert not torch.equal(losses, other_losses)


def test_update_ema_is_the_warmed_up_exponential_average():
    """ema <- d ema + (1 - d) net with d = min(decay, (1 + step) / (10 + step)): 0.1 at step 0, decay later."""
    from diffusion import update_ema
    policy = tiny_policy(network="mlp", mlp_width=8, mlp_blocks=1)
    with torch.no_grad():
        for p in policy.net.parameters():
            p.add_(1.0)                                                # the live weights move away from the EMA's
    for step, decay, d in ((0, 0.999, 0.1), (10_000, 0.9, 0.9)):
        ema_before = [e.clone() for e in policy.ema_net.parameters()]
        update_ema(policy, step, decay)
        for e, before, p in zip(policy.ema_net.parameters(), ema_before, policy.net.parameters()):
            assert torch.allclose(e, d * before + (1 - d) * p, atol=1e-6)


def test_training_lowers_loss_and_logs_progress():
    obs, chunks = toy_two_mode_data(500, H=4, seed=2)
    lines = []
    policy = tiny_policy()
    train(policy, obs, chunks, TrainConfig(steps=200, batch_size=64, warmup_steps=20, log_every=100,
                                           log_seconds=1e9), log=lines.append)   # lines by steps only
    assert len(lines) == 2 and lines[-1].startswith("step 200/200 | loss ")
    assert "steps/s" in lines[0] and "s left" in lines[0]
    first, last = (float(line.split("| loss ")[1].split(" ")[0]) for line in lines)
    assert last < first < 1.2


def test_observation_noise_is_in_raw_units_per_entry_and_leaves_labels_alone():
    obs, chunks = constant_velocity_data(64, seed=2)                  # a distinct label per row
    policy = tiny_policy()
    seen = []
    real_loss = policy.loss
    policy.loss = lambda o, a, generator=None, mask=None: (seen.append((o.detach().clone(), a.detach().clone())),
                                                real_loss(o, a, generator))[1]
    # noise of std 0.5 on the second entry only (raw units), none on the first
    train(policy, obs, chunks, TrainConfig(steps=3, batch_size=16, warmup_steps=1, log_every=0,
                                           obs_noise=(0.0, 0.5, 0.0, 0.0)))
    clean_obs = policy.normalize_obs(torch.as_tensor(obs))
    clean_chunks = policy.normalize_actions(torch.as_tensor(chunks), torch.as_tensor(obs))
    for o, a in seen:
        # each row is a dataset row: its first entry and its label are exactly the clean ones ...
        rows = [int(torch.argmin((clean_chunks - a_row).abs().sum(dim=(1, 2)))) for a_row in a]
        assert torch.equal(a, clean_chunks[rows])
        assert torch.allclose(o[:, 0], clean_obs[rows, 0])
        # ... its second entry moved by noise of std 0.5 raw = 0.5 / half-range normalized
        moved = (o[:, 1] - clean_obs[rows, 1]) * policy.obs_half[1]
        assert 0.2 < float(moved.std()) < 1.0
    with pytest.raises(ValueError, match="obs_noise"):
        TrainConfig(obs_noise=-0.1)
    with pytest.raises(ValueError, match="obs_noise"):
        TrainConfig(obs_noise=[[0.1]])


def test_masked_loss_ignores_masked_steps_and_none_is_the_plain_loss():
    policy = tiny_policy()
    with torch.no_grad():  # an untrained net predicts zero noise, which would ignore the chunk entirely
        weights = torch.Generator().manual_seed(3)
        for p in policy.net.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=weights))
    g = lambda: torch.Generator().manual_seed(0)
    obs = torch.randn(8, 6, generator=torch.Generator().manual_seed(1))   # normalized: 4 obs entries, velocity
    chunk = torch.randn(8, 4, 2, generator=torch.Generator().manual_seed(2))
    # mask=None: exactly the old loss, DDPM's plain mean over every entry
    k = torch.randint(0, policy.cfg.K, (8,), generator=g())
    gen = g()
    torch.randint(0, policy.cfg.K, (8,), generator=gen)
    eps = torch.randn(chunk.shape, generator=gen)
    old = nn.functional.mse_loss(policy.predict_eps(q_sample(policy.schedule, chunk, k, eps), k, obs, use_ema=False), eps)
    assert policy.loss(obs, chunk, generator=g()).item() == old.item()
    # an all-True mask gives the same number (up to rounding)
    full = torch.ones(8, 4, dtype=torch.bool)
    assert abs(policy.loss(obs, chunk, generator=g(), mask=full).item() - old.item()) < 1e-6
    # masked steps do not count: with a step-local stand-in for the network (the U-Net's convolutions
    # would carry a change of one step into its neighbours' predictions), changing the chunk on
    # masked steps leaves the loss unchanged
    policy.predict_eps = lambda a_k, k, obs_norm, use_ema=False: 0.3 * a_k
    mask = full.clone()
    mask[:, 2:] = False
    mask[0] = True
    changed = chunk.clone()
    changed[1:, 2:] += 5.0
    a = policy.loss(obs, chunk, generator=g(), mask=mask).item()
    assert policy.loss(obs, changed, generator=g(), mask=mask).item() == a
    assert policy.loss(obs, changed, generator=g()).item() != policy.loss(obs, chunk, generator=g()).item()
    plain = policy.loss(obs, chunk, generator=g()).item()
    assert a != plain


def test_train_accepts_a_sampler_with_a_mask():
    obs = np.random.default_rng(0).normal(size=(32, 4)).astype(np.float32)
    chunks = np.random.default_rng(1).normal(size=(32, 4, 2)).astype(np.float32)
    seen = []

    def sampler(n, rng):
        mask = np.ones((n, 4), bool)
        mask[:, 3] = False
        seen.append(n)
        return obs[:n], chunks[:n], mask

    cfg = TrainConfig(steps=3, batch_size=8, aug_fraction=0.5, log_every=0)
    train(tiny_policy(), obs, chunks, cfg, sampler=sampler)
    assert seen == [4, 4, 4]


# ---------------------------------------------------------------------------------------------- the MLP option

def test_mlp_policy_learns_the_two_mode_toy_and_round_trips(tmp_path):
    obs, chunks = toy_two_mode_data(2000, H=4, seed=0)
    policy = tiny_policy(network="mlp", mlp_width=64, mlp_blocks=2)
    train(policy, obs, chunks, TrainConfig(steps=400, batch_size=128, lr=3e-3, warmup_steps=50, log_every=0))
    last = policy.sample(np.zeros((300, 4), np.float32), generator=torch.Generator().manual_seed(0))[:, -1]
    up = last.sum(axis=1) > 0
    assert 0.2 < up.mean() < 0.8                                       # both modes kept
    assert np.allclose(last[up].mean(0), [0.5, 0.5], atol=0.1) and np.allclose(last[~up].mean(0), [-0.5, -0.5], atol=0.1)
    checkpoints.save_policy(policy, str(tmp_path / "mlp.pt"))
    loaded = checkpoints.load_policy(str(tmp_path / "mlp.pt"))
    assert loaded.cfg.network == "mlp"
    assert all(torch.equal(v, loaded.state_dict()[k]) for k, v in policy.state_dict().items())


# ---------------------------------------------------------------------------------------------- continuation

def test_schedule_steps_sets_where_the_cosine_ends():
    cfg = TrainConfig(steps=600, schedule_steps=1100, lr=1e-3, warmup_steps=100)
    assert lr_at(600, cfg) == pytest.approx(0.5e-3)                  # half way through the cosine
    assert lr_at(1100, cfg) == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="schedule_steps"):
        TrainConfig(steps=600, schedule_steps=500)


def test_continuing_a_schedule_goes_on_from_the_state_on_checkpoint_handed_over():
    """train(start=pi_0's state) goes on from pi_0's AdamW state and step along the one schedule: with both
    random streams it is the uninterrupted run bit for bit (a resumed run); with only the step and optimizer
    (fine-tuning pi_0) another run from the same point, closer to the one-piece run than a fresh optimizer's."""
    obs, chunks = toy_two_mode_data(300, H=4, seed=1)
    base = dict(batch_size=32, warmup_steps=5, log_every=0, seed=3, schedule_steps=60)
    states = []
    pi0 = train(tiny_policy(), obs, chunks, TrainConfig(steps=30, checkpoint_steps=(20, 30), **base),
                on_checkpoint=states.append)
    assert [s["step"] for s in states] == [20, 30]
    weights = copy.deepcopy(pi0.state_dict())
    whole = train(tiny_policy(), obs, chunks, TrainConfig(steps=60, **base)).state_dict()

    def from_pi0(**start_keys):
        policy = tiny_policy()
        policy.load_state_dict(weights)
        return train(policy, obs, chunks, TrainConfig(steps=60, **base), start=start_keys or None).state_dict()

    assert all(torch.equal(whole[k], v) for k, v in from_pi0(**states[1]).items())       # resumed: bit for bit
    cont = from_pi0(step=30, optimizer=states[1]["optimizer"])          # fine-tuned: its own streams
    restart = train(tiny_policy(), obs, chunks, TrainConfig(steps=30, **{**base, "schedule_steps": 0})).state_dict()
    key = "net.down.0.0.conv1.0.weight"
    assert not torch.equal(weights[key], cont[key]) and not torch.equal(whole[key], cont[key])
    d_cont = sum(float((cont[k] - whole[k]).abs().sum()) for k in whole if k.startswith("net."))
    d_restart = sum(float((restart[k] - whole[k]).abs().sum()) for k in whole if k.startswith("net."))
    assert d_cont < 0.5 * d_restart
