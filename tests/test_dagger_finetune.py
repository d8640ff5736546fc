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


@pytest.mark.parametrize("overrides,match", [
    (dict(finetune="warm"), "finetune must be 'continue'"),
    (dict(finetune="continue", finetune_lr=1e-4), "finetune_lr"),
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
