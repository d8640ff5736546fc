"""Tests of the run folder's files: policy checkpoints (experiment/checkpoints.py: older files, damage, resuming a
run with Run.train), the calibration's JSON form and log text, and the episode files."""
import io
import json
from dataclasses import dataclass

import numpy as np
import pytest
import torch

import test_calibrate
from diffusion import DiffusionPolicy, PolicyConfig, TrainConfig, toy_two_mode_data, train
from experiment import checkpoints, cpu_kernels
from experiment.report import calibration_text
from experiment.run_folder import (Run, RunFolderError, calibration_from_json, calibration_to_json, read_episodes,
                                   write_episodes)


def tiny_policy(**overrides):
    kwargs = dict(obs_dim=4, dof=2, horizon=4, n_act=2, K=50, down_dims=(16, 32), n_groups=4, step_embed_dim=32)
    return DiffusionPolicy(PolicyConfig(**{**kwargs, **overrides}))


@pytest.fixture(scope="module")
def trained():
    """A policy made as the run makes one (dagger.make_policy): with the CPU kernels this machine takes, as
    checkpoints.load_policy gives them to the policy it loads (else the round trip compares two Mish functions)."""
    obs, chunks = toy_two_mode_data(300, H=4, seed=0)
    return train(cpu_kernels.use_kernels(tiny_policy()), obs, chunks,
                 TrainConfig(steps=30, batch_size=32, warmup_steps=5, log_every=0))


def test_save_load_round_trip(trained, tmp_path):
    path = str(tmp_path / "policy.pt")
    checkpoints.save_policy(trained, path)
    loaded = checkpoints.load_policy(path)
    obs = np.random.default_rng(0).uniform(-1, 1, (32, 4)).astype(np.float32)
    a = trained.sample(obs, generator=torch.Generator().manual_seed(3))
    assert np.array_equal(a, loaded.sample(obs, generator=torch.Generator().manual_seed(3)))
    assert loaded.cfg == trained.cfg
    assert not np.array_equal(a, loaded.sample(obs, generator=torch.Generator().manual_seed(4)))
    with pytest.raises(FileNotFoundError):
        checkpoints.load_policy(str(tmp_path / "missing.pt"))
    torch.save({"format": "diffusion-policy-v1", "config": {}, "state_dict": {}}, tmp_path / "mlp.pt")
    with pytest.raises(ValueError, match="not a diffusion-policy-v2 checkpoint"):
        checkpoints.load_policy(str(tmp_path / "mlp.pt"))


def test_a_checkpoint_of_a_deleted_option_loads_at_the_kept_value_and_is_refused_at_another(trained, tmp_path):
    """Checkpoints written before PolicyConfig.schedule / joint_obs were deleted name them: 'squaredcos' and
    joint_obs True (every profile's) load as before; 'linear' and absolute chunks are refused, naming the file."""
    checkpoints.save_policy(trained, str(tmp_path / "policy.pt"))
    payload = torch.load(tmp_path / "policy.pt", weights_only=True)
    for name, value in (("schedule", "squaredcos"), ("schedule", "linear"), ("joint_obs", True), ("joint_obs", False)):
        torch.save({**payload, "config": {**payload["config"], name: value}}, tmp_path / f"{name}_{value}.pt")
    assert checkpoints.load_policy(str(tmp_path / "schedule_squaredcos.pt")).cfg == trained.cfg
    assert checkpoints.load_policy(str(tmp_path / "joint_obs_True.pt")).cfg == trained.cfg
    with pytest.raises(ValueError, match=r"schedule_linear\.pt.*linear noise schedule"):
        checkpoints.load_policy(str(tmp_path / "schedule_linear.pt"))
    with pytest.raises(ValueError, match=r"joint_obs_False\.pt.*absolute chunks"):
        checkpoints.load_policy(str(tmp_path / "joint_obs_False.pt"))


