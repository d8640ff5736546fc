"""experiment/controls.py's rows beside Table I's (research controls): HG-DAgger as the authors' kit trained
it, and the paper's text's co-training (half recorded, half noised); a committed start serving a run of other methods
and rounds; benchmarks/noise_trade.py's class split."""
import os
from dataclasses import replace

import numpy as np
import pytest

import dagger
import diffusion
import envs
import relabel
from experiment import controls, profiles, report, run_folder

H = 20
ROWS = ("authors_hg_dagger", "cotrain_fixed_8", "cotrain_pooled")
TINY = dagger.Config(name="tiny", n_demos=4, rounds=1, lineages=1, K=5, network="mlp", mlp_width=16, mlp_blocks=1,
                     bc_steps=30, finetune_steps=12, batch_size=32, methods=("bc", "hg_dagger") + ROWS,
                     eval_scenarios=3, eval_repeats=1, eval_unseen=False)


def episode():
    """An episode of D_k, 60 steps, joints 3; action[t] = t on every joint; the expert drives [5, 35) (30 >= H steps;
    a shorter intervention is not in D_k: the collection keeps diffusion.expert_runs)."""
    expert = np.zeros(60, bool)
    expert[5:35] = True
    t = np.arange(60, dtype=float)
    return {"obs": np.repeat(t[:, None], 4, axis=1).astype(np.float32), "q": np.zeros((60, 3)),
            "action": np.repeat(t[:, None], 3, axis=1), "expert": expert, "seed": 7}


def test_the_authors_rows_differ_from_hg_daggers_exactly_at_the_last_steps_of_each_intervention():
    """Fails if a step of a kept intervention starts no chunk (the paper's t + H <= end cut in), if a chunk past its
    intervention's end is padded with anything but that intervention's last action, if a chunk the paper's rule
    makes differs, or if the sampler hands train a mask (the padded steps would leave the loss, as in the authors'
    noised arms and lever.PaddedChunkSampler)."""
    ep = episode()
    authors = controls.AuthorsChunkSampler([ep], H)
    paper_obs, paper_chunks = diffusion.chunk_dataset([ep], H)
    starts = authors.obs[:, 0].astype(int)
    assert starts.tolist() == list(range(5, 35))  # every step of the intervention
    assert paper_obs[:, 0].astype(int).tolist() == list(range(5, 16))  # the paper's: t + H <= the run's end
    for t, chunk in zip(starts, authors.chunks):
        want = np.minimum(np.arange(t, t + H), 34)  # past the run's end: its last action, held
        assert chunk[:, 0].tolist() == want.tolist()
    same = np.isin(starts, paper_obs[:, 0])
    assert np.array_equal(authors.chunks[same], paper_chunks)  # where both rules label, the same chunk
    assert len(authors(64, np.random.default_rng(0))) == 2  # (obs, chunks): no mask, every padded step in the loss
    sampler = controls.Rows()(TINY, "authors_hg_dagger", [[ep]], None, None, envs.make_env)
    assert isinstance(sampler.samplers[0], controls.AuthorsChunkSampler)
    assert len(sampler(32, np.random.default_rng(1))) == 2


@pytest.fixture(scope="module")
def controls_run(tmp_path_factory):
    """A finished tiny run with the three control rows."""
    root = str(tmp_path_factory.mktemp("controls"))
    report.run_experiment(TINY, root, workers=1)
    return root


def load(root, name):
    return run_folder.load_episodes(os.path.join(root, name))


@pytest.mark.slow
def test_the_control_rows_train_evaluate_and_are_named_in_the_table(controls_run):
    """Fails if a control row is not fine-tuned, evaluated or named in table.md (the report's METHOD_LABELS)."""
    for m in ROWS:
        assert os.path.exists(os.path.join(controls_run, "lineage_0", "round_1", "checkpoints", f"{m}.pt"))
        assert os.path.exists(os.path.join(controls_run, "lineage_0", "round_1", "eval", f"{m}.json"))
    table = open(os.path.join(controls_run, "table.md")).read()
    assert "HG-DAgger as the authors' kit trained it" in table and "Half recorded, half pooled" in table


@pytest.mark.slow
def test_the_co_training_rows_draw_half_as_recorded_half_noised_with_their_rows_noise(controls_run,
                                                                                     augmentation_samplers):
    """controls.co_trained. Fails if a co-training row's mix is not half and half, if its recorded half is not HG-DAgger's chunks, or if its
    noised half has another noise than fixed sigma = 8 / pooled Sigma-bar^alpha (dagger.noise_model's)."""
    D, demos = load(controls_run, "lineage_0/round_1/D.npz"), load(controls_run, "data/D0.npz")
    stats = dagger.demo_statistics(TINY, demos)
    cal = run_folder.calibration_from_json(run_folder.read_json(os.path.join(controls_run,
                                                                       "lineage_0/round_1/calibration.json")))
    for method, noise in (("cotrain_fixed_8", "fixed_8"), ("cotrain_pooled", "pooled")):
        augmentation_samplers.clear()
        mix = controls.Rows()(TINY, method, [D], cal, stats, envs.make_env).samplers[0]
        assert isinstance(mix, relabel.MixtureSampler) and np.allclose(mix.p, [0.5, 0.5])
        recorded, noised = mix.samplers
        assert isinstance(recorded, relabel.ChunkSampler)
        assert np.array_equal(recorded.obs, diffusion.chunk_dataset(D, H)[0])
        kind, sigma = dagger.noise_model(noise, cal, range(len(D)), stats.median_step, stats.paper_median_step)
        (built,) = augmentation_samplers
        assert built["sampler"] is noised and built["noise"] == kind and np.allclose(built["sigma"], sigma)
        obs, chunks, mask = mix(400, np.random.default_rng(0))
        assert 0.4 < mask.all(axis=1).mean() <= 1.0 and obs.shape == (400, recorded.obs.shape[1])


