"""experiment/lever.py, the authors' lever recipe (a research variant): pi_0 at the end of its own cosine and every
arm at a constant lr / 10 from its optimizer state, the BC row pi_0 itself, round shares by frames, short
interventions padded with their padded steps out of the loss, and seed replicates on lineage 0's interventions."""
import json
import os
from dataclasses import replace

import numpy as np
import pytest
import torch

import dagger
import diffusion
import envs
from experiment import cli, lever, profiles, report, run_folder

TINY = dagger.Config(name="tiny", n_demos=4, rounds=1, lineages=1, K=5, network="mlp",
                     mlp_width=16, mlp_blocks=1, bc_steps=30, finetune_steps=12, batch_size=32,
                     methods=("bc", "hg_dagger", "fixed_4", "pooled"), eval_scenarios=3, eval_repeats=1,
                     eval_unseen=False)
LEVER = replace(TINY, recipe="authors_lever")


def lever_sampler(*args):
    """The recipe's intervention rows (what the harness hands the loop as its sampler) for dagger's arguments."""
    return lever.loop_arguments(LEVER)["sampler"](*args, envs.make_env)


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory):
    """A finished tiny run of the paper's recipe: its D0, interventions and calibration feed the samplers below."""
    root = str(tmp_path_factory.mktemp("paper"))
    report.run_experiment(TINY, root, workers=1)
    return root


def load(root, name):
    return run_folder.load_episodes(os.path.join(root, name))


