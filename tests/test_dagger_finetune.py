"""dagger.py's fine-tuning (the paper's recipe: every arm continues pi_0's schedule, the authors' planar run), the BC
row, what a noised arm draws, the arms in worker processes; the noise each noised arm's sampler is built with
(Eqs. 14-16 of its own round's calibration, Table I's fixed sigmas). The authors' lever recipe: tests/test_lever.py."""
import json
import os
from dataclasses import replace

import numpy as np
import pytest
import torch

import calibrate
import dagger
import envs
import relabel
from experiment import checkpoints, controls, profiles, report, run_folder

TINY = dagger.Config(name="tiny", n_demos=4, rounds=1, lineages=1, K=5, network="mlp",
                     mlp_width=16, mlp_blocks=1, bc_steps=30, finetune_steps=12, batch_size=32,
                     methods=("bc", "hg_dagger", "fixed_4", "pooled"), eval_scenarios=3, eval_repeats=1,
                     eval_unseen=False)


@pytest.fixture(scope="module")
def two_workers(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("workers2"))
    report.run_experiment(TINY, root, workers=2)
    return root


@pytest.mark.slow
def test_continue_saves_pi0_with_its_optimizer_and_the_bc_row_continues_it(two_workers):
    state = torch.load(os.path.join(two_workers, "checkpoints", "bc.pt"), weights_only=True)["train_state"]
    assert state["step"] == TINY.bc_steps and state["optimizer"]["state"]          # AdamW moments kept
    assert json.loads(state["train_config"])["schedule_steps"] == TINY.bc_steps + TINY.finetune_steps
    pi0 = checkpoints.load_policy(os.path.join(two_workers, "checkpoints", "bc.pt")).state_dict()
    row = checkpoints.load_policy(os.path.join(two_workers, "checkpoints", "bc_continued.pt")).state_dict()
    assert any(not torch.equal(pi0[k], row[k]) for k in pi0 if k.startswith("net."))
    assert os.path.isfile(os.path.join(two_workers, "eval", "pi0.json"))          # round 1's collector
    assert os.path.isfile(os.path.join(two_workers, "eval", "bc.json"))           # the table's BC row
    assert "pi_0 continued on D0 alone" in open(os.path.join(two_workers, "log.txt")).read()


@pytest.mark.slow
def test_worker_processes_give_the_numbers_of_one_process(two_workers, tmp_path):
    root = str(tmp_path / "one")
    report.run_experiment(TINY, root, workers=1)
    a = json.load(open(os.path.join(two_workers, "results.json")))
    b = json.load(open(os.path.join(root, "results.json")))
    assert a["success"] == b["success"]
    for m in ("hg_dagger", "fixed_4", "pooled"):
        wa = checkpoints.load_policy(os.path.join(two_workers, "lineage_0/round_1/checkpoints", f"{m}.pt"))
        wb = checkpoints.load_policy(os.path.join(root, "lineage_0/round_1/checkpoints", f"{m}.pt"))
        assert all(torch.equal(v, wb.state_dict()[k]) for k, v in wa.state_dict().items())
    assert "2 jobs (train_and_evaluate) in 2 worker processes" in open(os.path.join(two_workers, "log.txt")).read()
    # D0 planned in batches by the two workers is the one process's, in scenario order (a batch given the wrong
    # scenarios would fail; its jobs are of equal length and finish in order: results taken in the order they
    # finished would pass here, tests/test_workers.py catches them)
    assert f"{TINY.n_demos} jobs (plan_demonstrations) in 2 worker processes" in open(
        os.path.join(two_workers, "log.txt")).read()
    da = run_folder.load_episodes(os.path.join(two_workers, "data/D0.npz"))
    db = run_folder.load_episodes(os.path.join(root, "data/D0.npz"))
    assert [d["seed"] for d in da] == [d["seed"] for d in db] == envs.train_seeds(TINY.n_demos)
    assert all(np.array_equal(a[k], b[k]) for a, b in zip(da, db) for k in ("obs", "q", "action"))


