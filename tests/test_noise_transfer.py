"""benchmarks/noise_transfer.py (the stated study of what the noise buys) and benchmarks/evaluate_policy.py: the
design still chooses the lineage count it states, each stated test computes the quantity it names with its side,
Holm's step-down, the new-scenario evaluation's files, and the policy command's seeds and interval."""
import json
import math
import os
import shutil

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
START = os.path.join(ROOT, "benchmarks", "results", "table1_strong", "start")


@pytest.fixture
def nt(load_benchmark):
    return load_benchmark("noise_transfer")


def test_the_design_still_chooses_the_stated_lineage_count(nt):
    """A changed pilot, effect, level or power rule would choose another count than the stated N_LINEAGES (and
    the committed design README's); the count must stay at least 8 and at most 16."""
    n, lines = nt.design(nt.load_lineages(nt.PILOT))
    assert n == nt.N_LINEAGES == 8
    assert lines[-1].startswith("lineages: 8 ")
    readme = open(os.path.join(nt.RESULTS, "README.md")).read()
    assert "lineages: 8 (the smallest n >= 8" in readme and "Lineages 5..12" in readme


def test_power_grows_with_lineages_and_is_the_level_at_no_effect(nt):
    """power() is the one-sided t test's rejection rate: alpha at no effect, rising with n (a wrong side or a
    two-sided quantile breaks both)."""
    assert nt.power(0.0, 1.0, 8, 0.05) == pytest.approx(0.05, abs=0.004)
    assert nt.power(1.0, 1.0, 6, 0.0125) < nt.power(1.0, 1.0, 10, 0.0125)
    assert nt.power(-1.0, 1.0, 8, 0.05) < 0.01


def test_holm_steps_down():
    """Holm at 0.05 over four: the smallest p against 0.0125, then 0.05/3, 0.05/2, 0.05; a failure stops the rest."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("nt", os.path.join(ROOT, "benchmarks", "noise_transfer.py"))
    nt = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(nt)
    assert nt.holm([0.012, 0.016, 0.024, 0.049]) == [True, True, True, True]
    assert nt.holm([0.013, 0.001, 0.02, 0.04]) == [True, True, True, True]
    assert nt.holm([0.001, 0.026, 0.026, 0.001]) == [True, False, False, True]   # 0.026 > 0.05 / 2 stops the rest
    assert nt.holm([0.0126, 0.5, 0.5, 0.5]) == [False, False, False, False]


def _table(rate, scenarios, repeats=3):
    """A (scenarios, repeats) success table whose mean is `rate` (a multiple of 1 / (scenarios * repeats))."""
    k = round(rate * scenarios * repeats)
    flat = np.zeros(scenarios * repeats, bool)
    flat[:k] = True
    return flat.reshape(scenarios, repeats).tolist()


def _lineage_files(nt, lineage, collected, new):
    """A lineage file's 'files' with the given rates (fractions) per row on both sets."""
    eval_seeds, new_seeds = list(range(10_000, 10_100)), list(nt.NEW_SEEDS)
    files = {"eval/bc.json": {"success": _table(collected["bc"], 100), "seeds": eval_seeds},
             "eval/pi0.json": {"success": _table(collected["bc"], 100), "seeds": eval_seeds},
             f"lineage_{lineage}/round_1/calibration.json": {"pooled": np.diag([4e-4, 1e-4, 1e-4]).tolist(),
                                                             "paper_median_step": 0.0176}}
    for row in nt.ROWS:
        files[f"lineage_{lineage}/round_1/eval/{row}.json"] = {"success": _table(collected[row], 100),
                                                               "seeds": eval_seeds}
    for row in ("pi0", "bc") + nt.ROWS:
        files[f"lineage_{lineage}/{nt.NEW}/{row}.json"] = {"success": _table(new["bc" if row == "pi0" else row], 300),
                                                          "seeds": new_seeds}
    unseen = {row: round(v - 0.01 * i, 4) for i, (row, v) in enumerate(new.items())}   # the run's own 20000..20099
    files["eval/bc_unseen.json"] = {"success": _table(unseen["bc"], 100), "seeds": list(range(20_000, 20_100))}
    for row in nt.ROWS:
        files[f"lineage_{lineage}/round_1/eval/{row}_unseen.json"] = {"success": _table(unseen[row], 100),
                                                                      "seeds": list(range(20_000, 20_100))}
    return files


