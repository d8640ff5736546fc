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
    for key in ("slope_new", "slope_collected", "pooled_new", "hg_bc_gap", "zero_new", "zero_collected"):
        terms = nt.scenario_terms(lineages, key)
        assert all(m.shape == (2, 300 if new else 100) for new, m in terms.items()), key
        assert sum(m.mean(axis=1) for m in terms.values()) == pytest.approx(q[key], abs=1e-9), key
    assert set(nt.scenario_terms(lineages, "hg_bc_gap")) == {False, True}
    assert nt.slope_weights() == pytest.approx({"zero_noise": -7 / 140, "fixed_4": -3 / 140, "fixed_8": 1 / 140,
                                                "fixed_16": 9 / 140})


def test_two_way_bootstrap_resamples_lineages_and_each_sets_scenarios_apart(nt):
    """Lineages alike but scenarios not: the SE is the scenarios' (a bootstrap of lineages alone gives 0).
    Scenarios alike but lineages not: the lineages' (one of scenarios alone gives 0). One array entered for two
    sets with opposite signs: the draws cancel only if both sets reuse one draw of scenario indices."""
    scen = np.tile(np.arange(200.0) % 10, (8, 1))                      # 8 lineages alike; scenarios 0..9 repeating
    se, low, high = nt.two_way_bootstrap({True: scen}, draws=4000)
    assert se == pytest.approx(np.std(scen[0]) / math.sqrt(200), rel=0.1) and low < 4.5 < high
    lin = np.tile(np.arange(8.0)[:, None], (1, 50))                     # lineages 0..7, every scenario alike
    se, *_ = nt.two_way_bootstrap({True: lin}, draws=4000)
    assert se == pytest.approx(np.std(np.arange(8.0)) / math.sqrt(8), rel=0.1)
    se, *_ = nt.two_way_bootstrap({False: scen, True: -scen}, draws=4000)
    assert se == pytest.approx(math.sqrt(2) * np.std(scen[0]) / math.sqrt(200), rel=0.1)
    assert nt.two_way_bootstrap({True: scen}, draws=500) == nt.two_way_bootstrap({True: scen}, draws=500)  # seeded


def test_the_scenario_part_prints_every_quantity_with_both_ses(nt):
    lines = nt.scenario_part(_varied_lineages(nt))
    assert len(lines) == 2 + 6 and lines[2].startswith("| H1 slope, new | ") and "…" in lines[-1]
