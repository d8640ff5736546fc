"""dagger.py's fine-tuning recipe: continuing pi_0's schedule (the authors' run) or restarting, the BC row,
the recorded share of a noised arm (raw_mix), the arms in worker processes, the planar start option."""
import json
import os
import shutil
from dataclasses import asdict, replace

import numpy as np
import pytest
import torch

import calibrate
import dagger
import diffusion
import relabel
from experiment import run_folder

TINY = dagger.Config(name="tiny", n_demos=4, rounds=1, lineages=1, episodes_per_round=3, K=5, network="mlp",
                     mlp_width=16, mlp_blocks=1, bc_steps=30, finetune_steps=12, batch_size=32,
                     methods=("bc", "hg_dagger", "fixed_4", "pooled"), finetune="continue",
                     calib_blend_segments=1, calib_samples=2, eval_scenarios=3, eval_repeats=1, eval_unseen=False)


@pytest.fixture(scope="module")
def two_workers(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("workers2"))
    dagger.run_experiment(TINY, root, workers=2)
    return root


def test_continue_saves_pi0_with_its_optimizer_and_the_bc_row_continues_it(two_workers):
    state = torch.load(os.path.join(two_workers, "checkpoints", "bc.pt"), weights_only=True)["train_state"]
    assert state["step"] == TINY.bc_steps and state["optimizer"]["state"]          # AdamW moments kept
    assert json.loads(state["train_config"])["schedule_steps"] == TINY.bc_steps + TINY.finetune_steps
    pi0 = diffusion.DiffusionPolicy.load(os.path.join(two_workers, "checkpoints", "bc.pt")).state_dict()
    row = diffusion.DiffusionPolicy.load(os.path.join(two_workers, "checkpoints", "bc_continued.pt")).state_dict()
    assert any(not torch.equal(pi0[k], row[k]) for k in pi0 if k.startswith("net."))
    assert os.path.isfile(os.path.join(two_workers, "eval", "pi0.json"))          # round 1's collector
    assert os.path.isfile(os.path.join(two_workers, "eval", "bc.json"))           # the table's BC row
    assert "pi_0 continued on D0 alone" in open(os.path.join(two_workers, "log.txt")).read()


def test_worker_processes_give_the_numbers_of_one_process(two_workers, tmp_path):
    root = str(tmp_path / "one")
    dagger.run_experiment(TINY, root, workers=1)
    a = json.load(open(os.path.join(two_workers, "results.json")))
    b = json.load(open(os.path.join(root, "results.json")))
    assert a["success"] == b["success"]
    for m in ("hg_dagger", "fixed_4", "pooled"):
        wa = diffusion.DiffusionPolicy.load(os.path.join(two_workers, "lineage_0/round_1/checkpoints", f"{m}.pt"))
        wb = diffusion.DiffusionPolicy.load(os.path.join(root, "lineage_0/round_1/checkpoints", f"{m}.pt"))
        assert all(torch.equal(v, wb.state_dict()[k]) for k, v in wa.state_dict().items())
    assert "2 jobs (noised_arm) in 2 worker processes" in open(os.path.join(two_workers, "log.txt")).read()


def test_restart_keeps_pi0_as_the_bc_row(two_workers, tmp_path):
    """Under finetune='restart' the table's BC row is pi_0 itself (no continued checkpoint), evaluated with the
    same draws as pi_0's own evaluation of the 'continue' run; under 'continue' pi_0 has a file of its own."""
    restart = replace(TINY, finetune="restart")
    assert dagger.pi0_eval_name(restart) == "eval/bc.json" and dagger.pi0_eval_name(TINY) == "eval/pi0.json"
    root = tmp_path / "restart"
    for name in ("data/D0.npz", "checkpoints/bc.pt"):  # the same D0 and pi_0
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(os.path.join(two_workers, name), root / name)
    dagger.bc_row_arm(str(root), asdict(restart))
    assert not (root / "checkpoints" / "bc_continued.pt").exists()
    row = json.load(open(root / "eval" / "bc.json"))["success"]
    assert row == json.load(open(os.path.join(two_workers, "eval", "pi0.json")))["success"]


