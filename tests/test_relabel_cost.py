"""benchmarks/relabel_cost.py (the stated study of what the relabelled chunks cost): each lineage's new scenarios, the
variance components, the design's lineage count and cost, the study's evaluation files, each stated test's quantity
and side, Holm over T1-T3, Hotelling's T² over the interactions, the table and the figure."""
import json
import math
import os
import shutil

import numpy as np
import pytest

import envs

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
START = os.path.join(ROOT, "benchmarks", "results", "table1_strong", "start")


@pytest.fixture(scope="module")
def rc():
    import importlib.util
    spec = importlib.util.spec_from_file_location("relabel_cost", os.path.join(ROOT, "benchmarks", "relabel_cost.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_each_lineage_draws_its_own_new_scenarios_no_stage_draws(rc):
    """300 consecutive seeds a lineage, from 100000 + 1000 L: above every range a stage or an earlier study draws
    from, and no two lineages share one (a stride below 300, or a range starting at the training seeds, would)."""
    seen = set()
    for lineage in range(rc.FIRST_LINEAGE, rc.FIRST_LINEAGE + rc.N_MAX):
        seeds = rc.new_seeds(lineage)
        assert len(seeds) == 300 and seeds == tuple(range(seeds[0], seeds[0] + 300))
        assert seeds[0] == 100_000 + 1_000 * lineage
        assert not seen & set(seeds)
        seen |= set(seeds)
    taken = set(range(envs.TRAIN_SEED_END)) | set(envs.eval_seeds()) | set(envs.unseen_seeds()) | set(
        range(30_000, 30_300))
    assert not seen & taken
    with pytest.raises(ValueError, match="lineage -1"):
        rc.new_seeds(-1)


def test_variance_components_recover_a_known_table(rc):
    """A table of lineage effects + scenario effects + an interaction whose mean squares are known: each component
    and the SE = sqrt((MS_L + MS_S − MS_E) / (R C)) come out (a swapped R and C, a missing −MS_E, a /R for /(R − 1)
    would not); lineage_se is the lineage means' SD / √R."""
    R, C = 4, 6
    a = np.array([-3.0, -1.0, 1.0, 3.0])  # lineage effects: sum of squares 20
    b = np.array([-5.0, -3.0, -1.0, 1.0, 3.0, 5.0])  # scenario effects: sum of squares 70
    e = np.outer([1.0, -1.0, 1.0, -1.0], [1.0, -1.0, 1.0, -1.0, 1.0, -1.0])  # rows and columns sum to 0
    table = 10.0 + a[:, None] + b[None, :] + e
    vc = rc.variance_components(table)
    ms_l, ms_s, ms_e = C * 20 / (R - 1), R * 70 / (C - 1), 24.0 / ((R - 1) * (C - 1))
    assert vc["ms_lineage"] == pytest.approx(ms_l) and vc["ms_scenario"] == pytest.approx(ms_s)
    assert vc["ms_error"] == pytest.approx(ms_e)
    assert vc["var_lineage"] == pytest.approx((ms_l - ms_e) / C)
    assert vc["var_scenario"] == pytest.approx((ms_s - ms_e) / R) and vc["var_error"] == pytest.approx(ms_e)
    assert vc["se"] == pytest.approx(math.sqrt((ms_l + ms_s - ms_e) / (R * C)))
    assert vc["lineage_se"] == pytest.approx(np.std(a, ddof=1) / math.sqrt(R))
    # Satterthwaite: (MS_L + MS_S − MS_E)² / (MS_L² / (R − 1) + MS_S² / (C − 1) + MS_E² / ((R − 1)(C − 1)))
    want = (40.0 + 56.0 - 1.6) ** 2 / (40.0 ** 2 / 3 + 56.0 ** 2 / 5 + 1.6 ** 2 / 15)
    assert (ms_l, ms_s, ms_e) == pytest.approx((40.0, 56.0, 1.6)) and want == pytest.approx(7.6775, abs=1e-4)
    assert vc["df"] == pytest.approx(want)


def test_the_variance_components_t_runs_on_satterthwaites_df_not_the_lineages(rc):
    """Two lineages, three scenarios: scenario effects (1, 3, 8) and an interaction ±(1, −1, 0), no lineage effect.
    MS_L = 0 is floored, so se² = MS_S / (R C) = 26 / 6 on C − 1 = 2 df (not R − 1 = 1), t = 4 / √(26 / 6), and on
    2 df the two-sided p is 1 − t / √(t² + 2) = 0.195 (on 1 df it would be 0.31); one-sided, half of it."""
    table = np.array([[2.0, 2.0, 8.0], [0.0, 4.0, 8.0]])
    vc = rc.variance_components(table)
    assert (vc["ms_lineage"], vc["ms_scenario"], vc["ms_error"]) == pytest.approx((0.0, 26.0, 2.0))
    assert vc["var_lineage"] == 0.0 and vc["se"] == pytest.approx(math.sqrt(26.0 / 6))
    assert vc["df"] == pytest.approx(2.0)
    t = 4.0 / math.sqrt(26.0 / 6)
    p = rc.vc_p(table.mean(), vc["se"], vc["df"], "two-sided")
    assert p == pytest.approx(1 - t / math.sqrt(t * t + 2), abs=1e-9) and p == pytest.approx(0.1946, abs=1e-4)
    assert rc.vc_p(table.mean(), vc["se"], vc["df"], ">") == pytest.approx(p / 2, abs=1e-9)
    assert rc.vc_p(-table.mean(), vc["se"], vc["df"], "<") == pytest.approx(p / 2, abs=1e-9)
    assert rc.vc_p(0.0, 0.0, vc["df"], "two-sided") == 1.0
    # both components floored: se² = MS_E / (R C) on (R − 1)(C − 1) df
    assert rc.satterthwaite_df(0.0, 1.0, 2.0, 2, 3, lineage=False, scenario=False) == pytest.approx(2.0)
    assert rc.satterthwaite_df(5.0, 1.0, 2.0, 4, 3, lineage=True, scenario=False) == pytest.approx(3.0)


def test_holm_adjusted_p_by_hand(rc):
    """m = 4: sorted p × (4, 3, 2, 1), a running maximum, at most 1, back in the order given."""
    assert rc.holm_adjusted([0.04, 0.01, 0.30, 0.02]) == pytest.approx([0.08, 0.04, 0.30, 0.06])
    assert rc.holm_adjusted([0.5, 0.4]) == pytest.approx([0.8, 0.8])


def test_variance_components_floor_a_negative_component_at_zero(rc):
    """Identical lineages (MS_L = 0 < MS_E): var_L is 0, not negative, and the SE keeps the scenarios' and the
    noise's parts; a table of one lineage is refused."""
    table = np.array([[0.0, 1.0, 0.0, 1.0], [1.0, 0.0, 1.0, 0.0]])
    vc = rc.variance_components(table)
    assert vc["ms_lineage"] == 0.0 and vc["var_lineage"] == 0.0
    assert vc["se"] == pytest.approx(math.sqrt(vc["var_scenario"] / 4 + vc["var_error"] / 8))
    assert vc["df"] == pytest.approx(3.0)  # both floored here: MS_E's (R − 1)(C − 1) df
    with pytest.raises(ValueError, match="at least 2"):
        rc.variance_components(np.ones((1, 5)))


def test_design_sd_adds_the_scenarios_part_to_the_larger_fixed_set_variance(rc):
    """The fixed set's variance is the larger of the observed SD² and var_L + var_E / C; fresh scenarios add var_S
    over the new set's size (dropping either part, or dividing by the pilot's size, changes these numbers)."""
    vc = {"var_lineage": 0.0, "var_scenario": 90.0, "var_error": 600.0}
    assert rc.design_sd(1.0, vc, 300) == pytest.approx(math.sqrt(2.0 + 90.0 / 300))
    assert rc.design_sd(2.0, vc, 300) == pytest.approx(math.sqrt(4.0 + 90.0 / 300))
    assert rc.design_sd(2.0, vc, 300, scenarios=100) == pytest.approx(math.sqrt(4.0 + 0.9))


def test_the_design_still_chooses_the_stated_lineage_count(rc):
    """A changed pilot, effect, level, SD rule or power rule would choose another count than the stated
    N_LINEAGES, which the committed design README states with its power table."""
    n, lines = rc.lineage_count(rc.load_lineages(rc.PILOT))
    assert n == rc.N_LINEAGES == 13
    assert lines[-1].startswith("lineages: 13 (the smallest n >= 8")
    readme = open(os.path.join(os.path.dirname(rc.PILOT), "relabel_cost", "README.md")).read()
    for line in lines:
        assert line in readme, line


def test_the_cost_sums_a_lineages_stage_seconds(rc):
    """A lineage's core-hours are the sum of its stages' seconds; the projection is collection and calibration plus
    the rows' trainings and evaluations plus the new set's at 3 x an evaluation, at the medians."""
    def files(train, evaluate, collect=40.0, calibrate=5.0):
        out = {"timings/collect.json": {"stage": "collect/lineage_1/round_1", "seconds": collect},
               "timings/calibrate.json": {"stage": "calibrate/lineage_1/round_1", "seconds": calibrate}}
        out.update({f"timings/t{i}.json": {"stage": f"train_row{i}/lineage_1/round_1", "seconds": s}
                    for i, s in enumerate(train)})
        out.update({f"timings/e{i}.json": {"stage": f"evaluate/lineage_1/round_1/eval/r{i}", "seconds": s}
                    for i, s in enumerate(evaluate)})
        return out
    pilot = {1: files([100.0, 300.0], [10.0, 10.0]), 2: files([200.0, 200.0], [10.0, 30.0])}
    c = rc.lineage_cost(pilot[1])
    assert c["total"] == pytest.approx(40 + 5 + 400 + 20) and sorted(c["train"]) == [100.0, 300.0]
    lines = rc.cost_per_lineage(pilot, rows=3, new_policies=5)
    projected = 45 + 3 * (200 + 2 * 10) + 5 * 3 * 10
    assert f"= {projected} s = {projected / 3600:.2f} core-hours" in lines[-1]
    totals = {1: 465.0, 2: 485.0}  # each lineage's stages, and its row of the table in core-hours
    for lineage, line in zip((1, 2), lines[2:4]):
        assert line.split()[0] == str(lineage) and line.split()[-1] == f"{totals[lineage] / 3600:.2f}"
    quiet = projected * totals[1] / np.median(list(totals.values()))  # at the quietest lineage's load
    assert f"({quiet / 3600:.2f} at its quietest lineage's)" in lines[-1]


def test_the_design_runs_the_most_lineages_where_none_reaches_the_power(rc, monkeypatch):
    """An effect too small for 80 % power at any n up to N_MAX: the design says so and runs N_MAX lineages, the
    range named from FIRST_LINEAGE."""
    monkeypatch.setattr(rc, "EFFECT", 0.2)
    n, lines = rc.lineage_count(rc.load_lineages(rc.PILOT))
    assert n == rc.N_MAX == 16
    assert lines[-1].startswith("lineages: 16 (no n <= 16 reaches power 0.8") and lines[-1].endswith("lineages 13..28")


# ---- the study's evaluation: each lineage's own new scenarios, and its D_1's labels ---------------------------------
def _study_folder(rc, root, lineages=26):
    """A run folder of the study's config whose every policy is the start's BC row (a link: nothing trained)."""
    config = json.load(open(os.path.join(START, "config.json")))
    config["methods"] = ["bc", *rc.ROWS]
    config["name"] = "table1_strong_" + "-".join(rc.ROWS)  # as --methods names it
    config["lineages"] = lineages
    (root / "checkpoints").mkdir(parents=True)
    (root / "lineage_13" / "round_1" / "checkpoints").mkdir(parents=True)
    json.dump(config, open(root / "config.json", "w"))
    for rel in rc.study_policies(13).values():
        os.symlink(os.path.join(START, "checkpoints", "bc_continued.pt"), root / rel)
    return config


def test_evaluate_lineage_writes_each_policy_on_its_lineages_own_seeds_and_resumes(rc, tmp_path, monkeypatch):
    """--evaluate: pi_0, BC and the seven rows on the lineage's own new seeds, one sampling seed for all of them
    (stage_seed(cfg, 'eval_new', L): another lineage gets another), each policy's hash recorded, then the D_1's
    labels; a second call keeps every file. A folder of another config, a lineage outside the study or a missing
    policy is refused before anything is written."""
    import dagger
    root = tmp_path / "run"
    config = _study_folder(rc, root)
    monkeypatch.setattr(rc, "new_seeds", lambda l: (100_000 + 1_000 * l, 100_001 + 1_000 * l))
    diagnosed = []
    monkeypatch.setattr(rc, "diagnose_lineage", lambda root, lineage, cfg, log: diagnosed.append(lineage))
    rc.evaluate_lineage(str(root), 13, log=lambda m: None)
    new = root / "lineage_13" / rc.NEW
    assert sorted(os.listdir(new)) == sorted(f"{r}.json" for r in ("pi0", "bc") + rc.ROWS) and diagnosed == [13]
    first = json.load(open(new / "pooled_pd.json"))
    assert first["seeds"] == [113_000, 113_001] and np.shape(first["success"]) == (2, config["eval_repeats"])
    assert first["policy"] == "lineage_13/round_1/checkpoints/pooled_pd.pt" and len(first["policy_sha256"]) == 64
    cfg = type("Cfg", (), {"seed": config["seed"]})
    assert first["sample_seed"] == dagger.stage_seed(cfg, "eval_new", 13) != dagger.stage_seed(cfg, "eval_new", 14)
    same = json.load(open(new / "hg_dagger.json"))
    assert same["success"] == first["success"] and same["sample_seed"] == first["sample_seed"]  # paired draws
    stamp = os.path.getmtime(new / "pooled_pd.json")
    rc.evaluate_lineage(str(root), 13, log=lambda m: None)
    assert os.path.getmtime(new / "pooled_pd.json") == stamp
    shutil.rmtree(new)
    with pytest.raises(SystemExit, match=r"--lineage 12: the study's lineages are 13\.\.25"):
        rc.evaluate_lineage(str(root), 12, log=lambda m: None)
    with pytest.raises(SystemExit, match=r"--lineage 26"):
        rc.evaluate_lineage(str(root), 26, log=lambda m: None)
    os.remove(root / "lineage_13" / "round_1" / "checkpoints" / "fixed_8_pd.pt")
    with pytest.raises(SystemExit, match="fixed_8_pd.pt missing; finish lineage 13 first"):
        rc.evaluate_lineage(str(root), 13, log=lambda m: None)
    config["methods"] = ["bc", "hg_dagger", "pooled"]
    json.dump(config, open(root / "config.json", "w"))
    with pytest.raises(SystemExit, match="not the study's run folder"):
        rc.evaluate_lineage(str(root), 13, log=lambda m: None)
    assert not new.exists()


def test_export_policies_copies_the_seven_rows_for_sampling_only(rc, tmp_path):
    """--export-policies: the lineage's seven round-1 policies, byte for byte, under folder/lineage_<l>/; a policy
    that still holds its training state (AdamW's moments: twice the weights again) is refused before any file is
    written."""
    root = tmp_path / "run"
    _study_folder(rc, root)
    rc.export_policies(str(root), 13, str(tmp_path / "policies"))
    out = tmp_path / "policies" / "lineage_13"
    assert sorted(os.listdir(out)) == sorted(f"{row}.pt" for row in rc.ROWS)
    source = open(os.path.join(START, "checkpoints", "bc_continued.pt"), "rb").read()
    assert all((out / f"{row}.pt").read_bytes() == source for row in rc.ROWS)
    os.remove(root / "lineage_13" / "round_1" / "checkpoints" / "pooled_pd.pt")
    os.symlink(os.path.join(START, "checkpoints", "bc.pt"), root / "lineage_13" / "round_1" / "checkpoints" / "pooled_pd.pt")
    with pytest.raises(SystemExit, match="pooled_pd.pt holds a training state"):
        rc.export_policies(str(root), 13, str(tmp_path / "again"))
    assert not (tmp_path / "again").exists()  # refused before anything is written


def test_diagnose_lineage_records_the_d1s_labels_with_the_runs_d0(rc, tmp_path):
    """relabel_diagnostic.json: the four labels (the diagnostic's LABELS, PD then the servo, x velocity noise on, off)
    of the lineage's D_1, labelled with the statistics of the run's D0 (not of the D_1 itself) at the run's H; every
    statistic is the diagnostic's own for the same episodes; a second call keeps the file. (The committed lineage
    files, made before 6192871, hold the old servo first, then PD, each under its name.)"""
    import relabel_diagnostic as rd
    from helpers import straight_line_episode
    from experiment import run_folder
    root = tmp_path / "run"
    (root / "data").mkdir(parents=True)
    (root / "lineage_13" / "round_1").mkdir(parents=True)
    env = envs.make_env("planar")
    d0 = [straight_line_episode(env, seed) for seed in (0, 1, 2, 3)]
    d1 = [straight_line_episode(env, seed, peak=0.03) for seed in (4, 5)]
    run_folder.save_episodes(str(root / "data" / "D0.npz"), d0)
    run_folder.save_episodes(str(root / "lineage_13" / "round_1" / "D.npz"), d1)
    cfg = type("Cfg", (), {"env": "planar", "horizon": 8})
    rc.diagnose_lineage(str(root), 13, cfg, log=lambda m: None)
    got = json.load(open(root / "lineage_13" / rc.DIAGNOSTIC))
    stats = rd.run_statistics("planar", run_folder.load_episodes(str(root / "data" / "D0.npz")))
    assert got["median_step"] == pytest.approx(stats.median_step)
    assert got["median_step"] != pytest.approx(rd.run_statistics("planar", d1).median_step)
    assert got["n_episodes"] == 2 and got["horizon"] == 8
    assert [(g["label"], g["velocity_noise"] > 0) for g in got["labels"]] == [
        (label, noise) for label in rd.LABELS for noise in (True, False)]
    pd_off = next(g for g in got["labels"] if g["label"] == "pd" and not g["velocity_noise"])
    again = rd.relabel_every_step(run_folder.load_episodes(str(root / "lineage_13" / "round_1" / "D.npz")),
                                  lambda: envs.make_env("planar"), stats, "pd", 8, velocity_noise=0.0)
    assert pd_off["all"] == pytest.approx(rd.summary(again), nan_ok=True)
    assert pd_off["to_end"] == pytest.approx(rd.summary(again, again.reaches_end), nan_ok=True)
    stamp = os.path.getmtime(root / "lineage_13" / rc.DIAGNOSTIC)
    rc.diagnose_lineage(str(root), 13, cfg, log=lambda m: None)
    assert os.path.getmtime(root / "lineage_13" / rc.DIAGNOSTIC) == stamp


# ---- the stated tests, from lineage files --------------------------------------------------------------------------
def _table(count, scenarios, repeats=3):
    """A (scenarios, repeats) success table with `count` successes, spread over the scenarios in turn."""
    flat = np.zeros(scenarios * repeats, bool)
    flat[:count] = True
    return flat.reshape(repeats, scenarios).T.tolist()


def _lineage_files(rc, lineage, collected, new):
    """A lineage file's 'files': success counts per row out of 300 (collected) and 900 (new) evaluations."""
    eval_seeds = list(range(10_000, 10_100))
    files = {"eval/bc.json": {"success": _table(collected["bc"], 100), "seeds": eval_seeds},
             "eval/pi0.json": {"success": _table(collected["bc"], 100), "seeds": eval_seeds}}
    for row in rc.ROWS:
        files[f"lineage_{lineage}/round_1/eval/{row}.json"] = {"success": _table(collected[row], 100),
                                                               "seeds": eval_seeds}
    for row in ("pi0", "bc") + rc.ROWS:
        files[f"lineage_{lineage}/{rc.NEW}/{row}.json"] = {
            "success": _table(new["bc" if row == "pi0" else row], 300), "seeds": list(rc.new_seeds(lineage))}
    return files


def _counts(hg, zero, t1, fixed, t2, pooled, t3, bc=None):
    """Counts by row: zero_noise, fixed_8, pooled as given; each _pd row its servo row + t1 (zero) or HG + t2 / t3."""
    return {"bc": hg - 60 if bc is None else bc, "hg_dagger": hg, "zero_noise": zero, "zero_noise_pd": zero + t1,
            "fixed_8": fixed, "fixed_8_pd": hg + t2, "pooled": pooled, "pooled_pd": hg + t3}


@pytest.fixture
def three(rc):
    """Three lineages with known differences: on new (900 evaluations, 9 counts a point) T1 = +2 / +3 / +4 points,
    T2 = +1 / +1 / +4, T3 = −1 / 0 / +1; on collected (300, 3 counts a point) T1 = −1 / −2 / −3."""
    lineages = {}
    for l, (t1, t2, t3, c1) in zip((13, 14, 15), ((2, 1, -1, -1), (3, 1, 0, -2), (4, 4, 1, -3))):
        new = _counts(450 + 9 * l, 432, 9 * t1, 459, 9 * t2, 441 + l, 9 * t3)
        collected = _counts(180, 171, 3 * c1, 183, 6, 177 + {13: 0, 14: 3, 15: -3}[l], 0)
        lineages[l] = _lineage_files(rc, l, collected, new)
    return lineages


def test_the_stated_quantities_are_the_ones_named(rc, three):
    """T1 is zero_noise_pd − zero_noise on new, T2 fixed_8_pd − HG-DAgger, T3 pooled_pd − HG-DAgger, each '>' (a
    row swapped for its twin, the sets swapped or the side turned gives other numbers); Holm's verdicts are
    noise_transfer.holm's over their p; the collected set's T1 is the secondary one."""
    assert sorted(rc.complete(three)) == [13, 14, 15]
    res = {name: (s, side, e, ok) for name, _, s, side, e, ok in rc.stated_tests(three)}
    assert [res[t][:2] for t in ("T1", "T2", "T3")] == [("new", ">")] * 3
    assert list(res["T1"][2]["values"]) == pytest.approx([2.0, 3.0, 4.0])
    assert list(res["T2"][2]["values"]) == pytest.approx([1.0, 1.0, 4.0])
    assert list(res["T3"][2]["values"]) == pytest.approx([-1.0, 0.0, 1.0])
    assert res["T1"][2]["se"] == pytest.approx(1 / math.sqrt(3)) and res["T1"][2]["t"] == pytest.approx(3 * math.sqrt(3))
    assert res["T3"][2]["p"] == pytest.approx(0.5)   # mean 0: one-sided p 1/2
    ps = [res[t][2]["p"] for t in ("T1", "T2", "T3")]
    assert [res[t][3] for t in ("T1", "T2", "T3")] == rc.noise_transfer.holm(ps, rc.ALPHA)
    second = {(name, s): rc.estimate(three, combo, s, side) for name, _, s, combo, side in rc.SECONDARY}
    assert list(second[("T1", "collected")]["values"]) == pytest.approx([-1.0, -2.0, -3.0])
    # I_8 = (fixed_8_pd − fixed_8) − (zero_noise_pd − zero_noise) on new: (HG + t2 − 459) − t1, in points
    want = [(450 + 9 * l + 9 * t2 - 459) / 9 - t1 for l, t1, t2 in ((13, 2, 1), (14, 3, 1), (15, 4, 4))]
    assert list(second[("I_8", "new")]["values"]) == pytest.approx(want)


def test_each_quantity_carries_both_ses(rc, three):
    """An estimate's 'se' is the lineage values' SD / √R and 'vc_se' the variance components' SE of the same lineage
    x scenario table (not of the row's own table, not over the other set), its p on that table's Satterthwaite df."""
    e = rc.estimate(three, rc.difference("pooled_pd", "hg_dagger"), "new", ">")
    table = rc.combination_table(three, rc.difference("pooled_pd", "hg_dagger"), "new")
    assert table.shape == (3, 300)
    assert e["se"] == pytest.approx(np.std(table.mean(axis=1), ddof=1) / math.sqrt(3))
    vc = rc.variance_components(table)
    assert e["vc_se"] == pytest.approx(vc["se"]) and e["vc_df"] == pytest.approx(vc["df"])
    assert e["vc_p"] == pytest.approx(rc.vc_p(e["mean"], vc["se"], vc["df"], ">"))


def test_a_new_set_evaluated_on_other_seeds_is_refused(rc, three):
    """A lineage's new-set file holding another lineage's seeds (a copied folder, a wrong --lineage) stops the
    reading with both ranges named."""
    files = dict(three[13])
    files["lineage_13/new_scenarios/pooled.json"] = dict(files["lineage_13/new_scenarios/pooled.json"],
                                                         seeds=list(rc.new_seeds(14)))
    with pytest.raises(ValueError, match=r"seeds 114000\.\.114299, not lineage 13's own 113000\.\.113299"):
        rc.per_scenario(files, 13, "pooled", "new")
    with pytest.raises(ValueError, match="'collected' or 'new'"):
        rc.per_scenario(files, 13, "pooled", "unseen")


def test_f_cdf_is_the_t_distribution_squared_and_the_closed_form_at_2_2(rc):
    """F(1, d) at t² is P(|T| <= t) for Student's t on d df; F(2, 2)'s CDF is x / (1 + x)."""
    import dagger
    for t, d in ((0.5, 3), (2.0, 7), (4.1, 12)):
        assert rc.f_cdf(t * t, 1, d) == pytest.approx(2 * dagger.student_t_cdf(t, d) - 1, abs=1e-9)
    for x in (0.1, 1.0, 8.0):
        assert rc.f_cdf(x, 2, 2) == pytest.approx(x / (1 + x), abs=1e-9)
    assert rc.f_cdf(0.0, 2, 5) == 0.0


def test_hotelling_by_hand_and_as_the_t_test_in_one_dimension(rc, load_benchmark):
    """(1, 1), (3, 1), (1, 3), (3, 3): mean (2, 2), S = 4/3 I, T² = 4 · 8 / (4/3) = 24, F = 2 / 6 · 24 = 8 on (2, 2),
    p = 1 − 8/9; in one dimension T² = t² and p the two-sided t's. Refused with no more lineages than quantities."""
    t2, f, d1, d2, p = rc.hotelling([[1, 1], [3, 1], [1, 3], [3, 3]])
    assert (t2, f, d1, d2) == (pytest.approx(24.0), pytest.approx(8.0), 2, 2) and p == pytest.approx(1 / 9)
    x = [1.0, 2.5, 0.5, 3.0, 1.5]
    mean, se, t, df, p_t = load_benchmark("paired_bc").t_test(x)
    t2, f, d1, d2, p = rc.hotelling(np.array(x)[:, None])
    assert t2 == pytest.approx(t * t) and (d1, d2) == (1, 4) and p == pytest.approx(p_t, abs=1e-9)
    with pytest.raises(ValueError, match="2 lineages for 2 quantities"):
        rc.hotelling([[1, 2], [3, 4]])
    with pytest.raises(ValueError, match=r"singular \(rank 1\)"):
        rc.hotelling([[1, 2], [2, 4], [3, 6]])


def test_the_command_prints_the_table_the_tests_and_draws_the_figure(rc, three, tmp_path, capsys):
    """From lineage files: every row on both sets, T1-T3 with Holm, the interim note below the stated count, the
    secondary results with Hotelling's T² on each set, and the figure."""
    import gzip
    for l, files in three.items():
        with gzip.open(tmp_path / f"lineage_{l}.json.gz", "wt") as fh:
            json.dump({"lineage": l, "files": files}, fh)
    rc.main(["--results", str(tmp_path), "--figure", str(tmp_path / "fig.png")])
    out = capsys.readouterr().out
    assert "3 complete lineage(s) [13, 14, 15] of the stated 13 (13..25)" in out
    assert out.count("| T") == 3 and "an interim look at 3 lineages" in out
    assert out.count("none before 13 lineages") == 3 and "rejected" not in out  # no verdict at an interim look
    hg = next(line for line in out.splitlines() if line.startswith("| hg_dagger |"))
    assert hg.split("|")[3].strip().startswith(f"{np.mean([(450 + 9 * l) / 9 for l in (13, 14, 15)]):.1f} ± 0.6")
    assert out.count("Hotelling's T² =") == 2 and "I_pooled on new" in out
    assert (tmp_path / "fig.png").stat().st_size > 10_000


def test_lineage_values_equal_but_for_float_noise_have_no_spread(rc, monkeypatch):
    """Two lineages whose value is 0.3 point, one summed as 0.1 + 0.2: their SD is 0, not 3e-17 (which printed a
    t of 1e16 on the committed lineages' I_pooled)."""
    tables = np.array([[0.1 + 0.2] * 4, [0.3] * 4])
    monkeypatch.setattr(rc, "combination_table", lambda lineages, combo, scenario_set: tables)
    e = rc.estimate({13: {}, 14: {}}, {}, "new", "two-sided")
    assert e["se"] == 0.0 and e["mean"] == pytest.approx(0.3)


def test_at_the_stated_count_each_test_gets_holms_verdict(rc, three, monkeypatch):
    """Once the lineages reach the stated count the table gives Holm's verdict per test: here, at 0.10, T1
    (p 0.018 against 0.10 / 3) is rejected, T2 (p 0.092 against 0.10 / 2) stops the rest. A table that kept
    "none before" at the count, gave every test its own uncorrected verdict (T2 would pass 0.10) or read the
    verdicts out of order would print other words."""
    monkeypatch.setattr(rc, "N_LINEAGES", 3)
    monkeypatch.setattr(rc, "ALPHA", 0.10)
    rows = {line.split("|")[1].strip(): line.split("|")[-2].strip() for line in rc.tests_table(three)[2:]
            if line.startswith("|")}
    assert rows == {"T1": "rejected", "T2": "not rejected", "T3": "not rejected"}
    ps = {name: e["p"] for name, _, _, _, e, _ in rc.stated_tests(three)}
    assert ps["T1"] == pytest.approx(0.0176, abs=1e-4) and ps["T2"] == pytest.approx(0.0918, abs=1e-4)


def test_the_committed_study_prints_the_numbers_its_readmes_quote(rc, capsys):
    """The script over the committed lineage files prints what README.md, benchmarks/README.md and the study's
    README quote: the thirteen lineages, T1-T3 with Holm's verdicts (no second SE on the nested new set), the
    secondary results they cite with Holm's adjusted p and, on the collected set, the variance-components t on
    Satterthwaite's df (T2's −2.95: p 0.0096 over lineages, 0.15 with the scenarios' draw on 77 df), the
    after-the-fact power, bounds and differences, the note that every SE is conditional on one π0, a table row and
    the D_1 labels. A lineage file changed, dropped or added, or a quantity computed otherwise, breaks a line."""
    rc.main([])
    out = capsys.readouterr().out
    for line in ("13 complete lineage(s) [13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25] of the stated 13",
                 "is conditional on one π0",
                 "| hg_dagger | 73.9 ± 0.9 (3.0) | 55.3 ± 0.6 |",
                 "| zero_noise_pd | 74.7 ± 0.7 (2.8) | 55.3 ± 0.6 |",
                 "| +0.91 | 0.25 | 3.58 | 12 | 0.0019 | rejected |",
                 "| +1.37 | 0.45 | 3.03 | 12 | 0.0052 | rejected |",
                 "| +0.42 | 0.25 | 1.71 | 12 | 0.057 | not rejected |",
                 "lies within 0.04 of it for T1-T3",
                 "T1 on collected (zero_noise_pd − zero_noise (PD − the old servo, σ 0)): +3.18 ± 0.83 points, t(12) = "
                 "3.85, p = 0.0023 (Holm over the 15: 0.033); var. comp. SE 1.02, t(24) = 3.13, p = 0.0046",
                 "T2 on collected (fixed_8_pd − HG-DAgger): -2.95 ± 0.96 points, t(12) = -3.08, p = 0.0096 (Holm over "
                 "the 15: 0.11); var. comp. SE 2.02, t(77) = -1.46, p = 0.15",
                 "pooled − HG-DAgger on collected (the calibrated σ, the old servo): -1.77 ± 0.55 points, t(12) = "
                 "-3.20, p = 0.0076 (Holm over the 15: 0.099); var. comp. SE 1.03, t(99) = -1.71, p = 0.09",
                 "pooled_pd − pooled on collected (the label at the calibrated σ): +1.74 ± 0.43 points, t(12) = 4.02, "
                 "p = 0.0017 (Holm over the 15: 0.026); var. comp. SE 0.79, t(99) = 2.20, p = 0.03",
                 "I_8 on collected ((fixed_8_pd − fixed_8) − (zero_noise_pd − zero_noise)): -2.72 ± 0.94 points, "
                 "t(12) = -2.89, p = 0.014 (Holm over the 15: 0.15); var. comp. SE 1.15, t(22) = -2.36, p = 0.028",
                 "pooled_pd − pooled on new (the label at the calibrated σ): +0.55 ± 0.31 points, t(12) = 1.76, p = 0.1",
                 "fixed_8_pd − fixed_8 on new (the label at σ 8): +0.60 ± 0.35 points, t(12) = 1.71, p = 0.11",
                 "I_8 and I_pooled at once on collected: Hotelling's T² = 9.59, F(2, 11) = 4.40, p = 0.039",
                 "I_8 and I_pooled at once on new: Hotelling's T² = 0.78, F(2, 11) = 0.36, p = 0.71",
                 "SD 0.88, level 0.0500: power 1.00 at the stated +1.5, 0.49 at the +0.42 seen; one-sided 95 % bounds: "
                 "> -0.02, < +0.86",
                 "SD 1.63, level 0.0250: power 0.86 at the stated +1.5, 0.79 at the +1.37 seen",
                 "SD 0.91, level 0.0167: power 1.00 at the stated +1.5, 0.86 at the +0.91 seen",
                 "-0.91 ± 0.27, t(12) = -3.36, p = 0.0057",
                 "fixed_8 − HG-DAgger on new (σ 8 with the old servo): +0.77 ± 0.35, t(12) = 2.22, p = 0.047",
                 "zero_noise_pd − HG-DAgger on collected (σ 0 with PD): +0.85 ± 0.60, t(12) = 1.42, p = 0.18; var. "
                 "comp. SE 0.69, df 19, p = 0.24",
                 "| servo | off | 5.3% | 1.73 | 0.04 | 5.97 | 1.88 | 1.24 |",
                 "| pd | off | 0.0% | 0.20 | 0.00 | 0.82 | 0.00 | 0.73 |"):
        assert line in out, line
    assert "none before" not in out
    # the new set's cells and T1-T3 carry one SE: no floored second SE in brackets there
    hg = next(line for line in out.splitlines() if line.startswith("| hg_dagger |"))
    assert "(" not in hg.split("|")[3]
    assert "var. comp." not in "".join(line for line in out.splitlines() if " on new (" in line)
