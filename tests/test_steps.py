"""The paper's steps as plain functions: called one by one with hand-made inputs, as in a notebook (no run folder),
they give what the run gives through the harness's memo (experiment/run_folder.Run.memo), bit for bit."""
import os
from dataclasses import replace

import numpy as np
import pytest
import torch

import dagger
import envs
from experiment import run_folder
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
    continue pi_0's optimizer (or moves pi_0 itself), or if the harness computes anything the step does not."""
    monkeypatch.chdir(tmp_path)  # a step that wrote a file would write it here
    torch.set_num_threads(1)
    demos, interventions = hand_made_data()
    stats = dagger.demo_statistics(CFG, demos)
    lines = []

    pi0 = dagger.behavior_cloning(CFG, demos, log=lines.append)
    assert pi0.train_state["step"] == CFG.bc_steps and pi0.train_state["optimizer"]["state"]
    before = weights(pi0)
    hg = dagger.fine_tune(CFG, 0, 1, "hg_dagger", demos, pi0, [interventions], None, stats, log=lines.append)
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
def test_the_loop_runs_without_a_folder(tmp_path, monkeypatch):
    """policy_calibrated_dagger with no memo and no map: every step a plain call, here, nothing written."""
    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    made = []
    real = dagger.evaluation
    monkeypatch.setattr(dagger, "evaluation", lambda *a, **k: made.append(a[2]) or real(*a, **k))
    dagger.policy_calibrated_dagger(replace(CFG, n_demos=2, bc_steps=10, finetune_steps=4), [0], log=lambda m: None)
    assert made == ["pi_0 (BC)", "bc", "hg_dagger (lineage 0, K=1)", "pooled (lineage 0, K=1)"]
    assert os.listdir(tmp_path) == []