def test_d0_skips_a_scenario_the_oracle_cannot_plan_and_plans_the_next_one(tmp_path, monkeypatch):
    """D0 is the first n_demos training scenarios the oracle can plan: an unplannable one (here the second) is
    replaced by the scenario after the last one tried, not by a repeat of one already in D0."""
    demonstrate = dagger.oracle_mod.Oracle.demonstrate

    def fails_on_scenario_1(self, env, seed):
        if seed == 1:
            raise dagger.oracle_mod.PlanningFailed("no plan (test)")
        return demonstrate(self, env, seed)

    monkeypatch.setattr(dagger.oracle_mod.Oracle, "demonstrate", fails_on_scenario_1)
    run = run_folder.Run(str(tmp_path / "d0"), replace(TINY, n_demos=3))
    demos = dagger.oracle_demonstrations(run.cfg, log=run.log)
    assert [d["seed"] for d in demos] == [0, 2, 3]
    assert "demos 3/3 | " in open(os.path.join(run.root, "log.txt")).read() and "1 unplannable" in open(
        os.path.join(run.root, "log.txt")).read()


@pytest.mark.slow
def test_hg_dagger_draws_the_recorded_chunks_and_a_noised_arm_only_noised_states(two_workers):
    D = run_folder.load_episodes(os.path.join(two_workers, "lineage_0/round_1/D.npz"))
    demos = run_folder.load_episodes(os.path.join(two_workers, "data/D0.npz"))
    stats = dagger.demo_statistics(TINY, demos)
    cal = run_folder.calibration_from_json(run_folder.read_json(os.path.join(two_workers,
                                                                       "lineage_0/round_1/calibration.json")))
    kinds = lambda s: [type(x).__name__ for x in s.samplers]
    hg = dagger.intervention_sampler(TINY, "hg_dagger", [D, D], None, stats)
    assert kinds(hg) == ["ChunkSampler"] * 2 and np.allclose(hg.p, 0.5)
    code = dagger.intervention_sampler(TINY, "fixed_4", [D, D], cal, stats)       # the authors' code: all noised
    assert kinds(code) == ["AugmentationSampler"] * 2 and np.allclose(code.p, 0.5)
    recorded = relabel.ChunkSampler(D, TINY.horizon)
    is_recorded = lambda rows: np.array([any(np.array_equal(o, r) for r in recorded.obs) for o in rows])
    assert is_recorded(hg(100, np.random.default_rng(0))[0]).all()
    assert not is_recorded(code(100, np.random.default_rng(0))[0]).any()  # the authors' code: every row noised


@pytest.mark.parametrize("overrides,match", [
    (dict(recipe="restart"), "recipe must be one of paper, authors_lever"),  # 'restart': deleted, not adopted
    (dict(network="gru"), "network must be one of"),
])
def test_bad_recipe_fields_raise(overrides, match):
    """Fails if a recipe or network this code does not run passes the config's check (where a config enters)."""
    with pytest.raises(ValueError, match=match):
        profiles.check_config(replace(TINY, **overrides))


# ---- each noised arm's sampler gets its own round's noise (Eqs. 14-16, Table I's rows) -------------------------
def synthetic_rounds(dof=3, H=TINY.horizon):
    """Two rounds of intervention episodes (2 and 3 episodes, of different lengths) with one intervention of
    2H steps each: no env is made until a sampler draws, and these tests only build samplers."""
    rounds, seed = [], 100
    for n_episodes in (2, 3):
        D = []
        for _ in range(n_episodes):
            T = 3 * H + seed % 7
            expert = np.zeros(T, bool)
            expert[5:5 + 2 * H] = True
            q = np.cumsum(np.full((T, dof), 0.02), axis=0) + 0.01 * seed
            D.append({"obs": np.zeros((T, 2 * dof + 2), np.float32), "q": q, "action": np.roll(q, -1, axis=0),
                      "expert": expert, "seed": seed})
            seed += 1
        rounds.append(D)
    return rounds


def synthetic_calibration(episodes, W, seed=0):
    """A calibrate.Calibration of `episodes` (the rounds' episodes concatenated, as calibrate_noise passes them)
    measured at every step: a random Sigma_hat_t per step (trace ~2e-4 rad^2, so ||W||^2 = W^2 rescales it by a
    large factor), Sigma^alpha_t and the pooled Sigma_bar^alpha by calibrate.py (as calibrate.calibrate makes
    them)."""
    rng = np.random.default_rng(seed)
    dof = episodes[0]["q"].shape[1]
    episode_index = np.concatenate([np.full(len(ep["q"]), e) for e, ep in enumerate(episodes)])
    timestep = np.concatenate([np.arange(len(ep["q"])) for ep in episodes])
    A = rng.normal(scale=0.005, size=(len(timestep), dof, dof))
    sigma_hat = A @ np.swapaxes(A, 1, 2) + 1e-6 * np.eye(dof)                   # (M, dof, dof) rad^2
    empty = np.zeros(0)
    return calibrate.Calibration(W=W, r=None, fit_note="fit", median_step=0.02, sigma_hat=sigma_hat,
                                 sigma_alpha=calibrate.calibrated_sigma(sigma_hat, W), episode_index=episode_index,
                                 timestep=timestep, pooled=calibrate.pooled_sigma(sigma_hat, W),
                                 blend_beta=empty, blend_s=empty,
                                 blend_x=empty, blend_kept=np.zeros(0, bool), blend_episode=empty,
                                 blend_start=empty, paper_median_step=envs.PlanarReacher.paper_median_step)


