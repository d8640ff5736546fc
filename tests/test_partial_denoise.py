"""Tests of partial_denoise.py: the formulas, the index convention, beta = 0 / 1, Eq. (7), Fig. 3."""

import math

import numpy as np
import pytest
import torch

from diffusion import DiffusionPolicy, PolicyConfig, TrainConfig, toy_two_mode_data, train
from partial_denoise import (lerp_blend, noise_fraction, partial_denoise, plot_partial_denoising,
                             sdedit_bound, switch_step)




class StubPolicy(DiffusionPolicy):
    """A DiffusionPolicy whose noise prediction is a given function eps_fn(a_k, k (B,), policy): a test double
    with a known noise prediction. The normalizer is the identity, so joint units = normalized units."""

    def __init__(self, eps_fn, H=4, dof=2, K=100):
        super().__init__(PolicyConfig(obs_dim=2 * dof, dof=dof, horizon=H, n_act=1, K=K, down_dims=(4,), n_groups=4,
                                      step_embed_dim=4))
        self.eps_fn = eps_fn

    def encode(self, obs_norm, use_ema=True):
        return obs_norm

    def predict_eps(self, a_k_norm, k, features, use_ema=True):
        if not torch.is_tensor(k):
            k = torch.full((a_k_norm.shape[0],), int(k))
        return self.eps_fn(a_k_norm, k, self)


def zero_eps(a, k, policy):
    return torch.zeros_like(a)


def gaussian_prior_eps(mean, std, bound):
    """The exact noise prediction for actions ~ N(mean, std^2 I), scaled down where its norm exceeds `bound`:
    a model that pulls toward `mean` and whose prediction satisfies ||eps|| <= bound everywhere."""
    def eps_fn(a, k, policy):
        abar = policy.schedule.alphas_cumprod[k].view(-1, 1, 1)
        eps = (1 - abar).sqrt() * (a - abar.sqrt() * mean) / (abar * std ** 2 + 1 - abar)
        norm = eps.flatten(1).norm(dim=1).view(-1, 1, 1)
        return eps * torch.clamp(bound / norm, max=1.0)
    return eps_fn


def generator(seed=0):
    return torch.Generator().manual_seed(seed)


@pytest.fixture(scope="module")
def toy_policy():
    """Two-mode toy task (diffusion.toy_two_mode_data), trained for a few seconds."""
    obs, chunks = toy_two_mode_data(2000, H=4, seed=0)
    policy = DiffusionPolicy(PolicyConfig(obs_dim=4, dof=2, horizon=4, n_act=2, K=100, down_dims=(16, 32),
                                          n_groups=4, step_embed_dim=32))
    train(policy, obs, chunks, TrainConfig(steps=400, batch_size=128, lr=1e-2, warmup_steps=50, log_every=0))
    return policy


# ---------------------------------------------------------------------------------------------- formulas

def test_switch_step_rounds_to_nearest():
    assert switch_step(0.0, 100) == 0 and switch_step(1.0, 100) == 100
    assert switch_step(0.29, 100) == 29          # 0.29 * 100 = 28.999999999999996: floor would give 28
    assert switch_step(0.005, 100) == 1          # halves round up
    assert switch_step(0.3, 10) == 3
    grid = np.linspace(0, 1, 1001)
    k = switch_step(grid, 100)
    assert k.dtype == np.int64 and np.all(np.diff(k) >= 0) and np.all(np.abs(k - grid * 100) <= 0.5)


def test_noise_fraction_is_one_minus_alphabar_at_switch_step():
    from diffusion import make_schedule
    sch = make_schedule(100)
    assert noise_fraction(sch, 0.0) == 0.0
    for beta in (0.05, 0.3, 0.9, 1.0):
        k_sw = switch_step(beta, 100)
        # paper alphabar_{k_sw} = code alphas_cumprod[k_sw - 1]
        assert noise_fraction(sch, beta) == pytest.approx(1 - sch.alphas_cumprod[k_sw - 1].item(), rel=1e-6)
    s = noise_fraction(sch, np.linspace(0, 1, 21))
    assert np.all(np.diff(s) > 0) and s[-1] > 0.999999


