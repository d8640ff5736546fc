"""The paper's steps as plain functions: called one by one with hand-made inputs, as in a notebook (no run folder),
they give what the run gives through the harness's memo (experiment/run_folder.Run.memo), bit for bit."""
import os
from dataclasses import replace

import numpy as np
import pytest
import torch

import calibrate
import dagger
import envs
from experiment import cpu_kernels, run_folder, workers
from helpers import straight_line_episode  # tests/helpers.py

CFG = dagger.Config(name="steps", n_demos=3, rounds=1, lineages=1, K=5, down_dims=(8, 16), bc_steps=20,
                    finetune_steps=10, batch_size=16, methods=("bc", "hg_dagger", "pooled"), eval_scenarios=2,
                    eval_repeats=1, eval_unseen=False)


def hand_made_data():
    """D0: three straight-line demonstrations (expert throughout); D_1: two episodes, the expert from step 5 on."""
    env = envs.make_env("planar")
    demos = [straight_line_episode(env, s, expert_from=0) for s in env.train_seeds(3)]
    interventions = [straight_line_episode(env, s, expert_from=5) for s in env.eval_seeds()[:2]]
    return demos, interventions


def weights(policy):
    return {k: v.clone() for k, v in policy.state_dict().items()}


def same(a, b):
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.slow
def test_three_steps_called_as_in_a_notebook_equal_the_harness(tmp_path, monkeypatch):
    """behavior_cloning, fine_tune (the HG-DAgger row) and evaluation with hand-made D0 and D_1 and no folder: pi_0
    keeps its AdamW state for the arms, an arm leaves pi_0 as it was, nothing is written; the same calls through a
    run folder's memo give the same weights and successes. Fails if a step needs the run folder, if an arm does not
    continue pi_0's optimizer (or moves pi_0 itself), or if the harness computes anything the step does not but
    swap the CPU kernels into the policy it trains and give pi_0 its two torch threads (here the same: `fit`,
    torch_threads)."""
    monkeypatch.chdir(tmp_path)  # a step that wrote a file would write it here
    torch.set_num_threads(1)
    demos, interventions = hand_made_data()
    stats = dagger.demo_statistics(CFG, demos)
    lines = []

    def fit(policy, *args, **kwargs):  # the harness's swap (Run.train), without its files
        return dagger.train_policy(cpu_kernels.use_kernels(policy), *args, **kwargs)

    with workers.torch_threads(run_folder.PI0_THREADS):  # as the harness trains pi_0 (Run.memo)
        pi0 = dagger.behavior_cloning(CFG, demos, log=lines.append, fit=fit)
    assert pi0.train_state["step"] == CFG.bc_steps and pi0.train_state["optimizer"]["state"]
    before = weights(pi0)
    hg = dagger.fine_tune(CFG, 0, 1, "hg_dagger", demos, pi0, [interventions], None, stats, log=lines.append,
                          fit=fit)
    assert same(weights(pi0), before)  # pi_0 is as it was, for the next arm
    assert not same(weights(hg), before)  # the arm trained
    ok = dagger.evaluation(CFG, hg, "hg_dagger", "eval", log=lines.append)
    assert np.shape(ok["success"]) == (CFG.eval_scenarios, CFG.eval_repeats)
    assert ok["seeds"] == list(envs.eval_seeds()[:CFG.eval_scenarios])
    assert os.listdir(tmp_path) == []  # no folder, no file
    assert any(line.startswith("BC: 20 steps") for line in lines)

    run = run_folder.Run(str(tmp_path / "run"), CFG)
    pi0_run = run.memo("checkpoints/bc.pt", dagger.behavior_cloning, CFG, demos, log=run.log)
    hg_run = run.memo("lineage_0/round_1/checkpoints/hg_dagger.pt", dagger.fine_tune, CFG, 0, 1, "hg_dagger", demos,
                      pi0_run, [interventions], None, stats, log=run.log)
    ok_run = run.memo("lineage_0/round_1/eval/hg_dagger.json", dagger.evaluation, CFG, hg_run, "hg_dagger", "eval",
                      log=run.log)
    assert same(weights(pi0_run), before) and same(weights(hg_run), weights(hg)) and ok_run == ok
    # ... and from the files, as a resumed run reads them
    again = run_folder.Run(str(tmp_path / "run"), CFG)
    assert same(weights(again.memo("checkpoints/bc.pt", None)), before)
    assert same(weights(again.memo("lineage_0/round_1/checkpoints/hg_dagger.pt", None)), weights(hg))