def _rates(hg, bc, per_sigma, pooled):
    """Rates with row - HG-DAgger = per_sigma * sigma for zero_noise / fixed rows (sigma 0 / 4 / 8 / 16)."""
    return {"bc": bc, "hg_dagger": hg, "zero_noise": hg, "fixed_4": hg + 4 * per_sigma,
            "fixed_8": hg + 8 * per_sigma, "fixed_16": hg + 16 * per_sigma, "pooled": pooled}


def test_the_stated_quantities_are_the_ones_named(nt):
    """Two lineages built with known differences: on new, row - HG = +1/9 points per median step and pooled +2 / +3;
    on collected -0.25 per step; HG - BC +20 / +22 collected, +1 / +2 new. A σ mapped to the wrong row, the sets
    swapped, or H4's difference taken the other way round gives other numbers; the sides are the stated ones."""
    lineages = {}
    for l, (gap_c, gap_n, pooled_new) in zip((5, 6), ((0.20, 0.01, 0.02), (0.22, 0.02, 0.03))):
        collected = _rates(0.60, 0.60 - gap_c, -0.0025, 0.59)
        new = _rates(0.55, 0.55 - gap_n, 1 / 900, 0.55 + pooled_new)  # 900 episodes a row
        lineages[l] = _lineage_files(nt, l, collected, new)
    assert sorted(nt.complete(lineages)) == [5, 6]
    q = nt.per_lineage(lineages)
    assert q["slope_new"] == pytest.approx([100 / 900] * 2, abs=1e-9)
    assert q["slope_collected"] == pytest.approx([-0.25, -0.25], abs=1e-9)
    assert q["pooled_new"] == pytest.approx([2.0, 3.0], abs=1e-9)
    assert q["hg_bc_gap"] == pytest.approx([19.0, 20.0], abs=1e-9)
    assert q["zero_new"] == pytest.approx([0.0, 0.0], abs=1e-9)
    res = {name: (side, r) for name, _, side, r, _ in nt.stated_tests(lineages)}
    assert [res[h][0] for h in ("H1", "H2", "H3", "H4")] == [">", ">", "<", ">"]
    assert res["H2"][1][0] == pytest.approx(2.5) and res["H2"][1][4] < 0.1      # t = 5 over 1 df: p = 0.063
    assert res["H4"][1][0] == pytest.approx(19.5) and res["H4"][1][4] < 0.02
    assert nt.pooled_sigma(lineages[5], 5) == pytest.approx(math.sqrt(6e-4 / 3) / 0.0176)
    assert nt.table(lineages)[2].startswith("| bc | 39.0 ± 1.0 | 53.5 ± 0.5 |")


def test_one_sided_p_takes_the_stated_side(nt):
    """A positive mean has a small p for '>' and a large one for '<' (p_> + p_< = 1)."""
    m, se, t, df, p_up = nt.one_sided([1.0, 2.0, 1.5, 2.5], ">")
    *_, p_down = nt.one_sided([1.0, 2.0, 1.5, 2.5], "<")
    assert p_up < 0.01 and p_up + p_down == pytest.approx(1.0)