def test_lerp_blend_eq3():
    a_pol, a_exp = np.array([[1.0, 2.0]]), np.array([[3.0, -2.0]])
    assert np.array_equal(lerp_blend(a_pol, a_exp, 0.0), a_exp)
    assert np.array_equal(lerp_blend(a_pol, a_exp, 1.0), a_pol)
    assert np.allclose(lerp_blend(a_pol, a_exp, 0.25), [[2.5, -1.0]])
    both = lerp_blend(np.zeros((2, 3, 2)), np.ones((2, 3, 2)), np.array([0.0, 0.5]))   # per-row beta
    assert np.allclose(both[0], 1.0) and np.allclose(both[1], 0.5)


def test_sdedit_bound_eq7():
    s2, bound, d, delta = 0.1, 3.0, 8, 0.05
    expected = s2 * (bound * s2 + d + 2 * math.sqrt(-d * math.log(delta)) - 2 * math.log(delta))
    assert sdedit_bound(s2, bound, d, delta) == pytest.approx(expected)
    assert sdedit_bound(0.0, bound, d, delta) == 0.0
    with pytest.raises(ValueError):
        sdedit_bound(0.1, 3.0, 8, 1.5)


@pytest.mark.parametrize("bad", [-0.1, 1.1, float("nan"), float("inf")])
def test_bad_beta_raises(bad):
    policy = StubPolicy(zero_eps)
    with pytest.raises(ValueError):
        partial_denoise(policy, np.zeros((2, 4)), np.zeros((2, 4, 2)), bad)
    with pytest.raises(ValueError):
        switch_step(bad, 100)
    with pytest.raises(ValueError):
        lerp_blend(np.zeros(2), np.zeros(2), bad)


def test_bad_shapes_raise():
    policy = StubPolicy(zero_eps)
    with pytest.raises(ValueError):
        partial_denoise(policy, np.zeros((2, 4)), np.zeros((2, 3, 2)), 0.5)          # wrong horizon
    with pytest.raises(ValueError):
        partial_denoise(policy, np.zeros((2, 4)), np.zeros((3, 4, 2)), 0.5)          # batch mismatch
    with pytest.raises(ValueError):
        partial_denoise(policy, np.zeros((2, 4)), np.zeros((2, 4, 2)), [0.5, 0.5, 0.5])
    with pytest.raises(ValueError):
        partial_denoise(policy, np.zeros((2, 4)), np.full((2, 4, 2), np.nan), 0.5)


# ---------------------------------------------------------------------------------------------- convention

def test_first_reverse_step_gets_the_noise_level_it_expects():
    """The chunk enters the first network call at exactly the level that call is told (no off-by-one):
    paper level k_sw = code index k_sw - 1, and exactly k_sw reverse steps run."""
    calls = []

    def recording_eps(a, k, policy):
        calls.append((k.clone(), a.clone()))
        return torch.zeros_like(a)

    policy = StubPolicy(recording_eps)
    n, a_star = 20_000, 0.3
    beta = 0.03                                                  # k_sw = 3: small levels differ a lot
    k_sw = switch_step(beta, 100)
    partial_denoise(policy, np.zeros((n, 4)), np.full((n, 4, 2), a_star), beta, generator=generator())
    assert len(calls) == k_sw
    assert [int(k[0]) for k, _ in calls] == list(range(k_sw - 1, -1, -1))
    k_first, a_first = calls[0]
    abar = policy.schedule.alphas_cumprod[k_first[0]].item()    # what the network is told
    assert a_first.mean().item() == pytest.approx(math.sqrt(abar) * a_star, abs=3e-4)
    assert a_first.var().item() == pytest.approx(1 - abar, rel=0.03)
    wrong = policy.schedule.alphas_cumprod[k_first[0] - 1].item()   # one level less noise
    assert abs(a_first.var().item() - (1 - wrong)) > 0.2 * (1 - abar)