def test_raw_mix_takes_that_share_of_each_round_as_recorded(two_workers):
    D = run_folder.load_episodes(os.path.join(two_workers, "lineage_0/round_1/D.npz"))
    demos = run_folder.load_episodes(os.path.join(two_workers, "data/D0.npz"))
    stats = dagger.demo_statistics(TINY, demos)
    cal = calibrate.Calibration.from_dict(run_folder.read_json(os.path.join(two_workers,
                                                                       "lineage_0/round_1/calibration.json")))
    kinds = lambda s: [type(x).__name__ for x in s.samplers]
    hg = dagger.intervention_sampler(TINY, "hg_dagger", [D, D], None, stats)
    assert kinds(hg) == ["ChunkSampler"] * 2 and np.allclose(hg.p, 0.5)
    code = dagger.intervention_sampler(TINY, "fixed_4", [D, D], cal, stats)       # the authors' code: all noised
    assert kinds(code) == ["AugmentationSampler"] * 2 and np.allclose(code.p, 0.5)
    text = dagger.intervention_sampler(replace(TINY, raw_mix=0.5), "pooled", [D, D], cal, stats)   # the paper's text
    assert kinds(text) == ["ChunkSampler", "AugmentationSampler"] * 2 and np.allclose(text.p, 0.25)
    third = dagger.intervention_sampler(replace(TINY, raw_mix=0.25), "fixed_4", [D], cal, stats)
    assert np.allclose(third.p, [0.25, 0.75])
    obs, chunks, mask = third(400, np.random.default_rng(0))
    recorded = relabel.ChunkSampler(D, TINY.horizon)
    is_recorded = np.array([any(np.array_equal(o, r) for r in recorded.obs) for o in obs])
    assert 0.15 < is_recorded.mean() < 0.35 and mask[is_recorded].all()            # recorded rows: whole chunks


def test_constant_mode_continues_pi0s_optimizer_at_a_tenth_of_its_peak_and_keeps_pi0_as_the_bc_row(tmp_path,
                                                                                                    monkeypatch):
    """finetune='constant' (the authors' lever runs): pi_0 ends its own cosine at bc_steps with its AdamW state
    saved; an arm goes on from that state at lr / 10 at every step (or finetune_lr) to bc_steps + finetune_steps;
    the BC row is pi_0 itself."""
    cfg = replace(TINY, finetune="constant", methods=("bc", "hg_dagger"))
    root = str(tmp_path / "constant")
    made, real = [], dagger.train_config
    monkeypatch.setattr(dagger, "train_config", lambda *a, **kw: made.append(real(*a, **kw)) or made[-1])
    resumed, real_train = [], run_folder.Run.train
    monkeypatch.setattr(run_folder.Run, "train", lambda self, name, *a, **kw: resumed.append(
        (name, kw.get("continue_from"))) or real_train(self, name, *a, **kw))
    dagger.run_experiment(cfg, root)
    pi0 = torch.load(os.path.join(root, "checkpoints", "bc.pt"), weights_only=True)["train_state"]
    assert pi0["step"] == cfg.bc_steps and pi0["optimizer"]["state"]
    assert json.loads(pi0["train_config"])["schedule_steps"] == 0  # its own cosine, over bc_steps
    bc_tc, arm_tc = made  # pi_0, then the HG-DAgger arm
    assert not bc_tc.constant_lr and bc_tc.steps == cfg.bc_steps
    assert arm_tc.constant_lr and arm_tc.lr == pytest.approx(cfg.lr / 10)
    assert arm_tc.steps == cfg.bc_steps + cfg.finetune_steps  # finetune_steps more, from pi_0's step
    assert resumed == [("checkpoints/bc.pt", None), ("lineage_0/round_1/checkpoints/hg_dagger.pt", "checkpoints/bc.pt")]
    assert not os.path.exists(os.path.join(root, "checkpoints", "bc_continued.pt"))
    assert dagger.pi0_eval_name(cfg) == "eval/bc.json"
    lrs = [diffusion.lr_at(step, diffusion.TrainConfig(steps=100, lr=2e-4, constant_lr=True)) for step in (0, 5, 99)]
    assert lrs == [2e-4] * 3  # no warm-up, no cosine
    tc = dagger.train_config(replace(cfg, finetune_lr=3e-5), dagger.make_policy(cfg, dagger.make_run_env(cfg)),
                             10, 0, lr=3e-5, constant_lr=True)
    assert tc.lr == 3e-5 and tc.constant_lr


