"""The image-observation variant (experiment/image_obs.py): the UR5 env 'engine3d_image' whose observation ends
with a camera image, the CNN ImageEncoder the policy reads it with, and how the variant reaches the core -- the
env factory the harness hands the loop, the encoder class the env names, the policy's config and checkpoint, the
augmentation's recorded images, the command line, worker processes, the run folder's retired config fields --
without a core function knowing images."""
import gzip
import json
import os
from dataclasses import dataclass, fields, replace

import numpy as np
import pytest
import torch

import dagger
import diffusion
import envs
from helpers import straight_line_episode  # tests/helpers.py
import relabel
from diffusion import DiffusionPolicy, PolicyConfig, TrainConfig, train
from experiment import checkpoints, cli, environments, profiles, report, run_folder, workers
from experiment import engine3d
from experiment.image_obs import EngineImageConfig, EngineReach3DImage, ImageEncoder

TINY_NET = dict(down_dims=(16, 32), n_groups=4, step_embed_dim=32)  # as tests/test_diffusion.py's
TINY = dagger.Config(name="tiny", n_demos=4, rounds=1, lineages=1, K=5, down_dims=(8, 16),
                     bc_steps=30, finetune_steps=12, batch_size=32, methods=("bc", "hg_dagger", "pooled"),
                     eval_scenarios=3, eval_repeats=1)


@pytest.fixture(scope="module")
def image_env():
    e = EngineReach3DImage()
    e.reset(seed=e.eval_seeds()[0])
    return e


def small_images(monkeypatch, size):
    """'engine3d_image<size>' in the harness's env factory: the variant's env with smaller images (in this process
    only: a run that uses it must not spawn workers)."""
    @dataclass
    class SmallImages(EngineImageConfig):
        image_size: int = size
    name = f"engine3d_image{size}"
    monkeypatch.setitem(environments.ENVIRONMENTS, name, (EngineReach3DImage, SmallImages))
    return name


# ---- the plug-in points ----------------------------------------------------------------------------------------
def test_the_variant_is_the_harness_env_factorys_and_the_core_holds_no_table_for_it():
    """Fails if the core grew a table a variant registers into again, or the variant's env stopped being the lever
    for what follows the paper's env (the unit, the table, the memory bound)."""
    assert environments.ENVIRONMENTS["engine3d_image"] == (EngineReach3DImage, EngineImageConfig)
    assert environments.OBS_ENCODERS["image_cnn"] is ImageEncoder is EngineReach3DImage().obs_encoder
    assert not hasattr(envs, "ENVIRONMENTS") and not hasattr(diffusion, "OBS_ENCODERS")
    with pytest.raises(ValueError, match="unknown env 'engine3d_image'"):
        envs.make_env("engine3d_image")  # the core makes only Table I's env
    assert issubclass(EngineReach3DImage, engine3d.EngineReach3D)
    assert environments.paper_env("engine3d_image") == "engine3d" and EngineReach3DImage().paper_env == "engine3d"
    assert environments.paper_median_step("engine3d_image") == environments.paper_median_step("engine3d") == 0.0166
    assert environments.paper_env("planar") == "planar" and environments.paper_env("mars") is None
    assert EngineReach3DImage.max_parallel == engine3d.EngineReach3D.max_parallel == 100
    assert not {"image_obs", "image_size"} & {f.name for f in fields(dagger.Config)}  # no Config field for it


def test_make_env_builds_the_image_env_with_config_fields():
    env = environments.make_env("engine3d_image", max_steps=50, image_size=24)
    assert isinstance(env, EngineReach3DImage) and env.max_steps == 50 and env.cfg.image_size == 24
    assert env.image_shape == (3, 24, 24) and env.obs_dim == 15 + 3 * 24 * 24
    assert env.obs_encoder is ImageEncoder and env.obs_encoder_args == {"shape": (3, 24, 24)}
    assert environments.make_env("engine3d_image").cfg.image_size == 32            # the variant's default
    plain = environments.make_env("engine3d")
    assert plain.obs_encoder is None and plain.obs_encoder_args == {} and plain.obs_dim == 127
    assert not hasattr(plain, "obs_image") and not hasattr(plain.cfg, "image_size")


# ---- the env ----------------------------------------------------------------------------------------------------
def test_render_image_is_small_rgb_and_shows_the_arm(image_env):
    a = image_env.render_image(image_env.q)
    b = image_env.render_image(image_env.witness)
    assert a.shape == (32, 32, 3) and a.dtype == np.uint8  # EngineImageConfig.image_size's default
    assert np.abs(a.astype(int) - b).sum() > 1000  # the arm moved in the picture
    env = EngineReach3DImage(EngineImageConfig(image_size=24))
    _, info = env.reset(seed=10_002)
    assert info["image"].shape == (24, 24, 3)
    _, _, _, _, info = env.step(env.q)
    assert info["image"].shape == (24, 24, 3)