def test_evaluate_lineage_writes_each_row_on_the_new_seeds_and_resumes(nt, tmp_path, monkeypatch):
    """--evaluate: every study policy (pi_0, BC, the six rows) evaluated on the study's seeds with one sampling
    seed, its file's hash recorded; a second call keeps the files (the step resumes); a folder of another
    config is refused before anything is written."""
    root = tmp_path / "run"
    config = json.load(open(os.path.join(START, "config.json")))
    config["methods"] = ["bc", "hg_dagger", "zero_noise", "fixed_4", "fixed_8", "fixed_16", "pooled"]
    config["name"] = "table1_strong_hg_dagger-zero_noise-fixed_4-fixed_8-fixed_16-pooled"  # as --methods names it
    (root / "checkpoints").mkdir(parents=True)
    (root / "lineage_5" / "round_1" / "checkpoints").mkdir(parents=True)
    json.dump(config, open(root / "config.json", "w"))
    policy = os.path.join(START, "checkpoints", "bc_continued.pt")
    for rel in nt.study_policies(5).values():
        os.symlink(policy, root / rel)
    monkeypatch.setattr(nt, "NEW_SEEDS", (30_000, 30_001))
    nt.evaluate_lineage(str(root), 5, log=lambda m: None)
    files = sorted(os.listdir(root / "lineage_5" / nt.NEW))
    assert files == sorted(f"{r}.json" for r in ("pi0", "bc") + nt.ROWS)
    first = json.load(open(root / "lineage_5" / nt.NEW / "pooled.json"))
    assert first["seeds"] == [30_000, 30_001] and np.shape(first["success"]) == (2, config["eval_repeats"])
    assert first["policy"] == "lineage_5/round_1/checkpoints/pooled.pt" and len(first["policy_sha256"]) == 64
    same = json.load(open(root / "lineage_5" / nt.NEW / "hg_dagger.json"))
    assert same["success"] == first["success"] and same["sample_seed"] == first["sample_seed"]  # paired draws
    stamp = os.path.getmtime(root / "lineage_5" / nt.NEW / "pooled.json")
    nt.evaluate_lineage(str(root), 5, log=lambda m: None)
    assert os.path.getmtime(root / "lineage_5" / nt.NEW / "pooled.json") == stamp
    config["methods"] = ["bc", "hg_dagger", "pooled"]
    json.dump(config, open(root / "config.json", "w"))
    shutil.rmtree(root / "lineage_5" / nt.NEW)
    with pytest.raises(SystemExit, match="not the study's run folder"):
        nt.evaluate_lineage(str(root), 5, log=lambda m: None)
    assert not (root / "lineage_5" / nt.NEW).exists()


def test_evaluate_policy_parses_seeds_and_refuses_bad_ones(load_benchmark):
    ep = load_benchmark("evaluate_policy")
    assert ep.parse_seeds("30000-30002,7") == [30000, 30001, 30002, 7]
    for bad, words in (("3-1", "start <= its end"), ("a-b", "not a seed"), ("", "names no seed"),
                       ("5,5", "twice"), ("-3", "not a seed")):
        with pytest.raises(ValueError, match=words):
            ep.parse_seeds(bad)


def test_evaluate_policy_interval_is_the_t_interval_over_scenarios(load_benchmark):
    """Scenario means 0, 1/3, 2/3, 1 (x 100): mean 50, SD 43.03, t(0.975, 3) = 3.182: half-width 68.5."""
    ep = load_benchmark("evaluate_policy")
    table = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]]
    mean, half = ep.interval(table)
    assert mean == pytest.approx(50.0)
    assert ep.t_quantile(0.975, 3) == pytest.approx(3.1824, abs=1e-3)
    assert half == pytest.approx(3.1824 * np.std([0, 100 / 3, 200 / 3, 100], ddof=1) / 2, rel=1e-3)


def test_evaluate_policy_command_prints_success_with_its_interval(load_benchmark, capsys):
    ep = load_benchmark("evaluate_policy")
    ep.main([os.path.join(START, "checkpoints", "bc_continued.pt"), "--seeds", "30000-30002", "--repeats", "1"])
    out = capsys.readouterr().out
    assert "success" in out and "95 % t interval over 3 scenarios, 1 repeats each" in out
    with pytest.raises(SystemExit):
        ep.main(["no_such_policy.pt"])