def test_a_damaged_checkpoint_is_a_clear_error_naming_the_file(trained, tmp_path):
    """A truncated file (half of a real checkpoint), junk bytes, an empty file and a saved tensor raise
    CheckpointDamagedError (a ValueError) naming the file and saying how to re-make it, never a raw
    EOFError / RuntimeError / UnpicklingError; the run folder names it too."""
    full = str(tmp_path / "full.pt")
    checkpoints.save_policy(trained, full)
    data = open(full, "rb").read()
    not_a_dict = io.BytesIO()
    torch.save(torch.zeros(3), not_a_dict)                             # a torch file, but no checkpoint
    damaged = {"half.pt": data[:len(data) // 2], "junk.pt": bytes(range(256)) * 4, "empty.pt": b"",
               "tensor.pt": not_a_dict.getvalue()}
    for name, content in damaged.items():
        path = str(tmp_path / name)
        with open(path, "wb") as f:
            f.write(content)
        with pytest.raises(checkpoints.CheckpointDamagedError, match="damaged") as err:
            checkpoints.load_policy(path)
        assert isinstance(err.value, ValueError)
        assert path in str(err.value) and "delete it" in str(err.value)
    run = Run(str(tmp_path / "run"), RunCfg())
    (tmp_path / "run" / "p.pt").write_bytes(damaged["half.pt"])
    with pytest.raises(RunFolderError, match=r"p\.pt is damaged \(truncated, or not a checkpoint\)"):
        run.load("p.pt")
    checkpoints.load_policy(full)                                      # the intact file still loads
    with pytest.raises(ValueError, match="no training state"):         # a final file cannot be continued
        checkpoints.train_state(full, checkpoints.read_checkpoint(full))


@dataclass
class RunCfg:
    device: str = "cpu"
    lineages: int = 1


@pytest.fixture(autouse=True)
def pool_sampler_state(monkeypatch):
    """PoolSampler's state is what a resumed run restores of it, as relabel.AugmentationSampler's pool."""
    monkeypatch.setitem(checkpoints.SAMPLER_STATE, PoolSampler, ("_pool",))


class PoolSampler:
    """A co-training sampler with state (a pool of pairs, partly refreshed every call), like relabel's; it stops
    the run (KeyboardInterrupt) at its call `stop_at`. Its state, like relabel's, is named in
    checkpoints.SAMPLER_STATE (pool_sampler_state)."""

    def __init__(self, stop_at=None):
        self._pool, self.calls, self.stop_at = None, 0, stop_at

    def __call__(self, n, rng):
        self.calls += 1
        if self.calls == self.stop_at:
            raise KeyboardInterrupt
        if self._pool is None:
            self._pool = rng.uniform(-1, 1, (16, 4)).astype(np.float32)
        self._pool[rng.integers(0, 16)] = rng.uniform(-1, 1, 4)
        obs = self._pool[rng.integers(0, 16, n)] + self._pool.mean(0)  # depends on the whole pool
        return obs, np.repeat(obs[:, None, :2], 4, axis=1)


def test_a_stopped_training_resumes_from_its_last_quarter_as_if_never_stopped(tmp_path):
    """Run.train writes checkpoints at quarters of the run (10, 20, 30 of 40 steps); a run stopped at step 25
    goes on from step 20's file -- weights, AdamW, both random streams and the sampler's pool -- to the same
    weights bit for bit as the uninterrupted run; the partial files are gone at the end. Fails if the pool
    (SAMPLER_STATE) or a random stream were not restored, or the resumed run started over."""
    obs, chunks = toy_two_mode_data(300, H=4, seed=1)
    cfg = TrainConfig(steps=40, batch_size=32, warmup_steps=5, log_every=0, seed=3, aug_fraction=0.25, obs_noise=0.05)
    whole = Run(str(tmp_path / "whole"), RunCfg()).train("p.pt", tiny_policy(), obs, chunks, cfg, PoolSampler())
    run = Run(str(tmp_path / "stopped"), RunCfg())
    with pytest.raises(KeyboardInterrupt):
        run.train("p.pt", tiny_policy(), obs, chunks, cfg, PoolSampler(stop_at=26))
    assert sorted(p.name for p in (tmp_path / "stopped").glob("p_step*.pt")) == ["p_step10.pt", "p_step20.pt"]
    sampler = PoolSampler()
    resumed = run.train("p.pt", tiny_policy(seed=99), obs, chunks, cfg, sampler)
    assert sampler.calls == 20, "resumed at step 20: 20 steps left"
    assert all(torch.equal(v, resumed.state_dict()[k]) for k, v in whole.state_dict().items())
    assert not list((tmp_path / "stopped").glob("p_step*.pt"))
    final = checkpoints.load_policy(str(tmp_path / "stopped" / "p.pt"))
    assert all(torch.equal(v, final.state_dict()[k]) for k, v in whole.state_dict().items())
    other = train(tiny_policy(), obs, chunks, TrainConfig(**{**cfg.__dict__, "seed": 4}), sampler=PoolSampler())
    key = "net.down.0.0.conv1.0.weight"
    assert not torch.equal(whole.state_dict()[key], other.state_dict()[key])  # another seed, other weights


def test_continuing_pi0_goes_on_from_its_step_and_optimizer(tmp_path):
    """Run.train(start=pi_0's train_state, pi_0 kept with its state) trains from pi_0's step to the total: the
    checkpoints fall at quarters of the remaining steps, and the result is train(start=pi_0's step and AdamW state);
    pi_0 as trained and as loaded from its file hold the same train_state."""
    obs, chunks = toy_two_mode_data(300, H=4, seed=1)
    base = dict(batch_size=32, warmup_steps=5, log_every=0, schedule_steps=60)
    run = Run(str(tmp_path / "run"), RunCfg())
    trained = run.train("pi0.pt", tiny_policy(), obs, chunks, TrainConfig(steps=30, seed=1, **base), keep_state=True)
    payload = checkpoints.read_checkpoint(str(tmp_path / "run" / "pi0.pt"))
    assert payload["train_state"]["step"] == 30 == trained.train_state["step"]
    loaded = run.load("pi0.pt").train_state["optimizer"]["state"]
    assert all(torch.equal(v, loaded[i][name]) for i, s in trained.train_state["optimizer"]["state"].items()
               for name, v in s.items())
    marks = []
    real = checkpoints.save_policy
    checkpoints.save_policy = lambda p, path, state=None, *a: (marks.append(state and state["step"]), real(p, path, state, *a))
    try:
        pi0 = run.load("pi0.pt")
        cont = run.train("arm.pt", pi0, obs, chunks, TrainConfig(steps=60, seed=2, **base), start=pi0.train_state)
    finally:
        checkpoints.save_policy = real
    assert marks == [37, 45, 52, None]                                 # 30 + quarters of 30, then the final file
    policy = run.load("pi0.pt")
    start = {"step": 30, "optimizer": payload["train_state"]["optimizer"]}
    same = train(policy, obs, chunks, TrainConfig(steps=60, seed=2, **base), start=start)
    assert all(torch.equal(v, cont.state_dict()[k]) for k, v in same.state_dict().items())


# ---- calibration.json and the calibration's log text

def _calibration():
    return test_calibrate._calibration()


def test_report_gives_sigma_and_W_in_one_unit_radians_beside():
    """One unit in the log: the paper's median steps where the env has one, else ours; radians beside. A W or an
    interval divided by the other unit, or the two units mixed in one line, fails."""
    c = _calibration()                                                       # median step 0.01 rad, W 0.05 rad
    text = calibration_text(c)                                               # no paper unit: ours, rad beside
    assert "paper median steps" not in text
    assert "W = 5.00 median steps (0.050 rad) (95 % bootstrap interval 4.00–6.20" in text
    assert "our median step 0.0100 rad (per joint, base demos); the paper gives none" in text
    c.paper_median_step = 0.0176
    text = calibration_text(c)
    assert (f"W = {0.05 / 0.0176:.2f} paper median steps (0.050 rad) (95 % bootstrap interval "
            f"{0.04 / 0.0176:.2f}–{0.062 / 0.0176:.2f}, ") in text
    assert text.count("W = ") == 1 and " median steps" not in text.replace("paper median steps", "")
    sigma = np.sqrt(np.diag(c.pooled))
    assert ("per-joint sigma = " + ", ".join(f"{v / 0.0176:.2f}" for v in sigma) + " paper median steps ("
            + ", ".join(f"{v:.3f}" for v in sigma) + " rad)") in text
    assert f"ours 0.0100 rad (per joint, base demos) = {0.01 / 0.0176:.2f}x theirs" in text
    back = calibration_from_json(json.loads(json.dumps(calibration_to_json(c))))
    assert back.paper_median_step == 0.0176 and calibration_text(back) == text


def test_calibration_json_round_trip(tmp_path):
    c = _calibration()
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(calibration_to_json(c)))
    back = calibration_from_json(json.loads(path.read_text()))
    for key, value in calibration_to_json(c).items():
        got = getattr(back, key)
        if isinstance(getattr(c, key), np.ndarray):
            assert got.dtype == getattr(c, key).dtype, key
            np.testing.assert_array_equal(got, getattr(c, key))
        else:
            assert got == value, key
    assert "W = 5.00 median steps (0.050 rad) (95 % bootstrap interval 4.00–6.20" in calibration_text(back)
    np.testing.assert_allclose(back.sigma_per_joint, np.sqrt(np.diag(c.pooled)) / 0.01)
    # a calibration written before W_ci existed still loads
    old = json.loads(path.read_text())
    del old["W_ci"]
    assert calibration_from_json(old).W_ci is None
    assert "bootstrap" not in calibration_text(calibration_from_json(old))
    # and one written with the unguided control (now experiment/unguided.py), under either of its names
    for key in ("unguided_pooled", "closed_loop_pooled"):
        assert calibration_to_json(calibration_from_json(dict(old, **{key: c.pooled.tolist()}))) == \
            calibration_to_json(calibration_from_json(old))
        assert calibration_from_json(dict(old, **{key: None})).W == c.W