@pytest.mark.slow
def test_a_committed_start_serves_a_run_of_other_methods_and_rounds_and_a_run_folder_does_not(controls_run,
                                                                                               tmp_path):
    """The shared stages (D0, pi_0, the BC row) depend on neither the methods nor the rounds: table1's committed start
    loads into a one-round run of the control rows. A folder with lineages of another round count is refused."""
    cfg = replace(profiles.PROFILES["table1"], rounds=1, methods=("bc", "hg_dagger") + ROWS)
    start = run_folder.committed_start("table1", cfg, str(tmp_path / "k1"))
    assert start is not None and start.endswith(os.path.join("table1", "start"))
    run = run_folder.Run(str(tmp_path / "k1"), cfg)
    assert run_folder.copy_from(run, start) == len(run_folder.start_files(start)) - 1  # all but config.json
    longer = run_folder.Run(str(tmp_path / "src2"), replace(TINY, rounds=2)).root
    os.makedirs(os.path.join(longer, "lineage_0"))
    with pytest.raises(run_folder.ConfigMismatch, match="rounds"):  # lineages of more rounds than this run's: refused
        run_folder.copy_from(run_folder.Run(str(tmp_path / "half"), TINY), longer)


@pytest.mark.slow
def test_a_folder_of_fewer_rounds_gives_a_longer_run_its_first_rounds(controls_run, tmp_path, trained_stages):
    """--rounds 2 --copy-from a one-round folder: only round 2 trains, and round 1's stages are the folder's (no stage
    depends on the round count). Fails if round 1 retrains or the copy is refused."""
    root = str(tmp_path / "two")
    report.run_experiment(replace(TINY, rounds=2), root, copy_src=controls_run)
    assert sorted(trained_stages) == sorted(f"lineage_0/round_2/checkpoints/{m}.pt" for m in ("hg_dagger",) + ROWS)
    for name in ("D.npz", "eval/hg_dagger.json", "eval/authors_hg_dagger.json"):
        a, b = (open(os.path.join(r, "lineage_0", "round_1", name), "rb").read() for r in (controls_run, root))
        assert a == b


def files_of(pi0, rows):
    """A lineage's files: pi_0's evaluation (scenarios x 3) and round-1 rows {method: (scenarios x 3)}."""
    files = {"eval/pi0.json": {"success": pi0.tolist(), "seeds": list(range(len(pi0)))}}
    for m, s in rows.items():
        files[f"lineage_0/round_1/eval/{m}.json"] = {"success": s.tolist(), "seeds": list(range(len(pi0)))}
    return files


def test_the_class_split_takes_each_rows_difference_on_the_scenarios_of_pi0s_class(load_benchmark):
    """Fails if a scenario lands in another class than pi_0's count of solved repeats says (0: never, all: always),
    if a class's difference is taken over other scenarios, if a lineage whose HG-DAgger differs is joined, or if a
    joined row is credited to the wrong folder."""
    nt = load_benchmark("noise_trade")
    pi0 = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]], bool)
    assert nt.pi0_classes(files_of(pi0, {})).tolist() == ["never", "sometimes", "sometimes", "always"]
    hg = np.array([[1, 1, 1], [0, 0, 0], [1, 0, 0], [1, 1, 1]], bool)
    row = np.array([[0, 0, 0], [1, 1, 1], [1, 1, 0], [1, 1, 1]], bool)
    d = nt.class_differences({0: files_of(pi0, {"hg_dagger": hg, "row": row})}, 1, "row")
    assert d["never"] == [-100.0] and d["always"] == [0.0]
    assert d["sometimes"] == pytest.approx([100.0 * (5 / 6 - 1 / 6)]) and d["all"] == pytest.approx([100.0 * (8 - 7) / 12])
    main = {0: files_of(pi0, {"hg_dagger": hg, "fixed_8": row})}
    same = {0: files_of(pi0, {"hg_dagger": hg, "new": row})}
    other = {0: files_of(pi0, {"hg_dagger": row, "new": row})}
    merged, ok, origin = nt.merge(main, same, [1], ("main", "same"))
    assert ok == {0: True} and {"fixed_8", "new"} <= set(nt.rows_of(merged, 1))
    # each row names the folder it came from (a joined folder's rows once came out titled "table1")
    assert nt.row_origin(origin, merged, 1, "fixed_8") == "main: 0"
    assert nt.row_origin(origin, merged, 1, "new") == "same: 0"
    assert "| new | 1 |" in nt.class_table("x", merged, 1, origin=origin).split("same: 0 |")[0]
    merged, ok, origin = nt.merge(main, other, [1], ("main", "other"))
    assert ok == {0: False} and "fixed_8" not in nt.rows_of(merged, 1)  # another round 1: only its own rows
    assert nt.row_origin(origin, merged, 1, "hg_dagger") == "other: 0"  # ... and its HG-DAgger is named as other's