def test_slope_is_the_least_squares_line_through_the_sigmas(nt):
    """slope() on a curved response: cov(sigma, d) / var(sigma), not a higher coefficient or an end-to-end rise."""
    sig = np.array([0.0, 4.0, 8.0, 16.0])
    d = np.array([0.0, 1.0, 4.0, 9.0])
    expected = ((sig - sig.mean()) * (d - d.mean())).sum() / ((sig - sig.mean()) ** 2).sum()
    assert nt.slope(dict(zip(sig, d))) == pytest.approx(expected)
    assert nt.slope({16: 9.0, 0: 0.0, 8: 4.0, 4: 1.0}) == pytest.approx(expected)   # any order of the keys


def test_the_figure_is_drawn_from_the_lineage_files(nt, tmp_path):
    lineages = {l: _lineage_files(nt, l, _rates(0.6, 0.4, -0.0025, 0.59), _rates(0.55, 0.54, 1 / 900, 0.57))
                for l in (5, 6)}
    nt.figure(lineages, str(tmp_path / "f.png"))
    assert (tmp_path / "f.png").stat().st_size > 10_000


def _varied_lineages(nt):
    """Two lineages whose rows differ scenario by scenario (the first k scenarios solved, k from each rate)."""
    out = {}
    for l, (gap_c, gap_n, pooled_new) in zip((5, 6), ((0.20, 0.01, 0.02), (0.22, 0.05, -0.03))):
        out[l] = _lineage_files(nt, l, _rates(0.60, 0.60 - gap_c, -0.0025 * (l - 4), 0.59),
                                _rates(0.55, 0.55 - gap_n, 0.002 * (l - 4), 0.55 + pooled_new))
    return out


def test_scenario_terms_are_the_stated_quantities_spread_over_the_scenarios(nt):
    """Each quantity's per-scenario terms, averaged over the scenarios and summed over the sets, give per_lineage()'s
    value in every lineage: a wrong slope weight, a set swapped, H4's new-set term with the wrong sign or a row
    compared against the wrong one gives another number."""
    lineages = _varied_lineages(nt)
    q = nt.per_lineage(lineages)
    unseen = {l: {row: nt.per_scenario(f, l, row, "unseen").mean() for row in ("bc",) + nt.ROWS}
              for l, f in lineages.items()}
    new = {l: nt.rates(f, l, True) for l, f in lineages.items()}
    q["hg_bc_new_unseen"] = [(new[l]["hg_dagger"] - new[l]["bc"]) - (unseen[l]["hg_dagger"] - unseen[l]["bc"])
                             for l in lineages]
    q["zero_new_unseen"] = [(new[l]["zero_noise"] - new[l]["hg_dagger"]) -
                            (unseen[l]["zero_noise"] - unseen[l]["hg_dagger"]) for l in lineages]
    for key in q:
        terms = nt.scenario_terms(lineages, key)
        assert all(m.shape == (2, 300 if s == "new" else 100) for s, m in terms.items()), key
        assert sum(m.mean(axis=1) for m in terms.values()) == pytest.approx(q[key], abs=1e-9), key
    assert q["hg_bc_new_unseen"] == pytest.approx([1.0, 1.0])          # HG - BC: new 1 / 5 points, unseen 1 less
    assert set(nt.scenario_terms(lineages, "hg_bc_gap")) == {"collected", "new"}
    assert set(nt.scenario_terms(lineages, "zero_new_unseen")) == {"new", "unseen"}
    with pytest.raises(ValueError, match="'collected', 'new' or 'unseen'"):
        nt.per_scenario(lineages[5], 5, "pooled", "other")
    assert list(nt.scenario_terms(lineages, "slope_collected")) == ["collected"]
    assert nt.slope_weights() == pytest.approx({"zero_noise": -7 / 140, "fixed_4": -3 / 140, "fixed_8": 1 / 140,
                                                "fixed_16": 9 / 140})