def test_image_observations_end_with_the_rendered_camera_image():
    env = EngineReach3DImage(EngineImageConfig(image_size=16))
    assert env.image_shape == (3, 16, 16) and env.obs_dim == 15 + 3 * 16 * 16
    obs, info = env.reset(seed=10_004)
    assert obs.shape == (env.obs_dim,) and obs.dtype == np.float32
    assert np.array_equal(obs[:6], env.q.astype(np.float32)) and np.allclose(obs[12:15], env.goal)
    assert 0.0 <= obs[15:].min() and obs[15:].max() <= 1.0
    # channel-first in the vector: channel c of pixel (row, col) sits at 15 + c*S*S + row*S + col
    image = env.render_image(env.q)
    assert np.array_equal(info["image"], image) and np.array_equal(env.obs_image(obs), image)
    assert obs[15 + 2 * 256 + 5 * 16 + 7] == np.float32(image[5, 7, 2] / 255)
    # batched: every row rendered at its own q
    q = np.stack([env.q, env.witness])
    batch = env.make_obs(q, q)
    assert np.array_equal(env.obs_image(batch[1]), env.render_image(env.witness))
    assert np.abs(batch[0, 15:] - batch[1, 15:]).sum() > 1.0
    # near recorded observations, their images are copied, not rendered: the noised-state approximation of Sec. V
    kept = env.make_obs_near(q, q, batch[:1])
    assert np.array_equal(kept[1, 15:], batch[0, 15:]) and np.array_equal(kept[1, :6], env.witness.astype(np.float32))
    assert np.array_equal(env.make_obs_near(q, q, batch), batch)
    assert np.array_equal(env.make_obs_near(env.q, env.q, batch[1]), np.concatenate([obs[:15], batch[1, 15:]]))


def test_image_env_bad_input_names_the_value(image_env):
    env = EngineReach3DImage(EngineImageConfig(image_size=16))
    env.reset(seed=10_004)
    with pytest.raises(ValueError, match=r"recorded must have shape \(783,\)"):
        env.make_obs_near(env.q, env.q, np.zeros(10))
    with pytest.raises(ValueError, match="image_size must be an int >= 8"):
        EngineReach3DImage(EngineImageConfig(image_size=4))
    with pytest.raises(ValueError, match="obs_dim=783"):
        env.obs_image(np.zeros(127))
    with pytest.raises(ValueError, match="size"):
        image_env.render_image(size=4)
    plain = engine3d.EngineReach3D()  # the core env: recorded observations change nothing, all is recomputed
    plain.reset(seed=10_004)
    assert np.array_equal(plain.make_obs_near(plain.q, plain.q, np.zeros(127)), plain.make_obs(plain.q, plain.q))


# ---- the encoder and the policy ------------------------------------------------------------------------------------
def tiny_policy(encoder=None, **overrides):
    """A tiny policy; encoder: its observation encoder class (None: as numbers), recorded in its config as the
    harness's checkpoint loader reads it."""
    kwargs = dict(obs_dim=4, dof=2, horizon=4, n_act=2, K=50, **TINY_NET)
    kwargs.update(overrides)
    if encoder is not None:
        kwargs.update(obs_encoder=encoder.__name__, obs_encoder_sizes=encoder.sizes(**kwargs["obs_encoder_args"]))
    return DiffusionPolicy(PolicyConfig(**kwargs), obs_encoder=encoder)