def synthetic_stats(dof=3):
    """DemoStats with our median step 0.02 rad beside the paper's planar 0.0176 rad (fixed sigmas convert)."""
    return relabel.DemoStats(median_step=0.02, accel_max=np.full(dof, 0.01),
                             max_step=np.full(dof, 0.1),
                             paper_median_step=envs.PlanarReacher.paper_median_step, frames_per_step=3.0)


def eq16_pooled(cal):
    """Eqs. (15)-(16) from the calibration's raw measurements, written out here: Sigma_bar = mean_m Sigma_hat_m,
    Sigma_bar^alpha = ||W||^2 / tr(Sigma_bar) Sigma_bar (rad^2; W in rad)."""
    sigma_bar = cal.sigma_hat.mean(axis=0)
    return cal.W ** 2 / np.trace(sigma_bar) * sigma_bar


def eq14_per_step(cal, episode, t):
    """Eq. (14) at step t of calibrated episode `episode`: Sigma^alpha_t = ||W||^2 / tr(Sigma_hat_t) Sigma_hat_t."""
    (row,) = np.flatnonzero((cal.episode_index == episode) & (cal.timestep == t))
    return cal.W ** 2 / np.trace(cal.sigma_hat[row]) * cal.sigma_hat[row]


def sampler_covariances(sampler):
    """(N, dof, dof) rad^2: the covariance L_t L_t^T the sampler draws each of its table's rows with."""
    return sampler.factors @ np.swapaxes(sampler.factors, 1, 2)


def assert_pooled(sampler, expected):
    covs = sampler_covariances(sampler)
    np.testing.assert_allclose(covs, np.broadcast_to(expected, covs.shape), rtol=1e-9, atol=1e-15)


def assert_per_step(sampler, cal, offset):
    """Every row of `sampler` (episode i of its round, step t) has Eq. (14)'s Sigma^alpha_t of calibrated episode
    offset + i (the rounds' episodes are calibrated in order), step t."""
    covs = sampler_covariances(sampler)
    expected = [eq14_per_step(cal, offset + e, t) for e, t in zip(sampler.episode_of, sampler.step_of)]
    np.testing.assert_allclose(covs, np.array(expected), rtol=1e-9, atol=1e-15)


def test_pooled_arm_draws_eq_16_sigma_bar_alpha_scaled_to_w(augmentation_samplers):
    """Fails if the pooled arm's sampler is given anything but Eqs. (15)-(16) of the round's calibration: the
    unscaled Sigma_bar (W's scaling dropped, noise_model returning cal.sigma_hat.mean(0)), another matrix of the
    calibration, or a covariance in other units than rad^2."""
    rounds = synthetic_rounds()
    cal = synthetic_calibration(rounds[0] + rounds[1], W=0.06)
    expected = eq16_pooled(cal)
    unscaled = cal.sigma_hat.mean(axis=0)
    assert np.trace(expected) == pytest.approx(0.06 ** 2)                   # Eq. (16): tr = ||W||^2
    assert np.trace(expected) > 10 * np.trace(unscaled)                      # the scaling matters here
    sampler = dagger.intervention_sampler(TINY, "pooled", rounds, cal, synthetic_stats())
    assert [type(s).__name__ for s in sampler.samplers] == ["AugmentationSampler"] * 2
    assert [b["noise"] for b in augmentation_samplers] == ["pooled", "pooled"]
    for built, D in zip(augmentation_samplers, rounds):
        assert built["episodes"] == D
        np.testing.assert_allclose(built["sigma"], expected, rtol=1e-9)      # what the sampler receives ...
        assert_pooled(built["sampler"], expected)                            # ... and draws with, every row