def test_mean_squares_and_the_variance_components_se_by_hand(nt):
    """[[1, 2], [3, 6]]: grand mean 3, lineage means 1.5 / 4.5, scenario means 2 / 4, residuals ±0.5: MS_L = 2 x 4.5
    = 9, MS_S = 2 x 2 = 4, MS_E = 1 / 1 = 1; SE^2 = (9 + 4 - 1) / 4 = 3, the interval 3 ± t(0.975, 1) sqrt(3).
    Catches a mean square without its count (MS_L without C), a wrong df, a sign of the formula turned, a z or
    a df of R x C in place of the lineages' R - 1."""
    assert nt.mean_squares([[1.0, 2.0], [3.0, 6.0]]) == pytest.approx((9.0, 4.0, 1.0))
    mean, se, low, high = nt.components_se({"new": np.array([[1.0, 2.0], [3.0, 6.0]])})
    assert (mean, se) == pytest.approx((3.0, math.sqrt(3.0)))
    assert (low, high) == pytest.approx((3 - 12.7062 * math.sqrt(3), 3 + 12.7062 * math.sqrt(3)), rel=1e-4)
    rng = np.random.default_rng(1)                                     # a 3 x 4 table against numpy's own sums
    y = rng.normal(size=(3, 4))
    fit = y.mean(axis=1, keepdims=True) + y.mean(axis=0) - y.mean()
    assert nt.mean_squares(y) == pytest.approx((4 * y.mean(axis=1).var(ddof=1), 3 * y.mean(axis=0).var(ddof=1),
                                                ((y - fit) ** 2).sum() / 6))


def test_the_variance_components_se_is_the_lineage_se_without_a_scenario_effect(nt):
    """Every scenario column with one mean (MS_S = 0 < MS_E): the scenarios add nothing, and the SE is the plain SE
    over the lineages' means. Catches the scenario part left negative (then the SE falls below the lineages'
    alone) and the residual counted in again beside MS_L (the two-way bootstrap's error)."""
    rng = np.random.default_rng(2)
    y = rng.normal(size=(6, 40)) + np.arange(6.0)[:, None]
    y -= y.mean(axis=0) - y.mean()                                     # the scenarios' means made equal
    _, ms_s, ms_e = nt.mean_squares(y)
    assert ms_s == pytest.approx(0.0, abs=1e-12) and ms_e > 0.5
    assert nt.components_se({"new": y})[1] == pytest.approx(y.mean(axis=1).std(ddof=1) / math.sqrt(6))


def test_the_variance_components_se_is_the_spread_of_the_mean_over_fresh_draws(nt):
    """Tables y = lineage + scenario + residual drawn 3,000 times (SDs 1, 2, 3; R = 6, C = 20): the mean of SE^2
    is Var(mean) = 1/6 + 4/20 + 9/120 (unbiased), within 4 %. Catches the lineage part shrunk by (R - 1)/R, the
    residual counted three times (+2 x 9/120: +19 %) and the scenario part left out (-45 %)."""
    rng = np.random.default_rng(3)
    r, c = 6, 20
    se2 = [nt.components_se({"new": rng.normal(0, 1, (r, 1)) + rng.normal(0, 2, (1, c)) + rng.normal(0, 3, (r, c))})[1]
           ** 2 for _ in range(3000)]
    assert np.mean(se2) == pytest.approx(1 / r + 4 / c + 9 / (r * c), rel=0.04)


def test_the_variance_components_se_over_two_sets_counts_the_lineages_once(nt):
    """Two sets whose lineage effects cancel in the sum (H4 is such a sum): each lineage's quantity is the same, so
    the SE is the two sets' scenario parts alone, var(b) / C + var(b') / C'. Adding the two sets' own SEs instead
    counts the lineages' spread twice; one set's scenario part left out gives less."""
    rng = np.random.default_rng(4)
    a, b, b2 = rng.normal(0, 5, (8, 1)), rng.normal(0, 1, (1, 30)), rng.normal(0, 2, (1, 50))
    mean, se, *_ = nt.components_se({"collected": a + b, "new": -a + b2})
    assert mean == pytest.approx(b.mean() + b2.mean())
    assert se == pytest.approx(math.sqrt(b.var(ddof=1) / 30 + b2.var(ddof=1) / 50))