def image_direction_data(n, seed=0, side=8):
    """obs = (q_t, q_t-1, a 1 x side x side image); the chunk moves both joints up if the image's bright
    square is in its left half, down if in its right half: the direction is in the image only."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1, 1, (n, 2))
    left = rng.random(n) < 0.5
    images = np.zeros((n, 1, side, side), np.float32)
    for i in range(n):
        row = rng.integers(0, side - 2)
        col = rng.integers(0, side // 2 - 2) + (0 if left[i] else side // 2)
        images[i, 0, row:row + 3, col:col + 2] = 1.0
    obs = np.concatenate([q, q, images.reshape(n, -1)], axis=1).astype(np.float32)
    v = np.where(left, 0.05, -0.05)[:, None, None] * np.ones((1, 1, 2))
    chunks = q[:, None, :] + np.arange(1, 5)[None, :, None] * v
    return obs, chunks.astype(np.float32), left


CNN_8 = dict(encoder=ImageEncoder, obs_encoder_args={"shape": (1, 8, 8), "features": 16})


@pytest.mark.slow
def test_image_policy_reads_the_direction_from_the_image():
    obs, chunks, _ = image_direction_data(2000, seed=0)
    test_obs, _, left = image_direction_data(200, seed=1)
    policy = tiny_policy(obs_dim=obs.shape[1], **CNN_8)
    train(policy, obs, chunks, TrainConfig(steps=200, batch_size=128, lr=1e-2, warmup_steps=50, log_every=0))
    samples = policy.sample(test_obs, generator=torch.Generator().manual_seed(0))
    moved_up = (samples[:, -1] - test_obs[:, None, :2][:, 0]).mean(axis=1) > 0
    # without the CNN passing the image on this would be a coin flip (~50 %)
    assert (moved_up == left).mean() > 0.95


def test_image_policy_normalizer_layout_and_round_trip(tmp_path):
    obs, chunks, _ = image_direction_data(100, seed=3)
    policy = tiny_policy(obs_dim=obs.shape[1], **CNN_8)
    assert policy.cfg.low_dim == 4 and policy.cfg.encoder_sizes == (64, 16)
    assert policy.cfg.cond_input_dim == 4 + 2 + 16                # low-dim, velocity, image code
    policy.fit_normalizer(obs, chunks)
    # the pixels are not fitted: they reach the CNN as they are, which maps [0, 1] to [-1, 1] itself
    assert torch.all(policy.obs_center[4:] == 0) and torch.all(policy.obs_half[4:] == 1)
    assert policy.obs_half[:2].min() > 0.5                          # joint columns fitted on the data
    o = torch.as_tensor(obs)
    feats = policy.normalize_obs(o)
    assert feats.shape == (100, 4 + 2 + 64)                         # pixels last, for the CNN
    assert torch.equal(feats[:, 6:], o[:, 4:])
    encoder = policy.net.obs_encoder
    image = (2 * o[:, 4:] - 1).reshape(-1, 1, 8, 8)
    code = torch.nn.functional.silu(encoder.fc(encoder.conv(image).flatten(1)))
    assert torch.allclose(encoder(feats), torch.cat([feats[:, :6], code], dim=1))
    path = tmp_path / "image_policy.pt"
    checkpoints.save_policy(policy, path)
    loaded = checkpoints.load_policy(path)                          # the CNN rebuilt from the saved config
    assert loaded.cfg.obs_encoder == "ImageEncoder" and tuple(loaded.cfg.obs_encoder_args["shape"]) == (1, 8, 8)
    assert isinstance(loaded.net.obs_encoder, ImageEncoder)
    a = policy.sample(obs[:5], generator=torch.Generator().manual_seed(1))
    b = loaded.sample(obs[:5], generator=torch.Generator().manual_seed(1))
    assert np.array_equal(a, b)


def test_the_encoder_leaves_image_free_policies_unchanged_and_checks_its_arguments():
    plain, with_image = tiny_policy(obs_dim=68), tiny_policy(ImageEncoder, obs_dim=68,
                                                            obs_encoder_args={"shape": (1, 8, 8)})
    assert not any("obs_encoder" in k for k in plain.state_dict())   # 'flat' has no weights
    shared = {k: v for k, v in with_image.net.state_dict().items() if not k.startswith("obs_encoder")}
    assert sorted(shared) == sorted(plain.net.state_dict())         # the CNN is an addition, nothing else moved
    # obs_dim 68 = 4 + 64 pixels, and the CNN's 64 features: the U-Net's shapes agree, and so do its weights
    assert all(torch.equal(shared[k], plain.net.state_dict()[k]) for k in shared)
    with pytest.raises(ValueError, match="ImageEncoder: shape must be"):
        ImageEncoder.sizes(shape=(8, 8))
    with pytest.raises(ValueError, match="ImageEncoder: shape must be"):
        ImageEncoder.sizes(shape=(1, 4, 4))
    with pytest.raises(ValueError, match="ImageEncoder: features must be"):
        ImageEncoder.sizes(shape=(1, 8, 8), features=0)
    with pytest.raises(ValueError, match="must be longer"):
        PolicyConfig(obs_dim=64, dof=2, horizon=4, n_act=2, K=10, obs_encoder="ImageEncoder",
                     obs_encoder_args={"shape": (1, 8, 8)}, obs_encoder_sizes=(64, 64))


def test_checkpoints_of_earlier_versions_load_without_an_image_and_are_refused_with_one(tmp_path):
    """Before the variant moved out, PolicyConfig held image_shape / image_features: a checkpoint without an
    image (image_shape ()) loads as it is; one with an image names the variant and asks for a retrain."""
    policy = tiny_policy(obs_dim=6)
    path = str(tmp_path / "old.pt")
    checkpoints.save_policy(policy, path)
    payload = torch.load(path, weights_only=True)
    payload["config"].update(image_shape=(), image_features=64)
    torch.save(payload, path)
    loaded = checkpoints.load_policy(path)
    obs = np.zeros((2, 6), np.float32)
    assert np.array_equal(loaded.sample(obs, generator=torch.Generator().manual_seed(0)),
                          policy.sample(obs, generator=torch.Generator().manual_seed(0)))
    payload["config"].update(image_shape=(1, 8, 8))
    torch.save(payload, path)
    with pytest.raises(ValueError, match="image_shape=.*engine3d_image.*retrain"):
        checkpoints.load_policy(path)


# ---- the augmentation ----------------------------------------------------------------------------------------------
def test_sampler_reuses_the_recorded_image_for_noised_states():
    """Sec. V: with image observations a noised state keeps the original state's image; only the joint
    positions (and the labels) change. The image part of every pair is a recorded one, not a new render."""
    make = lambda: environments.make_env("engine3d_image", image_size=8)  # noqa: E731
    env = make()
    episodes = [straight_line_episode(env, seed, expert_from=2) for seed in (3, 4)]
    episodes = [ep for ep in episodes if len(ep["q"]) > 20]
    assert episodes, "stand-in episodes too short for this test"
    demo = relabel.demo_stats(episodes, envs.median_step(episodes), env.max_step)
    sampler = relabel.AugmentationSampler(episodes, make, demo, "isotropic", 4.0, relabel.RelabelConfig(horizon=8))
    obs, chunks, mask = sampler.generate(40, np.random.default_rng(0))
    assert len(obs) > 20 and obs.shape[1] == env.obs_dim
    n_pix = 3 * 8 * 8
    recorded = np.concatenate([ep["obs"][:, -n_pix:] for ep in episodes])
    for row in obs:
        assert np.any(np.all(recorded == row[-n_pix:], axis=1))      # an original image, bit for bit
    recorded_q = np.concatenate([ep["obs"][:, :6] for ep in episodes])
    moved = [np.abs(recorded_q - row[:6]).sum(axis=1).min() > 1e-4 for row in obs]
    assert np.mean(moved) > 0.9                                       # while the joints were noised


# ---- the run: command line, policy, evaluation, workers, the whole loop ------------------------------------------
def test_env_flag_chooses_the_variant_names_the_run_and_reaches_the_policy():
    _, cfg = cli.parse_args(["--env", "engine3d_image", "--profile", "smoke"])
    assert cfg.env == "engine3d_image" and cfg.name == "smoke_engine3d_image"
    env = environments.make_env(cfg.env)
    assert env.image_shape == (3, 32, 32)
    policy = dagger.make_policy(cfg, env)
    assert policy.cfg.obs_encoder == "ImageEncoder" and policy.cfg.obs_encoder_args == {"shape": (3, 32, 32)}
    assert isinstance(policy.net.obs_encoder, ImageEncoder) and isinstance(policy.ema_net.obs_encoder, ImageEncoder)
    assert policy.cfg.obs_encoder_sizes == (3 * 32 * 32, 64)
    assert policy.cfg.obs_dim == env.obs_dim
    assert policy.cfg.obs_encoder_args is not env.obs_encoder_args   # a copy: the env's stays as it is
    # the training observation noise: joints and goal as the lever's, the pixels none
    std = dagger.observation_noise(policy.cfg)
    assert np.all(std[:12] == dagger.OBS_NOISE_JOINTS) and np.all(std[12:15] == dagger.OBS_NOISE_ENV)
    assert np.all(std[15:] == 0)


def test_evaluate_runs_an_image_policy_on_image_observations(monkeypatch):
    """evaluate makes every env by the run's env name with the factory handed in: the policy's obs_dim only matches
    the image layout."""
    name = small_images(monkeypatch, 8)
    cfg = replace(profiles.PROFILES["smoke"], env=name, K=4, down_dims=(8, 16))
    env = environments.make_env(cfg.env)
    policy = dagger.make_policy(cfg, env)
    obs, _ = env.reset(seed=int(env.train_seeds(1)[0]))
    policy.fit_normalizer(obs[None], np.repeat(env.q[None, None], cfg.horizon, axis=1))
    seen = []
    sample = policy.sample
    policy.sample = lambda o, generator=None: seen.append(o.shape) or sample(o, generator)
    ok = dagger.evaluate(policy, name, env.eval_seeds()[:2], 1, cfg.n_act, 0, make_env=environments.make_env)
    assert ok.shape == (2, 1) and seen and all(shape[1] == env.obs_dim == 15 + 3 * 8 * 8 for shape in seen)
    with pytest.raises(ValueError, match="obs must have shape"):
        dagger.evaluate(policy, "engine3d", env.eval_seeds()[:1], 1, cfg.n_act, 0,
                        make_env=environments.make_env)  # no images: 127 != 207


@pytest.mark.slow
def test_a_worker_process_rebuilds_the_variant_env():
    """Workers are spawned: a job (a dagger.py function with the harness's env factory) rebuilds the variant's env."""
    cfg = replace(profiles.PROFILES["smoke"], env="engine3d_image", n_demos=1)
    workers.in_parallel(dagger.demo_statistics, [(cfg, [ep], environments.make_env) for ep in
                                                 [straight_line_episode(envs.make_env("planar"), 0)] * 2],
                        workers=2)  # a worker's error is raised here


@pytest.mark.slow
def test_whole_loop_on_engine3d_with_image_observations(tmp_path, monkeypatch):
    """Every stage with the UR5 env and camera images: demos, BC, HG-DAgger with the 6-dof oracle,
    calibration, augmentation that reuses recorded images, evaluation, every figure (figs 1-3 in the top view)."""
    name = small_images(monkeypatch, 16)
    cfg = replace(TINY, name="tiny_images", env=name, n_demos=2, eval_scenarios=2)
    root = report.run_experiment(cfg, str(tmp_path / "images"))
    results = json.load(open(os.path.join(root, "results.json")))
    assert set(results["success"]) == {"bc", "hg_dagger", "pooled"}
    D0 = run_folder.load_episodes(os.path.join(root, "data", "D0.npz"))
    assert D0[0]["obs"].shape[1] == 15 + 3 * 16 * 16                 # the images are in the data
    for f in ("fig1_recovery.png", "fig2_method_overview.png", "fig3_partial_denoising.png", "fig4_blend_fit.png",
              "fig5_environment.png", "fig5_policy_view.png", "table_i.png", "lineage_0/round_1/checkpoints/pooled.pt"):
        assert os.path.isfile(os.path.join(root, f if "/" in f else os.path.join("figures", f)))
    assert "Table II" in open(os.path.join(root, "table.md")).read()  # the lever's table, as the variant's env is
    pooled = run_folder.Run(root, cfg).load("lineage_0/round_1/checkpoints/pooled.pt")
    assert pooled.cfg.obs_encoder == "ImageEncoder" and isinstance(pooled.net.obs_encoder, ImageEncoder)


def test_planar_runs_draw_no_policy_view(tmp_path):
    env = envs.make_env("planar")
    assert env.plot_policy_view({"obs": np.zeros((3, env.obs_dim))}, str(tmp_path / "view.png")) is False
    assert not os.path.exists(tmp_path / "view.png")


# ---- the run folder: configs stored with the retired fields --------------------------------------------------------
def test_stored_configs_with_the_retired_image_fields_compare_at_their_one_value(tmp_path):
    """config.json (a resumed folder), a lineage's record and --join / --copy-from compare configs through
    check_same_config: image_obs false (what every config held) is dropped with image_size (read only with images),
    image_obs true refused naming the field and the new way."""
    assert run_folder.RETIRED_FIELDS["image_obs"] == (False,)
    assert run_folder.RETIRED_FIELDS["image_size"] is run_folder.ANY_VALUE
    root = str(tmp_path / "run")
    run_folder.Run(root, TINY)
    path = os.path.join(root, "config.json")
    stored = json.load(open(path))
    for size in (32, 16):
        json.dump({**stored, "image_obs": False, "image_size": size}, open(path, "w"))
        run_folder.Run(root, TINY)                                    # the folder resumes
    json.dump({**stored, "image_obs": True, "image_size": 32}, open(path, "w"))
    with pytest.raises(run_folder.ConfigMismatch, match="image_obs = True.*--env engine3d_image"):
        run_folder.Run(root, TINY)


def test_a_committed_lineage_file_with_the_retired_fields_joins(tmp_path):
    """benchmarks/results/ holds lineage files written with image_obs / image_size in their configs."""
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "results",
                        "table2", "lineage_0.json.gz")
    with gzip.open(path, "rt") as f:
        stored = json.load(f)["config"]
    assert stored["image_obs"] is False and stored["image_size"] == 32
    run = run_folder.Run(str(tmp_path / "table2"), profiles.PROFILES["table2"])
    assert run_folder.join_lineage(run, path) == 0