@pytest.mark.slow
def test_the_loop_runs_without_a_folder_and_returns_table_i_rows(tmp_path, monkeypatch):
    """policy_calibrated_dagger as a notebook calls it: no memo, no map, no folder; every step a plain call, here,
    nothing written, and what it made comes back: pi_0, D_1, the calibration, each row's policy and success, and
    Table I's cells from them. Fails if the loop drops a row, a round's data or calibration from its return, or if
    table() is not the mean success of each row's evaluations in percent."""
    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    seen = []
    real = dagger.evaluation
    monkeypatch.setattr(dagger, "evaluation", lambda *a, **k: seen.append(a[2]) or real(*a, **k))
    cfg = replace(CFG, n_demos=2, bc_steps=10, finetune_steps=4, lineages=2, methods=("bc", "hg_dagger", "pooled"))
    made = dagger.policy_calibrated_dagger(cfg, log=lambda m: None)
    assert seen == ["pi_0 (BC)", "bc", "hg_dagger (lineage 0, K=1)", "pooled (lineage 0, K=1)",
                    "hg_dagger (lineage 1, K=1)", "pooled (lineage 1, K=1)"]
    assert os.listdir(tmp_path) == []
    assert len(made.demos) == 2 and made.pi0.train_state["step"] == cfg.bc_steps
    assert made.pi0_success.shape == made.bc[1].shape == (cfg.eval_scenarios, cfg.eval_repeats)
    assert sorted(made.rows) == [(lin, 1, m) for lin in (0, 1) for m in ("hg_dagger", "pooled")]
    assert sorted(made.data) == sorted(made.calibrations) == [(0, 1), (1, 1)]
    assert all(ep["expert"].any() for ep in made.data[0, 1])  # D_1: episodes with kept interventions
    assert isinstance(made.calibrations[0, 1], calibrate.Calibration) and made.calibrations[0, 1].W is not None
    table = made.table()
    assert sorted(table) == ["bc", "hg_dagger", "pooled"] and table["bc"] == {0: [100.0 * made.bc[1].mean()]}
    for method in ("hg_dagger", "pooled"):
        policy, success = made.rows[1, 1, method]
        assert isinstance(policy, dagger.diffusion.DiffusionPolicy) and success.dtype == bool
        assert table[method] == {1: [100.0 * made.rows[lin, 1, method][1].mean() for lin in (0, 1)]}


def test_the_harness_swap_samples_what_the_plain_policy_samples():
    """The CPU kernels and the FiLM table the harness swaps into a policy (cpu_kernels.use_kernels, in Run.train and
    the checkpoint loader) compute the same eps_theta: a trained policy samples the same chunks before and after the
    swap, to float rounding. Fails if the swap changed the function (a wrong table, a kernel off by a term)."""
    torch.set_num_threads(1)
    demos, _ = hand_made_data()
    plain = dagger.behavior_cloning(replace(CFG, network="mlp", mlp_width=32, mlp_blocks=2), demos, log=lambda m: None)
    swapped = cpu_kernels.use_kernels(dagger.copy_policy(plain))
    assert type(swapped.ema_net) is not type(plain.ema_net)  # the FiLM table is in
    obs = np.stack([d["obs"][0] for d in demos])
    a, b = (p.sample(obs, generator=torch.Generator().manual_seed(3)) for p in (plain, swapped))
    assert np.allclose(a, b, rtol=0, atol=1e-4)


def test_a_steps_seed_is_the_master_seed_and_its_name_through_numpy_seed_sequence():
    """dagger.stage_seed: stable across runs (the files a resumed run reads were made with it), one per step name and
    keys, one per master seed. Fails if the keys' bytes, their order, or the master seed stop entering the seed."""
    word = lambda text: int.from_bytes(text.encode()[:8].ljust(8, b"\0"), "little")  # noqa: E731
    expect = int(np.random.SeedSequence([CFG.seed, word("train"), 0, 1, word("pooled")]).generate_state(1)[0])
    assert dagger.stage_seed(CFG, "train", 0, 1, "pooled") == expect
    seeds = {dagger.stage_seed(CFG, "train", 0, 1, m) for m in ("pooled", "fixed_4", "hg_dagger")}
    assert len(seeds) == 3 and dagger.stage_seed(CFG, 1, 0) != dagger.stage_seed(CFG, 0, 1)
    assert dagger.stage_seed(replace(CFG, seed=1), "bc") != dagger.stage_seed(CFG, "bc")


@pytest.mark.slow
def test_table_is_bc_cell_is_the_bc_rows_own_policy_not_pi0(tmp_path, monkeypatch):
    """Table I's BC row is pi_0 continued on D0 alone for the arms' budget (bc_row_arm), evaluated on its own: its
    cell is that policy's success, not pi_0's. The BC row here is stood in for by a policy that solves everything;
    pi_0 of this tiny run solves nothing. Fails if the loop or Made.table() takes pi_0's success for the BC cell."""
    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    cfg = replace(CFG, n_demos=2, bc_steps=10, finetune_steps=4, methods=("bc", "hg_dagger"))
    solved = np.ones((cfg.eval_scenarios, cfg.eval_repeats), bool)
    monkeypatch.setattr(dagger, "bc_row_arm", lambda cfg, demos, pi0, *rest: (pi0, solved))
    made = dagger.policy_calibrated_dagger(cfg, log=lambda m: None)
    assert not made.pi0_success.all()  # the case tells the two rules apart
    assert made.table()["bc"] == {0: [100.0]}


def test_the_rounds_intervention_rows_share_a_batch_equally_not_by_their_sizes():
    """A fine-tuning batch's intervention rows come from rounds 1..k in equal shares (the authors'; dagger's
    intervention_sampler and the harness's controls.Rows alike), however many frames each round kept: a round of
    two episodes and one of six each give half. Fails if the shares follow the rounds' sizes."""
    from experiment import controls
    env = envs.make_env("planar")
    small = [straight_line_episode(env, s, expert_from=5) for s in env.eval_seeds()[:2]]
    big = [straight_line_episode(env, s, expert_from=5) for s in env.eval_seeds()[2:8]]
    demos, _ = hand_made_data()
    stats = dagger.demo_statistics(CFG, demos)
    assert sum(ep["expert"].sum() for ep in big) > 2 * sum(ep["expert"].sum() for ep in small)
    for method in ("hg_dagger", "fixed_4"):
        for mixture in (dagger.intervention_sampler(CFG, method, [small, big], None, stats),
                        controls.Rows()(CFG, method, [small, big], None, stats, envs.make_env)):
            np.testing.assert_allclose(mixture.p, [0.5, 0.5])
            assert len(mixture.samplers) == 2