def test_the_scenario_part_prints_every_quantity_with_its_mean_squares(nt):
    lines = nt.scenario_part(_varied_lineages(nt))
    assert len(lines) == 2 + 8 and lines[2].startswith("| H1 slope, new | ") and "…" in lines[-1]
    assert "collected " in lines[5] and "; new " in lines[5]                  # H4: each set's mean squares
    assert lines[-1].startswith("| (zero_noise − HG-DAgger) new − unseen |") and "; unseen " in lines[-1]


def test_the_slope_without_zero_noise_two_ways(nt):
    """Rows built with row - HG-DAgger = p sigma on the fixed rows and zero_noise z under HG-DAgger: the stated
    slope is p + 0.05 z (zero_noise's weight -7 / 140), the pilot's (HG-DAgger at 0) and the fixed rows' alone
    are p; the printed parts sum to the stated slope. A sigma mapped to another row, HG-DAgger left out at 0 or
    zero_noise kept in gives other numbers."""
    lineages = {}
    for l, (p, z) in zip((5, 6, 7), ((1 / 900, 0.02), (2 / 900, 0.01), (3 / 900, 0.03))):
        new = {**_rates(0.55, 0.54, p, 0.56), "zero_noise": 0.55 - z}
        lineages[l] = _lineage_files(nt, l, _rates(0.6, 0.4, -0.0025, 0.59), new)
    s = nt.slopes(lineages, True)
    assert s["stated"] == pytest.approx([100 / 900 + 0.05 * 2, 200 / 900 + 0.05 * 1, 300 / 900 + 0.05 * 3])
    assert s["hg_at_0"] == pytest.approx([100 / 900, 200 / 900, 300 / 900])
    assert s["fixed_only"] == pytest.approx([100 / 900, 200 / 900, 300 / 900])
    assert nt.slopes(lineages, False)["hg_at_0"] == pytest.approx([-0.25] * 3)
    lines = nt.slope_parts(lineages)
    parts = [float(line.split("|")[5]) for line in lines[2:6]]
    assert sum(parts) == pytest.approx(np.mean(s["stated"]), abs=2e-3)
    assert lines[6].startswith("| | the stated slope | | | +0.322 |")
    assert lines[7] == "zero_noise's part of the slope on new: +0.100 of +0.322 (31 %)"
    assert lines[8].startswith("the slope with HG-DAgger at σ = 0 (the pilot's slope): new +0.222 ± 0.064")


def test_lineages_needed_is_the_first_count_with_the_power(nt):
    """The smallest n whose power reaches the target: n - 1 falls short (an off-by-one or a '>' for '>=' fails);
    more spread needs more lineages."""
    n = nt.lineages_needed(0.135, 0.140, 0.0125)
    assert nt.power(0.135, 0.140, n, 0.0125) >= 0.8 > nt.power(0.135, 0.140, n - 1, 0.0125)
    assert nt.lineages_needed(0.135, 0.090, 0.0125) < n
    assert nt.lineages_needed(0.01, 1.0, 0.0125) is None                  # beyond 60 lineages
    assert nt.lineages_needed(0.135, 0.140, 0.0125, n_max=n) == n         # the last count asked is tried ...
    assert nt.lineages_needed(0.135, 0.140, 0.0125, n_max=n - 1) is None  # ... and none beyond it
    assert nt.lineages_needed(10.0, 0.1, 0.05) == 2                       # two lineages: the fewest a t test takes