@pytest.mark.parametrize("beta", [0.03, 0.1])
def test_error_variance_matches_closed_form_for_zero_noise_prediction(beta):
    """With eps_theta = 0 every step is a_{k-1} = a_k / sqrt(alpha_k) + sigma_k z, so the output error has
    the per-dimension variance (1 - abar_n) / abar_n + sum_{j=2..n} beta~_j / abar_{j-1}, n = k_sw
    (paper indices): the forward noise plus the reverse steps' own noise."""
    policy = StubPolicy(zero_eps)
    sch = policy.schedule
    n_rows = 20_000
    out = partial_denoise(policy, np.zeros((n_rows, 4)), np.zeros((n_rows, 4, 2)), beta, generator=generator(1))
    n = switch_step(beta, 100)
    abar = np.concatenate([[1.0], sch.alphas_cumprod.double().numpy()])          # paper k = 0..K
    post_var = np.concatenate([[0.0], sch.posterior_variance.double().numpy()])  # paper k = 0..K
    expected = (1 - abar[n]) / abar[n] + sum(post_var[j] / abar[j - 1] for j in range(2, n + 1))
    assert out.var() == pytest.approx(expected, rel=0.03)
    assert abs(out.mean()) < 0.01


# ---------------------------------------------------------------------------------------------- beta = 0, 1

@pytest.mark.slow
def test_beta_zero_returns_expert_chunk(toy_policy):
    expert = np.random.default_rng(0).uniform(-1, 1, (16, 4, 2))
    obs = np.zeros((16, 4), dtype=np.float32)
    out = partial_denoise(toy_policy, obs, expert, 0.0, generator=generator())
    assert np.array_equal(out, expert)
    out = partial_denoise(toy_policy, obs, expert, 0.004, generator=generator())   # rounds to k_sw = 0
    assert np.array_equal(out, expert)


@pytest.mark.slow
def test_beta_one_is_unguided_sampling(toy_policy):
    n = 400
    obs = np.zeros((n, 4), dtype=np.float32)
    expert = np.repeat(np.array([[[0.3, -0.3]]]), n, axis=0).repeat(4, axis=1)     # off both modes
    guided = partial_denoise(toy_policy, obs, expert, 1.0, generator=generator(7))
    plain = toy_policy.sample(obs, generator=generator(7))
    # Same random draws; the only difference is the sqrt(alphabar_K) a* ~ 1e-3 a* left in the start.
    assert np.abs(guided - plain).max() < 0.02
    other = partial_denoise(toy_policy, obs, expert, 1.0, generator=generator(8))
    assert np.abs(other - plain).max() > 0.1, "a different generator gives different samples"
    up_guided, up_plain = (guided[:, -1].sum(1) > 0).mean(), (plain[:, -1].sum(1) > 0).mean()
    assert abs(up_guided - up_plain) < 0.02 and 0.3 < up_plain < 0.7


@pytest.mark.slow
def test_distance_to_expert_grows_with_beta(toy_policy):
    n = 300
    obs = np.zeros((n, 4), dtype=np.float32)
    t = np.arange(1, 5)[:, None] / 4
    expert = np.repeat((0.5 * t * np.array([[1.0, 0.4]]))[None], n, axis=0)      # bends off the (+, +) mode
    dists = []
    for beta in (0.0, 0.05, 0.15, 0.3, 0.6, 1.0):
        a_hat = partial_denoise(toy_policy, obs, expert, beta, generator=generator(2))
        dists.append(np.linalg.norm((a_hat - expert).reshape(n, -1), axis=1).mean())
    assert dists[0] == 0.0
    assert np.all(np.diff(dists) > 0), f"mean distance must grow with beta, got {np.round(dists, 3)}"


@pytest.mark.slow
def test_batched_equals_looped(toy_policy):
    rng = np.random.default_rng(3)
    obs = rng.uniform(-1, 1, (4, 4)).astype(np.float32)  # (q_t, q_{t-1}) of the toy's 2 joints
    expert = rng.uniform(-1, 1, (4, 4, 2))
    betas = np.array([0.0, 0.2, 0.5, 1.0])
    batched = partial_denoise(toy_policy, obs, expert, betas, generator=generator(4))
    gen = generator(4)
    looped = np.concatenate([partial_denoise(toy_policy, obs[i:i + 1], expert[i:i + 1], betas[i], generator=gen)
                             for i in range(4)])
    assert np.allclose(batched, looped, atol=1e-5)
    assert np.array_equal(batched[0], expert[0])


# ---------------------------------------------------------------------------------------------- Eq. (7)