def test_round_shares_by_frames_weigh_each_round_by_its_intervention_frames(two_workers):
    D = run_folder.load_episodes(os.path.join(two_workers, "lineage_0/round_1/D.npz"))
    demos = run_folder.load_episodes(os.path.join(two_workers, "data/D0.npz"))
    stats = dagger.demo_statistics(TINY, demos)
    small = D[:1]
    frames = np.array([sum(int(ep["expert"].sum()) for ep in x) for x in (D, small)], float)
    assert frames[0] > frames[1]
    equal = dagger.intervention_sampler(TINY, "hg_dagger", [D, small], None, stats)
    assert np.allclose(equal.p, 0.5)  # the authors' planar runs
    by_frames = dagger.intervention_sampler(replace(TINY, round_shares="frames"), "hg_dagger", [D, small], None, stats)
    assert np.allclose(by_frames.p, frames / frames.sum())  # their lever runs
    cal = calibrate.Calibration.from_dict(run_folder.read_json(os.path.join(two_workers,
                                                                       "lineage_0/round_1/calibration.json")))
    mixed = dagger.intervention_sampler(replace(TINY, round_shares="frames", raw_mix=0.5), "fixed_4", [D, small],
                                        cal, stats)
    assert np.allclose(mixed.p, np.repeat(frames / frames.sum(), 2) * 0.5)
    args, cfg = dagger.parse_args(["--profile", "smoke", "--finetune", "constant", "--round-shares", "frames"])
    assert (cfg.finetune, cfg.round_shares) == ("constant", "frames")
    assert cfg.name == "smoke_constant_frame_shares"


@pytest.mark.parametrize("overrides,match", [
    (dict(finetune="warm"), "finetune must be 'continue'"),
    (dict(finetune="continue", finetune_lr=1e-4), "finetune_lr"),
    (dict(round_shares="steps"), "round_shares must be 'equal'"),
    (dict(raw_mix=1.0), "raw_mix must be in"),
    (dict(network="gru"), "network must be one of"),
    (dict(start="home"), "not a start of the planar env"),
    (dict(env="engine3d", start="fixed"), "not a start of the engine3d env"),
])
def test_bad_recipe_fields_raise(overrides, match):
    with pytest.raises(ValueError, match=match):
        replace(TINY, **overrides)


def test_planar_start_option_reaches_the_env():
    assert dagger.make_run_env(replace(TINY, start="fixed")).cfg.start == "fixed"
    assert dagger.make_run_env(TINY).cfg.start == "random"                          # the authors' starts
    args, cfg = dagger.parse_args(["--profile", "smoke", "--start", "fixed"])
    assert cfg.start == "fixed" and cfg.name.endswith("_fixed_start")


def test_short_interventions_padded_are_kept_with_their_padded_steps_out_of_the_loss(two_workers, tmp_path,
                                                                                     monkeypatch):
    """short_interventions='pad' (the authors' lever runs): an intervention shorter than H is kept at collection,
    every one of its steps starts a chunk that repeats its last action past its end with those steps masked,
    and the noised arms draw states there too; 'drop' (the paper's rule) keeps neither."""
    H, pad_cfg = TINY.horizon, replace(TINY, short_interventions="pad")
    D = run_folder.load_episodes(os.path.join(two_workers, "lineage_0/round_1/D.npz"))
    ep = max(D, key=lambda e: len(e["expert"]))
    free = np.flatnonzero(~ep["expert"][1:-1]) + 1                     # policy-driven steps inside the episode
    s0 = int(free[np.flatnonzero(~ep["expert"][free - 1] & ~ep["expert"][free + 2])[0]])
    short = {**ep, "expert": ep["expert"].copy()}
    short["expert"][s0:s0 + 2] = True                                   # a 2-step intervention, H > 2
    only_short = {**ep, "expert": np.zeros_like(ep["expert"])}
    only_short["expert"][s0:s0 + 2] = True

    obs, chunks, mask = diffusion.chunk_dataset([short], H, pad=True)
    first = np.flatnonzero((obs == short["obs"][s0]).all(axis=1))[0]
    assert mask[first].tolist() == [True, True] + [False] * (H - 2)
    assert np.allclose(chunks[first, 2:], short["action"][s0 + 1])     # padded with the run's last action
    assert len(obs) == short["expert"].sum()                            # every expert step starts a chunk
    assert not (diffusion.chunk_dataset([short], H)[0] == short["obs"][s0]).all(axis=1).any()  # the paper: dropped

    demos = run_folder.load_episodes(os.path.join(two_workers, "data/D0.npz"))
    stats = dagger.demo_statistics(TINY, demos)
    assert len(dagger.intervention_sampler(TINY, "hg_dagger", [[short]], None, stats)(64, np.random.default_rng(0))) == 2
    o, c, m = dagger.intervention_sampler(pad_cfg, "hg_dagger", [[short]], None, stats)(256, np.random.default_rng(0))
    assert m.all(axis=1).mean() < 1 and m[:, 0].all()
    cal = calibrate.Calibration.from_dict(run_folder.read_json(os.path.join(two_workers,
                                                                       "lineage_0/round_1/calibration.json")))
    noised = {c.short_interventions: dagger.intervention_sampler(c, "fixed_4", [[short]], cal, stats).samplers[0]
              for c in (TINY, pad_cfg)}
    assert len(noised["pad"].center) == short["expert"].sum()
    assert len(noised["drop"].center) == diffusion.label_mask(short["expert"], H).sum()

    def fake_rollout(env_list, policy, n_act, gen, oracle=None, log=None, seed=0):
        return [{**short, "expert": short["expert"].copy()}, {**only_short, "expert": only_short["expert"].copy()}]
    monkeypatch.setattr(dagger, "rollout", fake_rollout)
    policy = type("Stub", (), {"device": "cpu"})()
    for cfg, kept in ((TINY, 1), (pad_cfg, 2)):
        run = run_folder.Run(str(tmp_path / cfg.short_interventions), cfg)
        got = dagger.collect_interventions(run, 0, 1, policy, np.zeros((TINY.eval_scenarios, 1), bool))
        assert len(got) == kept and bool(got[0]["expert"][s0]) == (cfg is pad_cfg)
    args, cfg = dagger.parse_args(["--profile", "table2", "--short-interventions", "pad"])
    assert cfg.short_interventions == "pad" and cfg.name == "table2_pad_short"
    with pytest.raises(ValueError, match="short_interventions must be 'drop'"):
        replace(TINY, short_interventions="keep")