def test_per_step_arm_draws_eq_14_of_each_episodes_own_steps_across_rounds(augmentation_samplers):
    """Fails if a per_step sampler's row is noised with anything but Eq. (14)'s Sigma^alpha_t of its own episode
    and step: W's scaling dropped (cal.sigma_hat instead of cal.sigma_alpha), the episodes of round 2 indexed from
    0 instead of after round 1's (the offset in intervention_sampler), rounds or episodes swapped, steps shifted."""
    rounds = synthetic_rounds()
    cal = synthetic_calibration(rounds[0] + rounds[1], W=0.06)
    ratio = cal.W ** 2 / np.trace(cal.sigma_hat, axis1=1, axis2=2)
    assert ratio.min() > 5                                                   # the scaling matters at every step
    dagger.intervention_sampler(TINY, "per_step", rounds, cal, synthetic_stats())
    assert [b["noise"] for b in augmentation_samplers] == ["per_step", "per_step"]
    offset = 0
    for built, D in zip(augmentation_samplers, rounds):
        assert built["episodes"] == D
        assert sorted(np.unique(built["sampler"].episode_of)) == list(range(len(D)))  # every episode has rows
        assert_per_step(built["sampler"], cal, offset)
        offset += len(D)


def test_every_noised_arm_gets_its_own_noise(augmentation_samplers):
    """Fails if two arms' noises are swapped (each arm's covariance differs here): pooled and closed_loop get
    Eq. (16)'s Sigma_bar^alpha of their calibration, per_step Eq. (14) per step, fixed_<s> the isotropic (s * paper_median_step)^2 I rad^2 of Table I (sigma in
    the paper's median steps: noise_model hands the sampler s * paper_median_step / median_step of ours),
    the sigma = 0 control (experiment/controls.py) none; hg_dagger builds no noised sampler."""
    rounds = synthetic_rounds()
    cal = synthetic_calibration(rounds[0] + rounds[1], W=0.06)
    stats, dof = synthetic_stats(), 3
    paper = envs.PlanarReacher.paper_median_step
    assert stats.median_step != paper                                        # the unit conversion matters here
    dagger.intervention_sampler(TINY, "hg_dagger", rounds, None, stats)
    assert augmentation_samplers == []
    for method in ("fixed_2", "fixed_16", "zero_noise", "pooled", "closed_loop", "per_step"):
        augmentation_samplers.clear()
        (controls.Rows() if method == "zero_noise" else dagger.intervention_sampler)(TINY, method, rounds, cal, stats,
                                                                                    envs.make_env)
        assert len(augmentation_samplers) == len(rounds), method
        offset = 0
        for built, D in zip(augmentation_samplers, rounds):
            sampler = built["sampler"]
            if method.startswith("fixed_"):
                s = float(method.split("_")[1])
                assert built["noise"] == "isotropic"
                assert_pooled(sampler, (s * paper) ** 2 * np.eye(dof))
            elif method == "zero_noise":
                assert built["noise"] == "isotropic" and np.all(sampler.factors == 0)
            elif method == "per_step":
                assert built["noise"] == "per_step"
                assert_per_step(sampler, cal, offset)
            else:
                assert built["noise"] == "pooled", method
                assert_pooled(sampler, eq16_pooled(cal))
            offset += len(D)