def test_the_recipe_continues_pi0s_optimizer_at_a_tenth_of_its_peak_and_keeps_pi0_as_the_bc_row(tmp_path,
                                                                                                 monkeypatch):
    """Fails if pi_0's cosine spans the arms' steps (the paper's recipe), if an arm restarts its optimizer or runs a
    schedule instead of lr / 10 at every step, or if the BC row is trained on (the authors' lever BC row is pi_0)."""
    cfg = replace(LEVER, methods=("bc", "hg_dagger"))
    root = str(tmp_path / "lever")
    made, real = [], dagger.train_config
    monkeypatch.setattr(dagger, "train_config", lambda *a, **kw: made.append(real(*a, **kw)) or made[-1])
    resumed, real_train = [], run_folder.Run.train
    monkeypatch.setattr(run_folder.Run, "train", lambda self, name, *a, **kw: resumed.append(
        (name, kw.get("start") is not None)) or real_train(self, name, *a, **kw))
    report.run_experiment(cfg, root)
    pi0 = torch.load(os.path.join(root, "checkpoints", "bc.pt"), weights_only=True)["train_state"]
    assert pi0["step"] == cfg.bc_steps and pi0["optimizer"]["state"]
    assert json.loads(pi0["train_config"])["lr_schedule"] == "AuthorsLeverLR"
    bc_tc, arm_tc = made  # pi_0, then the HG-DAgger arm
    assert bc_tc.lr_schedule == arm_tc.lr_schedule == lever.AuthorsLeverLR(cfg.bc_steps)
    assert bc_tc.steps == cfg.bc_steps and arm_tc.steps == cfg.bc_steps + cfg.finetune_steps  # from pi_0's step
    lr = [diffusion.lr_at(step, arm_tc) for step in range(arm_tc.steps)]
    warmup = min(500, cfg.bc_steps // 10)  # pi_0's own warm-up and cosine, over bc_steps
    assert lr[:warmup] == pytest.approx([cfg.lr * (s + 1) / warmup for s in range(warmup)]) and lr[warmup] == cfg.lr
    assert lr[cfg.bc_steps - 1] < 0.01 * cfg.lr and all(np.diff(lr[warmup:cfg.bc_steps]) < 0)
    assert lr[cfg.bc_steps:] == [cfg.lr / 10] * cfg.finetune_steps  # no warm-up, no cosine: a tenth of the peak
    assert resumed == [("checkpoints/bc.pt", False), ("lineage_0/round_1/checkpoints/hg_dagger.pt", True)]
    assert not os.path.exists(os.path.join(root, "checkpoints", "bc_continued.pt"))
    row = json.load(open(os.path.join(root, "eval", "bc.json")))["success"]
    assert row == json.load(open(os.path.join(root, "eval", "pi0.json")))["success"]  # pi_0 itself, the same draws
    args, named = cli.parse_args(["--profile", "table2", "--recipe", "authors_lever"])
    assert named.recipe == "authors_lever" and named.name == "table2_authors_lever"


@pytest.mark.slow
def test_round_shares_by_frames_weigh_each_round_by_its_intervention_frames(paper_run):
    D, demos = load(paper_run, "lineage_0/round_1/D.npz"), load(paper_run, "data/D0.npz")
    stats = dagger.demo_statistics(TINY, demos)
    small = D[:1]
    frames = np.array([sum(int(ep["expert"].sum()) for ep in x) for x in (D, small)], float)
    assert frames[0] > frames[1]
    assert np.allclose(dagger.intervention_sampler(TINY, "hg_dagger", [D, small], None, stats).p, 0.5)  # the paper's
    by_frames = lever_sampler(LEVER, "hg_dagger", [D, small], None, stats)
    assert np.allclose(by_frames.p, frames / frames.sum())
    cal = run_folder.calibration_from_json(run_folder.read_json(os.path.join(paper_run,
                                                                       "lineage_0/round_1/calibration.json")))
    assert np.allclose(lever_sampler(LEVER, "fixed_4", [D, small], cal, stats).p, frames / frames.sum())


@pytest.mark.slow
def test_short_interventions_are_kept_with_their_padded_steps_out_of_the_loss(paper_run, tmp_path, monkeypatch):
    """An intervention shorter than H is kept at collection, every one of its steps starts a chunk that repeats its
    last action past its end with those steps masked, and the noised arms draw states there too; the paper's recipe
    keeps neither (Sec. IV-C)."""
    H = TINY.horizon
    D = load(paper_run, "lineage_0/round_1/D.npz")
    ep = max(D, key=lambda e: len(e["expert"]))
    free = np.flatnonzero(~ep["expert"][1:-1]) + 1                     # policy-driven steps inside the episode
    s0 = int(free[np.flatnonzero(~ep["expert"][free - 1] & ~ep["expert"][free + 2])[0]])
    short = {**ep, "expert": ep["expert"].copy()}
    short["expert"][s0:s0 + 2] = True                                   # a 2-step intervention, H > 2
    only_short = {**ep, "expert": np.zeros_like(ep["expert"])}
    only_short["expert"][s0:s0 + 2] = True

    obs, chunks, mask = lever.padded_chunks([short], H)
    first = np.flatnonzero((obs == short["obs"][s0]).all(axis=1))[0]
    assert mask[first].tolist() == [True, True] + [False] * (H - 2)
    assert np.allclose(chunks[first, 2:], short["action"][s0 + 1])     # padded with the run's last action
    assert len(obs) == short["expert"].sum()                            # every expert step starts a chunk
    assert not (diffusion.chunk_dataset([short], H)[0] == short["obs"][s0]).all(axis=1).any()  # the paper: dropped

    stats = dagger.demo_statistics(TINY, load(paper_run, "data/D0.npz"))
    recorded = dagger.intervention_sampler(TINY, "hg_dagger", [[short]], None, stats)
    assert len(recorded(64, np.random.default_rng(0))) == 2  # the paper's rows carry no loss mask
    o, c, m = lever_sampler(LEVER, "hg_dagger", [[short]], None, stats)(256, np.random.default_rng(0))
    assert m.all(axis=1).mean() < 1 and m[:, 0].all()
    cal = run_folder.calibration_from_json(run_folder.read_json(os.path.join(paper_run,
                                                                       "lineage_0/round_1/calibration.json")))
    padded = lever_sampler(LEVER, "fixed_4", [[short]], cal, stats).samplers[0]
    paper = dagger.intervention_sampler(TINY, "fixed_4", [[short]], cal, stats).samplers[0]
    assert len(padded.center) == short["expert"].sum()
    assert len(paper.center) == diffusion.label_mask(short["expert"], H).sum()

    def fake_rollout(env_list, policy, n_act, gen, oracle=None, log=None, seed=0):
        return [{**short, "expert": short["expert"].copy()}, {**only_short, "expert": only_short["expert"].copy()}]
    monkeypatch.setattr(dagger, "rollout", fake_rollout)
    policy = type("Stub", (), {"device": "cpu"})()
    for cfg, kept, rule in ((TINY, 1, diffusion.expert_runs), (LEVER, 2, lever.every_run)):
        got = dagger.collect_interventions(cfg, (0, 1), policy, np.zeros((TINY.eval_scenarios, 1), bool),
                                           label_rule=rule)
        assert len(got) == kept and bool(got[0]["expert"][s0]) == (cfg is LEVER)


@pytest.mark.slow
def test_seed_replicates_train_every_lineage_on_lineage_0s_interventions_with_its_own_training_seed(
        tmp_path, trained_stages):
    """authors_lever_seeds: lineage 1 collects and calibrates nothing of its own -- it trains on lineage 0's D_1, D_2
    and calibrations -- but every arm is trained again with its own seed; the table says what a lineage is; the
    closed-loop row, which collects its own chain, is refused; lineage 1 alone before lineage 0 is refused.
    Lineage 0 is the same run under both designs: --copy-from an authors_lever folder brings lineage 0 (not
    lineage 1) and only lineage 1 (and the added row) trains."""
    cfg = replace(TINY, rounds=2, lineages=2, methods=("bc", "hg_dagger", "fixed_4"), recipe="authors_lever_seeds")
    with pytest.raises(run_folder.RunFolderError, match="run lineage 0 first"):
        report.run_experiment(cfg, str(tmp_path / "early"), lineage=1)
    src = str(tmp_path / "lineages")
    report.run_experiment(replace(cfg, recipe="authors_lever", methods=("bc", "hg_dagger")), src)
    trained_stages.clear()  # from here on: the seeds run's own training
    root = str(tmp_path / "seeds")
    report.run_experiment(cfg, root, copy_src=src)
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
    with pytest.raises(ValueError, match="collects its own chain"):
        profiles.check_config(replace(cfg, methods=("bc", "hg_dagger", "closed_loop")))


@pytest.mark.parametrize("stored,recipe", [
    (dict(finetune="continue", round_shares="equal", short_interventions="drop", replicates="lineages"), "paper"),
    (dict(finetune="constant", round_shares="frames", short_interventions="pad"), "authors_lever"),
    (dict(finetune="constant", round_shares="frames", short_interventions="pad", replicates="seeds"),
     "authors_lever_seeds"),
])
def test_a_stored_config_of_the_four_old_fields_reads_as_its_recipe(stored, recipe):
    """Run folders and results files made before the recipe (table2_authors_finetune, ..._seeds) name four fields;
    each combination that ran a recipe that remains is read as that recipe, any other is refused."""
    assert run_folder.without_retired_fields("here", {"seed": 0, **stored}) == {"seed": 0, "recipe": recipe}
    # the folder name the old options gave (cli.folder_name) reads as the recipe's
    old = "table2" + {"paper": "", "authors_lever": "_constant_frame_shares_pad_short",
                      "authors_lever_seeds": "_constant_frame_shares_pad_short_seed_replicates"}[recipe] + "_hg_dagger-pooled"
    _, cfg = cli.parse_args(["--profile", "table2", "--recipe", recipe, "--methods", "hg_dagger,pooled"])
    assert run_folder.without_retired_fields("here", {**stored, "name": old})["name"] == cfg.name
    with pytest.raises(run_folder.ConfigMismatch, match="a combination no recipe runs now"):
        run_folder.without_retired_fields("here", {**stored, "round_shares": "frames", "finetune": "continue"})


def test_the_recipes_label_rule_keeps_every_intervention_and_shares_go_by_frames():
    """lever.every_run keeps an intervention of one step (the paper's rule drops runs shorter than H), and
    frame_shares weighs rounds by their intervention frames. Fails if a run shorter than 2 steps is dropped, or the
    shares are equal, unnormalized or inverted."""
    expert = np.array([0, 1, 0, 1, 1, 0, 1], bool)
    assert [tuple(r) for r in lever.every_run(expert, 20)] == [(1, 2), (3, 5), (6, 7)]
    assert lever.frame_shares([10, 30]) == [0.25, 0.75] and lever.frame_shares([5]) == [1.0]