# ---- episode files (data/D0.npz, D.npz)

def test_episode_files_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    episodes = []
    for i, T in enumerate([5, 1, 12]):
        episodes.append({"obs": rng.normal(size=(T, 48)).astype(np.float32),
                         "q": rng.normal(size=(T, 3)), "action": rng.normal(size=(T, 3)),
                         "expert": rng.random(T) < 0.5, "seed": 100 + i, "success": bool(i % 2),
                         "goal": rng.normal(size=2)})
    path = tmp_path / "eps.npz"
    write_episodes(path, episodes)
    back = read_episodes(path)
    assert len(back) == 3
    for a, b in zip(episodes, back):
        assert set(a) == set(b)
        for k in ("obs", "q", "action", "expert"):
            np.testing.assert_array_equal(a[k], b[k])
            assert a[k].dtype == b[k].dtype
        assert b["seed"] == a["seed"] and isinstance(b["seed"], int)
        assert b["success"] == a["success"] and isinstance(b["success"], bool)
        np.testing.assert_array_equal(a["goal"], b["goal"])
    with pytest.raises(ValueError, match="missing"):
        write_episodes(path, [episodes[0], {"q": np.zeros((2, 3))}])
    with pytest.raises(FileNotFoundError):
        read_episodes(tmp_path / "missing.npz")