def test_observed_power_uses_the_studys_sds_at_the_designs_effects_and_level(nt):
    """H1 at the pilot's mean slope and H2 at +2 points, each at 0.05 / 4, with the SDs of the study's own lineages:
    the printed powers are power() of those, the SD ratio is the study's over the pilot's. A pilot SD in place of the
    study's, the level 0.05, or the stated slope's mean in place of the pilot's gives other numbers."""
    lineages, pilot = nt.complete(nt.load_lineages(nt.RESULTS)), nt.load_lineages(nt.PILOT)
    d, q = nt.pilot_differences(pilot), nt.per_lineage(lineages)
    sd1, sd2 = np.std(q["slope_new"], ddof=1), np.std(q["pooled_new"], ddof=1)
    p1 = nt.power(np.mean(d["slope"]), sd1, len(lineages), 0.0125)
    lines = nt.observed_power(lineages, pilot)
    assert f"power {p1:.2f} at 8 lineages" in lines[1] and f"{sd1 / np.std(d['slope'], ddof=1):.2f} ×" in lines[1]
    assert f"80 % needs {nt.lineages_needed(np.mean(d['slope']), sd1, 0.0125)}" in lines[1]
    assert f"SD {sd2:.3f}" in lines[2] and "> 0.99" in lines[2] and nt.power(2.0, sd2, 8, 0.0125) > 0.99
    assert f"the pilot's {np.std(d['pooled'], ddof=1):.3f}" in lines[2] and "+0.135" in lines[1]


def test_the_committed_study_prints_the_numbers_its_readmes_quote(nt, capsys):
    """The script over the committed lineage files prints what benchmarks/README.md and the study's README quote
    after the fact: the slope's parts, the power, the variance-components SEs and intervals."""
    nt.main([])
    out = capsys.readouterr().out
    for line in ("| 0 | zero_noise | -0.050 | -1.69 ± 0.31 | +0.085 |",
                 "zero_noise's part of the slope on new: +0.085 of +0.125 (68 %)",
                 "the slope with HG-DAgger at σ = 0 (the pilot's slope): new +0.040 ± 0.043, t(7) = 0.94, p = 0.19",
                 "the slope over σ 4 / 8 / 16 alone: new +0.042 ± 0.072",
                 "1.56 × the pilot's 0.090: power 0.50 at 8 lineages; 80 % needs 13",
                 "power > 0.99 at 8 lineages",
                 "| H2 pooled − HG-DAgger, new | -1.028 | 0.241 | 139 / 693 / 417 | 0.416 | -2.011 … -0.045 |",
                 "| zero_noise − HG-DAgger, new | -1.694 | 0.311 | 233 / 703 / 418 | 0.464 | -2.792 … -0.597 |",
                 "| H4 (HG-DAgger − BC) collected − new | +19.125 | 0.716 |",
                 "| (HG-DAgger − BC) new − unseen (20000..20099) | +1.875 | 0.732 |",
                 "variance components"):
        assert line in out, line


def test_the_paired_figure_places_each_row_at_its_sigma(nt, tmp_path):
    """Each row minus its lineage's HG-DAgger, at its sigma: zero_noise at 0, the fixed rows at theirs, pooled at
    each lineage's calibrated sigma; the figure is drawn."""
    lineages = _varied_lineages(nt)
    points = {row: (x, d) for row, x, d in nt.paired_points(lineages, True)}
    assert list(points) == ["zero_noise", "fixed_4", "fixed_8", "fixed_16", "pooled"]
    assert [points[r][0][0] for r in ("zero_noise", "fixed_4", "fixed_8", "fixed_16")] == [0.0, 4.0, 8.0, 16.0]
    assert points["pooled"][0] == pytest.approx([nt.pooled_sigma(lineages[l], l) for l in (5, 6)])
    rates = {l: nt.rates(f, l, True) for l, f in lineages.items()}
    assert points["fixed_16"][1] == pytest.approx([rates[l]["fixed_16"] - rates[l]["hg_dagger"] for l in (5, 6)])
    collected = {l: nt.rates(f, l, False) for l, f in lineages.items()}
    assert nt.paired_points(lineages, False)[3][2] == pytest.approx(
        [collected[l]["fixed_16"] - collected[l]["hg_dagger"] for l in (5, 6)])       # the set asked for
    nt.paired_figure(lineages, str(tmp_path / "p.png"))
    assert (tmp_path / "p.png").stat().st_size > 10_000
    nt.paired_figure({5: lineages[5]}, str(tmp_path / "one.png"))     # an interim look at one lineage: no interval
    assert (tmp_path / "one.png").stat().st_size > 10_000