def test_eq7_holds_for_a_bounded_noise_prediction():
    """A model whose noise prediction is bounded (||eps|| <= 3 by construction) and whose prior sits near
    the expert chunk: ||a* - a_hat||^2 stays within Eq. (7) with probability >= 1 - delta at every beta."""
    H, dof, bound, delta, n = 4, 2, 3.0, 0.05, 4000
    d = H * dof
    a_star = np.full((n, H, dof), 0.2)
    policy = StubPolicy(gaussian_prior_eps(mean=torch.tensor(0.4), std=0.3, bound=bound), H=H, dof=dof)
    for beta in (0.05, 0.1, 0.2, 0.3):            # beyond ~0.3 the bound exceeds the box [-1, 1]^d's diameter
        a_hat = partial_denoise(policy, np.zeros((n, 4)), a_star, beta, generator=generator(5))
        err = ((a_star - a_hat) ** 2).reshape(n, -1).sum(1)
        limit = sdedit_bound(noise_fraction(policy.schedule, beta), bound, d, delta)
        assert (err <= limit).mean() >= 1 - delta, f"beta={beta}: {(err <= limit).mean():.3f} within Eq. (7)"
        assert err.mean() > 0.05 * limit, "the check is not vacuous: errors are on the bound's scale"


def test_eq7_counts_only_the_forward_noise():
    """The caveat documented at sdedit_bound: with eps_theta = 0 (bound 0) the reverse steps add their own
    noise (previous test: error variance ~1.9 sigma^2 per dimension at beta = 0.2), so Eq. (7), whose
    leading term is the chi-square tail of the forward noise sigma^2 alone, is exceeded more often than delta."""
    n, delta = 4000, 0.05
    policy = StubPolicy(zero_eps)
    a_hat = partial_denoise(policy, np.zeros((n, 4)), np.zeros((n, 4, 2)), 0.2, generator=generator(6))
    err = (a_hat ** 2).reshape(n, -1).sum(1)
    within = (err <= sdedit_bound(noise_fraction(policy.schedule, 0.2), 0.0, 8, delta)).mean()
    assert 0.8 < within < 1 - delta


# ---------------------------------------------------------------------------------------------- Fig. 3

def test_plot_partial_denoising_writes_figure(tmp_path):
    envs = pytest.importorskip("envs")
    env = envs.make_env("planar")
    obs, info = env.reset(seed=int(env.train_seeds(1)[0]))
    q = info["q"]
    policy = DiffusionPolicy(PolicyConfig(obs_dim=env.obs_dim, dof=env.dof, horizon=16, n_act=8, K=20,
                                          down_dims=(8, 16), n_groups=4, step_embed_dim=16))
    expert = q[None, :] + np.linspace(0.02, 0.3, 16)[:, None] * np.array([[1.0, -0.5, 0.3]])   # (H, dof)
    policy.fit_normalizer(np.stack([obs, obs]), np.stack([expert, expert + 0.1]))
    # beta = 0 returns the expert chunk also through the normalization relative to q_t.
    assert np.array_equal(partial_denoise(policy, obs[None], expert[None], 0.0), expert[None])
    path = str(tmp_path / "fig3.png")
    plot_partial_denoising(env, policy, obs, expert, (0.1, 0.5), path, generator(), q=q, n_samples=3)
    with open(path, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"


def test_plot_partial_denoising_draws_the_3d_env_in_the_top_view(tmp_path):
    """Fig. 3 for EngineReach3D (dim 3): the same panels, end-effector paths projected on x, y (m)."""
    envs = pytest.importorskip("envs")
    pytest.importorskip("pybullet")
    from experiment import environments
    env = environments.make_env("engine3d")
    obs, info = env.reset(seed=int(env.train_seeds(1)[0]))
    q = info["q"]
    assert env.dim == 3 and env.dof == 6
    policy = DiffusionPolicy(PolicyConfig(obs_dim=env.obs_dim, dof=env.dof, horizon=16, n_act=8, K=10,
                                          down_dims=(8, 16), n_groups=4, step_embed_dim=16))
    expert = q[None, :] + np.linspace(0.02, 0.3, 16)[:, None] * np.array([[1.0, -0.5, 0.3, 0.2, 0.1, 0.0]])
    policy.fit_normalizer(np.stack([obs, obs]), np.stack([expert, expert + 0.1]))
    path = str(tmp_path / "fig3_engine3d.png")
    assert plot_partial_denoising(env, policy, obs, expert, (0.1, 0.5), path, generator(), q=q, n_samples=3) == path
    with open(path, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