def test_seed_replicates_train_every_lineage_on_lineage_0s_interventions_with_its_own_training_seed(
        tmp_path, trained_stages):
    """replicates='seeds' (the authors' lever runs: training seeds on one intervention set): lineage 1 collects
    and calibrates nothing of its own -- it trains on lineage 0's D_1, D_2 (D_2 collected by lineage 0's round-1
    policy) and calibrations -- but every arm is trained again with its own seed; the table says what a lineage
    is; the closed-loop row, which collects its own chain, is refused. Lineage 0 is the same run under both
    designs: --copy-from an independent-lineages folder brings lineage 0 (not lineage 1) and only lineage 1
    trains."""
    cfg = replace(TINY, rounds=2, lineages=2, methods=("bc", "hg_dagger", "fixed_4"), replicates="seeds")
    src = str(tmp_path / "lineages")
    dagger.run_experiment(replace(cfg, replicates="lineages", methods=("bc", "hg_dagger")), src)
    trained_stages.clear()  # from here on: the seeds run's own training
    root = str(tmp_path / "seeds")
    dagger.run_experiment(cfg, root, copy_src=src)
    assert sorted(trained_stages) == sorted([f"lineage_0/round_{k}/checkpoints/fixed_4.pt" for k in (1, 2)]
                                     + [f"lineage_1/round_{k}/checkpoints/{m}.pt" for k in (1, 2)
                                        for m in ("hg_dagger", "fixed_4")])
    assert not any("lineage_1" in name for name in os.listdir(os.path.join(root, "timings"))
                   if name.startswith("collect"))
    l0, l1 = (os.path.join(root, f"lineage_{l}") for l in (0, 1))
    for k in (1, 2):
        assert os.path.exists(os.path.join(l0, f"round_{k}", "D.npz"))
        assert os.path.exists(os.path.join(l0, f"round_{k}", "calibration.json"))
        assert not os.path.exists(os.path.join(l1, f"round_{k}", "D.npz"))
        assert not os.path.exists(os.path.join(l1, f"round_{k}", "calibration.json"))
        for m in ("hg_dagger", "fixed_4"):
            a, b = (torch.load(os.path.join(l, f"round_{k}", "checkpoints", f"{m}.pt"), weights_only=True)["state_dict"]
                    for l in (l0, l1))
            assert any(not torch.equal(a[n], b[n]) for n in a)  # another training seed, another policy
            assert os.path.exists(os.path.join(l1, f"round_{k}", "eval", f"{m}.json"))
    results = json.load(open(os.path.join(root, "results.json")))
    assert set(results["success"]["fixed_4"]) == {"0", "1"}
    assert "A lineage here is a training seed" in open(os.path.join(root, "table.md")).read()
    args, named = dagger.parse_args(["--profile", "table2", "--replicates", "seeds"])
    assert named.replicates == "seeds" and named.name == "table2_seed_replicates"
    with pytest.raises(ValueError, match="closed_loop row, which collects|collects its own chain"):
        replace(cfg, methods=("bc", "hg_dagger", "closed_loop"))
    with pytest.raises(ValueError, match="replicates must be 'lineages'"):
        replace(TINY, replicates="trainings")