# ---- the paper's figures drawn once per state of their inputs (report.write_report)

def test_inputs_changed_until_recorded_and_again_when_an_input_or_a_drawn_file_changes(tmp_path):
    """Run.inputs_changed / record_inputs, with which the report redraws the paper's figures only when D0 or lineage 0's
    round 1 changed: fails if an unchanged folder redrew (CI's README commands redrew five figures each time), or a
    new or rewritten input, or a deleted figure, did not."""
    run = Run(str(tmp_path / "run"), RunCfg())
    (tmp_path / "run" / "a.npz").write_bytes(b"12345")
    stamp, inputs = "figures/drawn_from.json", ["a.npz", "b.json"]
    assert run.inputs_changed(stamp, inputs)                           # never drawn
    (tmp_path / "run" / "figures").mkdir(exist_ok=True)
    (tmp_path / "run" / "figures" / "fig1.png").write_bytes(b"png")
    run.record_inputs(stamp, inputs)
    assert not run.inputs_changed(stamp, inputs)
    (tmp_path / "run" / "b.json").write_text("{}")                     # an input that was missing appears
    assert run.inputs_changed(stamp, inputs)
    run.record_inputs(stamp, inputs)
    (tmp_path / "run" / "a.npz").write_bytes(b"123456")                # an input rewritten
    assert run.inputs_changed(stamp, inputs)
    run.record_inputs(stamp, inputs)
    assert not run.inputs_changed(stamp, inputs)
    (tmp_path / "run" / "figures" / "fig1.png").unlink()               # a drawn figure deleted
    assert run.inputs_changed(stamp, inputs)


def test_a_run_of_two_noise_levels_gets_the_success_vs_sigma_panels():
    """sigma_panels: none for a run of one fixed sigma (the quick profile: its outputs stay as they were), one panel
    a scenario set otherwise, at the last round, each row one value a lineage; the pooled row at the isotropic sigma
    of its per-joint sigmas' mean variance (a mean of the sigmas, or our unit instead of the paper's, fails)."""
    from dataclasses import replace
    from experiment import report
    import dagger
    cfg = replace(dagger.Config(), rounds=2, methods=("bc", "hg_dagger", "fixed_4", "pooled"))
    res = {m: {"0": [50.0, 60.0], "1": [52.0, 58.0]} for m in cfg.methods}
    res["bc"] = {"0": [40.0], "1": [40.0]}
    cal = {"2": {"0": {"sigma_per_joint_paper": [3.0, 4.0, 5.0]}, "1": {"sigma_per_joint_paper": [1.0, 1.0, 1.0]}}}
    assert report.sigma_panels(cfg, {"eval": res, "unseen": res}, cal) == []
    cfg = replace(cfg, methods=("bc", "hg_dagger", "zero_noise", "fixed_4", "fixed_16", "pooled"))
    res.update({m: {"0": [50.0, 61.0], "1": [52.0, 59.0]} for m in ("zero_noise", "fixed_16")})
    panels = report.sigma_panels(cfg, {"eval": res, "unseen": res}, cal)
    assert len(panels) == 2 and "unseen" in panels[1][0] and "K = 2" in panels[0][0]
    title, rows, levels, pooled = panels[0]
    assert levels == {0.0: "zero_noise", 4.0: "fixed_4", 16.0: "fixed_16"}
    assert rows["hg_dagger"] == [60.0, 58.0] and rows["bc"] == [40.0, 40.0] and rows["fixed_16"] == [61.0, 59.0]
    assert pooled == pytest.approx((np.sqrt(50 / 3) + 1.0) / 2)
    assert report.t_975(4) == pytest.approx(2.776) and report.t_975(20) == pytest.approx(2.086, abs=1e-3)