@pytest.mark.slow
def test_each_rounds_noised_arms_get_that_rounds_calibration(tmp_path, monkeypatch, augmentation_samplers):
    """Fails if, in the loop (policy_calibrated_dagger, train_and_evaluate, closed_loop_round), a noised arm of round k is
    given another round's calibration (round 1's or k-1's; the first calibration kept for every round) or another
    chain's: round k's pooled, per_step and fixed arms use the main chain's round-k calibration, the closed_loop
    row round 1's main calibration at K=1 and its own chain's at K=2; and if the closed-loop row's round 1 is not
    made before round 2 starts (a stopped lineage could then export no finished round). Two rounds,
    calibrate.calibrate replaced by a synthetic calibration with its own W per call, no training
    (finetune_from_pi0 hands back pi_0) and no evaluation: only the samplers each arm builds are looked at."""
    cfg = replace(TINY, rounds=2, methods=("bc", "hg_dagger", "fixed_4", "pooled", "per_step", "closed_loop"))
    made = []

    def fake_calibrate(env, policy, episodes, median_step, cal_cfg, generator, log=None):
        made.append(synthetic_calibration(episodes, W=0.05 + 0.02 * len(made), seed=len(made)))
        return made[-1]
    monkeypatch.setattr(calibrate, "calibrate", fake_calibrate)
    calibrations, arms, order = {}, {}, []  # (k, chain): the loop's calibration; (k, method): the arm's samplers
    real_calibrate_noise, real_fine_tune = dagger.calibrate_noise, dagger.fine_tune

    def calibrate_noise(cfg, keys, *args, **kwargs):
        chain = keys[2] if len(keys) > 2 else None
        calibrations[(keys[1], chain)] = real_calibrate_noise(cfg, keys, *args, **kwargs)
        return calibrations[(keys[1], chain)]

    def fine_tune(cfg, lineage, k, method, *args, **kwargs):
        first = len(augmentation_samplers)
        policy = real_fine_tune(cfg, lineage, k, method, *args, **kwargs)
        arms[(k, method)] = augmentation_samplers[first:]
        order.append((k, method))
        return policy
    monkeypatch.setattr(dagger, "calibrate_noise", calibrate_noise)
    monkeypatch.setattr(dagger, "fine_tune", fine_tune)
    monkeypatch.setattr(dagger, "finetune_from_pi0", lambda cfg, pi0, *args, **kwargs: pi0)
    monkeypatch.setattr(dagger, "evaluate_policy", lambda memo, cfg, name, policy, label, log=None, unseen=None,
                        make_env=None: np.zeros((cfg.eval_scenarios, cfg.eval_repeats), bool))
    run = run_folder.Run(str(tmp_path), cfg)
    dagger.policy_calibrated_dagger(cfg, [0], memo=run.memo, log=run.log)

    assert set(calibrations) == {(1, None), (2, None), (2, "closed_loop")}
    assert order.index((1, "closed_loop")) < order.index((2, "hg_dagger"))  # round 1 whole before round 2
    Ws = [c.W for c in calibrations.values()]
    assert len(set(Ws)) == 3                                                 # three distinguishable calibrations
    main = {k: run_folder.load_episodes(str(tmp_path / f"lineage_0/round_{k}/D.npz")) for k in (1, 2)}
    chain_2 = run_folder.load_episodes(str(tmp_path / "lineage_0/round_2/closed_loop/D.npz"))
    for k in (1, 2):
        cal = calibrations[(k, None)]
        assert arms[(k, "hg_dagger")] == []
        for method in ("fixed_4", "pooled", "per_step"):
            assert len(arms[(k, method)]) == k, (k, method)                  # one sampler per round of data
        offset = 0
        for j in range(k):  # the sampler of round j + 1's data
            D = main[j + 1]
            for method in ("fixed_4", "pooled", "per_step"):
                assert [ep["seed"] for ep in arms[(k, method)][j]["episodes"]] == [ep["seed"] for ep in D]
            assert_pooled(arms[(k, "fixed_4")][j]["sampler"], (4 * envs.PlanarReacher.paper_median_step) ** 2 * np.eye(
                D[0]["q"].shape[1]))
            assert_pooled(arms[(k, "pooled")][j]["sampler"], eq16_pooled(cal))
            assert_per_step(arms[(k, "per_step")][j]["sampler"], cal, offset)
            offset += len(D)
    (cl_1,) = arms[(1, "closed_loop")]
    assert_pooled(cl_1["sampler"], eq16_pooled(calibrations[(1, None)]))   # round 1: the main chain's
    cl_2 = arms[(2, "closed_loop")]
    assert [[ep["seed"] for ep in b["episodes"]] for b in cl_2] == [[ep["seed"] for ep in D]
                                                                     for D in (main[1], chain_2)]
    for built in cl_2:
        assert_pooled(built["sampler"], eq16_pooled(calibrations[(2, "closed_loop")]))   # K=2: its own chain's


def test_pi0_trains_on_its_fixed_thread_count_and_the_next_stage_on_the_process_own(tmp_path, monkeypatch):
    """pi_0's training takes run_folder.PI0_THREADS torch threads in the harness (it runs alone: the second core is
    free), a number fixed by the stage, so that pi_0 is the same for any --workers; the process's own count is back
    after it. Fails if pi_0 trains on the process's count (or one set from the workers), or the count leaks into the
    stages after it (the arms and the collection run one thread each, as in the worker processes)."""
    import diffusion
    seen, train = [], diffusion.train
    monkeypatch.setattr(diffusion, "train", lambda *a, **k: (seen.append(torch.get_num_threads()), train(*a, **k))[1])
    run = run_folder.Run(str(tmp_path / "pi0"), replace(TINY, n_demos=2, bc_steps=4))
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        run.memo("checkpoints/bc.pt", dagger.behavior_cloning, run.cfg, dagger.oracle_demonstrations(run.cfg))
        assert seen == [run_folder.PI0_THREADS] and torch.get_num_threads() == 1
        run.memo("checkpoints/other.pt", dagger.behavior_cloning, run.cfg, dagger.oracle_demonstrations(run.cfg))
        assert seen == [run_folder.PI0_THREADS, 1]  # another stage: the process's own count
    finally:
        torch.set_num_threads(before)