def test_the_dose_response_is_the_slope_of_each_lineages_difference_on_sigma(load_benchmark):
    """noise_trade.dose_response and compare: fails if the slope is not of (fixed sigma - HG-DAgger) on sigma per
    lineage, or if a comparison pairs the wrong rows or scenarios."""
    nt = load_benchmark("noise_trade")
    pi0 = np.zeros((12, 3), bool)
    pi0[6:] = True  # 6 never, 6 always
    hg = np.zeros((12, 3), bool)
    lineages = {}
    for l, gain in enumerate((1, 2)):  # lineage l: fixed_s solves s // 2 * gain more never-scenarios' repeats
        rows = {"hg_dagger": hg}
        for s in (2, 4, 8):
            row = hg.copy()
            row.reshape(-1)[: (s // 2) * gain] = True  # the first scenarios are never-class
            rows[f"fixed_{s}"] = row
        lineages[l] = {k.replace("lineage_0", f"lineage_{l}"): v for k, v in files_of(pi0, rows).items()}
    slopes, sigmas, _ = nt.dose_response(lineages, 1)
    assert sigmas == [2, 4, 8]
    # never: s // 2 * gain of 18 episodes -> 100 * gain / 36 points per unit of sigma
    assert slopes["never"] == pytest.approx([100 / 36, 200 / 36]) and slopes["always"] == pytest.approx([0, 0])
    two = {l: {k: v for k, v in files.items() if "fixed_8" not in k} for l, files in lineages.items()}
    assert nt.dose_response(two, 1)[0]["never"] == pytest.approx([100 / 36, 200 / 36])  # two sigmas make a slope
    def renamed(files, l):
        return {k.replace("lineage_0/", f"lineage_{l}/").replace("lineage_1/", f"lineage_{l}/"): v
                for k, v in files.items()}
    # lineage 9, sorted first, lacks fixed_4 and fixed_8: the slopes pair each lineage's own differences
    partial = {9: renamed(files_of(pi0, {"hg_dagger": hg, "fixed_2": hg}), 9),
               10: renamed(lineages[0], 10), 11: renamed(lineages[1], 11)}
    assert nt.dose_response(partial, 1)[0]["never"] == pytest.approx([100 / 36, 200 / 36])  # complete lineages only
    (mean, se, t, df, p, n), (m2, *_rest) = nt.compare(lineages, 1, "fixed_8", "hg_dagger")
    assert n == 2 and mean == pytest.approx(100 * (4 + 8) / 2 / 36) and m2 == pytest.approx(mean)


def test_the_servo_rows_are_the_default_rows_with_the_authors_servo_label(controls_run, augmentation_samplers):
    """zero_noise_servo, fixed_8_servo and pooled_servo: the same noise as zero_noise, fixed_8 and pooled, every drawn
    frame relabelled by the authors' servo (experiment/servo.py) instead of the paper's PD, the default. Fails if a
    _servo row keeps the PD label, a default row takes the servo, a _servo row takes another noise than its twin, or
    is read as a row of the fixed sweep."""
    from experiment import servo
    D, demos = load(controls_run, "lineage_0/round_1/D.npz"), load(controls_run, "data/D0.npz")
    stats = dagger.demo_statistics(TINY, demos)
    cal = run_folder.calibration_from_json(run_folder.read_json(os.path.join(controls_run,
                                                                       "lineage_0/round_1/calibration.json")))
    for servo_row, twin in (("zero_noise_servo", "zero_noise"), ("fixed_8_servo", "fixed_8"),
                            ("pooled_servo", "pooled")):
        built = {}
        for method in (servo_row, twin):
            augmentation_samplers.clear()
            controls.Rows()(TINY, method, [D], cal, stats, envs.make_env)
            (built[method],) = augmentation_samplers
        assert isinstance(built[servo_row]["sampler"], servo.ServoSampler)
        assert type(built[twin]["sampler"]) is relabel.AugmentationSampler
        assert built[servo_row]["sampler"].cfg.label == "servo" and built[twin]["sampler"].cfg.label == "pd"
        assert built[servo_row]["noise"] == built[twin]["noise"]
        assert np.allclose(built[servo_row]["sigma"], built[twin]["sigma"])
        assert servo_row in profiles.ALL_METHODS and not report.is_fixed(servo_row)
    assert report.is_fixed("fixed_8") and report.method_label("fixed_8_servo").endswith(
        "the authors' servo label (not in the paper's table)")
    assert not any(m.endswith("_pd") for m in profiles.ALL_METHODS)  # the PD is every default row's label