"""Statistics of dagger.py and its t distribution (dagger.student_t_cdf; self-written, no scipy) against closed
forms and known table values."""
import math
from dataclasses import replace

import matplotlib.image
import numpy as np
import pytest

import dagger
from experiment import checkpoints, environments, report, run_folder


def t_pdf(x, df):
    c = math.exp(math.lgamma((df + 1) / 2) - math.lgamma(df / 2)) / math.sqrt(df * math.pi)
    return c * (1 + x * x / df) ** (-(df + 1) / 2)


@pytest.mark.parametrize("t", [-3.0, -0.5, 0.0, 0.7, 1.0, 4.2])
def test_t_cdf_closed_forms(t):
    # df = 1 is the Cauchy distribution, df = 2 has a simple closed form
    assert dagger.student_t_cdf(t, 1) == pytest.approx(0.5 + math.atan(t) / math.pi, abs=1e-12)
    assert dagger.student_t_cdf(t, 2) == pytest.approx(0.5 + t / (2 * math.sqrt(2 + t * t)), abs=1e-12)


@pytest.mark.parametrize("df,quantile,prob", [(4, 2.776445, 0.975), (5, 2.570582, 0.975),
                                              (10, 1.812461, 0.95), (30, 2.042272, 0.975),
                                              (3, 5.840909, 0.995)])
def test_t_cdf_table_quantiles(df, quantile, prob):
    assert dagger.student_t_cdf(quantile, df) == pytest.approx(prob, abs=1e-6)
    assert dagger.student_t_cdf(-quantile, df) == pytest.approx(1 - prob, abs=1e-6)


@pytest.mark.parametrize("df", [1.5, 3, 7, 25])
def test_t_cdf_matches_numeric_integration(df):
    xs = np.linspace(-60, 1.3, 400_001)
    pdf = np.array([t_pdf(x, df) for x in xs[::100]])  # coarse check of shape first
    assert np.all(pdf > 0)
    fine = t_pdf_vec(xs, df)
    integral = np.trapezoid(fine, xs) + tail_below(-60, df)
    assert dagger.student_t_cdf(1.3, df) == pytest.approx(integral, abs=2e-5)


def t_pdf_vec(x, df):
    c = math.exp(math.lgamma((df + 1) / 2) - math.lgamma(df / 2)) / math.sqrt(df * math.pi)
    return c * (1 + x * x / df) ** (-(df + 1) / 2)


def tail_below(x, df):
    # P(T < x) for very negative x: integrate the pdf's power-law tail analytically (approximation
    # c |x|^-df / df, error O(|x|^-df-2), negligible at x = -60).
    c = math.exp(math.lgamma((df + 1) / 2) - math.lgamma(df / 2)) / math.sqrt(df * math.pi)
    return c * df ** ((df + 1) / 2) * abs(x) ** (-df) / df


def test_incomplete_beta_symmetry_and_closed_forms():
    for a, b, x in [(2.0, 3.0, 0.3), (0.5, 0.5, 0.9), (10.0, 0.5, 0.95)]:
        assert dagger.incomplete_beta(a, b, x) == pytest.approx(1 - dagger.incomplete_beta(b, a, 1 - x),
                                                                   abs=1e-12)
    # I_x(1, 1) = x (uniform), I_x(a, 1) = x^a
    assert dagger.incomplete_beta(1.0, 1.0, 0.37) == pytest.approx(0.37, abs=1e-12)
    assert dagger.incomplete_beta(3.0, 1.0, 0.6) == pytest.approx(0.6 ** 3, abs=1e-12)
    # I_x(1, b) = 1 - (1 - x)^b near x = 1, where the continued fraction must be taken on the symmetric side: read
    # directly there it gives 0.98999 for b = 1/2 (the t distribution's b) and a negative number for b = 5
    for b in (0.5, 5.0):
        assert dagger.incomplete_beta(1.0, b, 0.9999) == pytest.approx(1 - 0.0001 ** b, abs=1e-12)


def test_paired_ttest_known_value():
    a = [81.9, 84.8, 85.1, 88.6, 89.1]
    b = [79.9, 81.9, 83.3, 85.3, 87.3]
    d = np.subtract(a, b)
    t_expected = d.mean() / (d.std(ddof=1) / math.sqrt(5))
    t, df, p = dagger.paired_ttest(a, b)
    assert df == 4
    assert t == pytest.approx(t_expected)
    assert p == pytest.approx(2 * (1 - dagger.student_t_cdf(abs(t_expected), 4)))
    # the paper's reported t(4) = 5.75 gives p ~ 0.005
    assert 2 * (1 - dagger.student_t_cdf(5.75, 4)) == pytest.approx(0.0045, abs=3e-4)


def test_paired_ttest_symmetry_and_errors():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=6), rng.normal(size=6)
    t1, _, p1 = dagger.paired_ttest(a, b)
    t2, _, p2 = dagger.paired_ttest(b, a)
    assert t1 == pytest.approx(-t2) and p1 == pytest.approx(p2)
    with pytest.raises(ValueError, match="at least 2"):
        dagger.paired_ttest([1.0], [2.0])


def test_equal_gains_in_episode_counts_have_no_spread_whatever_the_float_rounding():
    """Fails if the paired tests take float rounding for spread: success rates are counts of 300 episodes, and
    two lineages that both gain 3 episodes (47.0 -> 48.0, 46.67 -> 47.67) differ by 1.0 and 1.0000000000000071
    in floats; without paired_differences' rounding t was 2.8e14 and p 2e-15 (seen in table1's unseen K = 1)."""
    rate = lambda n: float(100 * (np.arange(300) < n).mean())  # noqa: E731 (a cell: n of 300 episodes succeed)
    a, b = [rate(144), rate(143)], [rate(141), rate(140)]
    assert np.subtract(a, b)[0] != np.subtract(a, b)[1]                # the float differences are not equal ...
    assert dagger.paired_ttest(a, b) == (math.inf, 1, 0.0)              # ... but the gains are: no spread
    assert report.degenerate(a, b).startswith("every lineage differs by exactly +1.0 points")
    assert dagger.tost(a, b, 2.0)[0] == 0.0 and dagger.tost(a, b, 0.5)[0] == 1.0


def test_paired_differences_are_kept_to_1e_9_points():
    """The rounding's grain is the docstring's 1e-9 points: a coarser one would merge true differences of a few
    1e-9, a finer one keep float noise of 4e-10 (both below any difference 300 episodes can make, 0.33 points)."""
    d = dagger.paired_differences([50.0 + 4e-10, 50.0 + 2e-9, 50.0 + 3e-8], [50.0, 50.0, 50.0])
    np.testing.assert_array_equal(d, [0.0, 2e-9, 3e-8])


def test_tost_equivalent_and_not():
    ref = np.array([85.0, 86.0, 87.0, 88.0, 89.0])
    close = ref + np.array([0.2, -0.1, 0.1, -0.2, 0.0])
    far = ref + np.array([4.8, 5.2, 5.0, 4.9, 5.1])
    p_close, _, _ = dagger.tost(close, ref, 2.0)
    p_far, _, _ = dagger.tost(far, ref, 2.0)
    assert p_close < 0.01
    assert p_far > 0.5
    with pytest.raises(ValueError, match="margin"):
        dagger.tost(close, ref, 0.0)


def test_collection_keeps_the_interventions_of_the_label_rule(tmp_path, monkeypatch):
    """D_k (collect_interventions, the paper's recipe) keeps whole the interventions diffusion.expert_runs keeps
    (Sec. IV-C: at least H steps) and no shorter one. Fails if a short intervention is kept, a kept one is cut, or an
    episode left with no intervention is kept (the rule itself: tests/test_diffusion.py)."""
    cfg = dagger.Config(name="tiny", horizon=3, n_act=2, eval_scenarios=2, eval_repeats=1)
    recorded = [np.array([0, 1, 1, 0, 1, 1, 1, 1, 0, 1, 1], bool), np.array([0, 1, 1, 0, 0, 1, 0, 0, 0, 0, 0], bool)]

    def fake_rollout(env_list, policy, n_act, gen, oracle=None, log=None, seed=0):
        return [{"obs": np.zeros((11, 4), np.float32), "q": np.zeros((11, 2)), "action": np.zeros((11, 2)),
                 "expert": e.copy(), "seed": i, "success": True, "interventions": 3} for i, e in enumerate(recorded)]
    monkeypatch.setattr(dagger, "rollout", fake_rollout)
    D = dagger.collect_interventions(cfg, (0, 1), type("Stub", (), {"device": "cpu"})(), np.zeros((2, 1), bool))
    assert len(D) == 1 and D[0]["expert"].tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 0, 0, 0]


def test_mean_se():
    m, se, n = report.mean_se([80.0, 82.0, 84.0])
    assert (m, n) == (82.0, 3)
    assert se == pytest.approx(2.0 / math.sqrt(3))


def test_summarize_pairs_hg_dagger_with_bc_per_round_and_finds_the_best_fixed_sigma():
    cfg = dagger.Config(name="t", rounds=2, lineages=3, methods=("bc", "hg_dagger", "fixed_2", "fixed_4", "pooled"))
    results = {"bc": {"all": [60.0]},
               "hg_dagger": {"0": [62.0, 65.0], "1": [64.0, 61.0], "2": [63.0, 66.0]},
               "fixed_2": {"0": [60.0, 70.0], "1": [61.0, 70.0], "2": [62.0, 70.0]},
               "fixed_4": {"0": [66.0, 60.0], "1": [65.0, 61.0], "2": [67.0, 62.0]},
               "pooled": {"0": [65.0, 67.0], "1": [66.0, 66.0], "2": [64.0, 68.0]}}
    table, stats = report.summarize(cfg, results)
    r1, r2 = stats["hg_dagger_vs_bc"]["1"], stats["hg_dagger_vs_bc"]["2"]
    assert r1["diff"] == pytest.approx(3.0) and r1["n_above"] == 3 and r1["df"] == 2
    t, df, p = dagger.paired_ttest([62.0, 64.0, 63.0], [60.0] * 3)  # one pi_0: the pairs share BC's number
    assert r1["t"] == pytest.approx(t) and r1["p"] == pytest.approx(p)
    assert r2["diff"] == pytest.approx(4.0) and r2["n_above"] == 3
    assert stats["best_fixed_per_round"] == {"1": "fixed_4", "2": "fixed_2"}  # per round, in hindsight
    assert stats["best_fixed"] == "fixed_2"  # averaged over rounds: 65.5 vs 63.5
    text = report.format_table(cfg, table, stats)
    assert "HG-DAgger vs BC at each round" in text and "K=1: +3.0 points, above BC in 3 of 3 lineages" in text


def test_format_table_adds_the_unseen_scenarios_with_their_own_paired_statistics():
    cfg = dagger.Config(name="t", rounds=1, lineages=3, methods=("bc", "hg_dagger", "pooled"))
    results = {"bc": {"all": [60.0]}, "hg_dagger": {"0": [70.0], "1": [72.0], "2": [71.0]},
               "pooled": {"0": [74.0], "1": [75.0], "2": [73.0]}}
    unseen = {"bc": {"all": [50.0]}, "hg_dagger": {"0": [55.0], "1": [57.0], "2": [54.0]},
              "pooled": {"0": [58.0], "1": [61.0], "2": [59.0]}}
    table, stats = report.summarize(cfg, results)
    table_u, stats_u = report.summarize(cfg, unseen)
    text = report.format_table(cfg, table, stats, (table_u, stats_u))
    main, second = text.split("**Unseen scenarios.**")
    assert "the 100 evaluation scenarios, on which HG-DAgger collected (the authors' protocol)" in main
    assert "100 unseen scenarios (never trained on)" in second
    assert "| HG-DAgger | 71.0 ± 0.6 (3) |" in main and "| HG-DAgger | 55.3 ± 0.9 (3) |" in second
    t, df, p = dagger.paired_ttest([58.0, 61.0, 59.0], [55.0, 57.0, 54.0])  # the same paired test, unseen
    assert f"+{np.mean([3.0, 4.0, 5.0]):.1f} points, t({df}) = {t:.2f}, p = {p:.3g}" in second
    assert "K=1: -5.7 points" not in second and "K=1: +5.3 points, above BC in 3 of 3 lineages" in second
    assert "Unseen" not in report.format_table(dagger.Config(name="t"), table, stats)


def test_calibration_lines_compare_with_the_paper_in_its_unit():
    cfg = dagger.Config(name="t", rounds=1, lineages=1, methods=("bc", "hg_dagger", "fixed_4", "pooled"))
    m = 0.0245  # our planar median step; the paper's is 0.0176
    sigma_rad = [4.0 * 0.0176, 4.5 * 0.0176, 5.0 * 0.0176]
    per = {"0": {"sigma_per_joint": [v / m for v in sigma_rad], "W": 8.0 * 0.0176 / m, "median_step": m,
                 "sigma_per_joint_rad": sigma_rad, "W_rad": 8.0 * 0.0176, "fit": "fit",
                 "W_paper": 8.0, "W_ci_paper": [7.5, 8.6], "sigma_per_joint_paper": [4.0, 4.5, 5.0]},
           "1": {"sigma_per_joint": [v / m for v in sigma_rad], "W": 8.0 * 0.0176 / m, "median_step": m,
                 "sigma_per_joint_rad": sigma_rad, "W_rad": 8.0 * 0.0176, "fit": "FALLBACK: no fit, ...",
                 "W_paper": 8.0, "W_ci_paper": None, "sigma_per_joint_paper": [4.0, 4.5, 5.0]}}
    stats = {"calibration": {"1": per}, "best_fixed_per_round": {"1": "fixed_4"}}
    text = "\n".join(report.calibration_lines(replace(cfg, lineages=2), stats))
    assert ("sigma = 4.00, 4.50, 5.00 paper median steps (0.070, 0.079, 0.088 rad) (the paper: 3.9–5.1); "
            "W = 8.00 paper median steps (0.141 rad) (the paper: 8.0); 2 lineages; best fixed: sigma = 4") in text
    assert " median steps" not in text.replace("paper median steps", "").replace("the paper's median steps", "")
    # each lineage in the paper's unit, with its interval; a fallback is said in capitals
    assert ("per lineage (the paper's median steps): 0: W 8.00 [7.50–8.60], sigma 4.00/4.50/5.00; "
            "1: W 8.00, sigma 4.00/4.50/5.00 FALLBACK") in text
    one = "\n".join(report.calibration_lines(cfg, {"calibration": {"1": {"0": per["0"]}}}))
    assert "(the paper: 8.0); 1 lineage; best fixed: –" in one and "FALLBACK" not in one


def test_scenario_paired_differences_and_their_se(tmp_path):
    """HG-DAgger - BC and arm - HG-DAgger paired over scenarios (repeats averaged): mean and SE of the
    per-scenario differences, for each set of scenarios; the one-lineage sentence quotes the SE."""
    cfg = dagger.Config(name="t", rounds=1, lineages=1, methods=("bc", "hg_dagger", "fixed_4"), eval_scenarios=4,
                        eval_repeats=2)
    run = run_folder.Run(str(tmp_path), cfg)
    bc = [[0, 0], [1, 1], [0, 1], [0, 0]]          # per scenario: 0, 1, 0.5, 0
    hg = [[1, 1], [1, 1], [1, 0], [0, 0]]          # 1, 1, 0.5, 0      -> HG - BC: 100, 0, 0, 0
    fx = [[1, 1], [0, 1], [1, 1], [1, 0]]          # 1, 0.5, 1, 0.5    -> fixed - HG: 0, -50, 50, 50
    for path, success in [("eval/bc.json", bc), ("lineage_0/round_1/eval/hg_dagger.json", hg),
                          ("lineage_0/round_1/eval/fixed_4.json", fx), ("eval/bc_unseen.json", hg),
                          ("lineage_0/round_1/eval/hg_dagger_unseen.json", bc)]:
        run_folder.write_json(run.path(*path.split("/")), {"success": success})
    p = report.scenario_paired(run)["1"]["0"]
    assert p["hg_dagger"]["vs"] == "bc" and p["hg_dagger"]["diff"] == pytest.approx(25.0)
    assert p["hg_dagger"]["se"] == pytest.approx(np.std([100, 0, 0, 0], ddof=1) / 2)
    assert p["fixed_4"]["vs"] == "hg_dagger" and p["fixed_4"]["diff"] == pytest.approx(12.5)
    assert p["fixed_4"]["se"] == pytest.approx(np.std([0, -50, 50, 50], ddof=1) / 2)
    unseen = report.scenario_paired(run, "unseen")["1"]["0"]
    assert set(unseen) == {"hg_dagger"} and unseen["hg_dagger"]["diff"] == pytest.approx(-25.0)
    lines = report.scenario_paired_lines(cfg, {"1": {"0": p}})
    assert "HG-DAgger − BC: +25.0 ± 25.0" in lines[2] and "fixed_4 − HG-DAgger: +12.5 ± 23.9" in lines[2]
    assert "±24 points" in lines[3]


def test_the_table_prints_and_draws_the_papers_cells_for_the_runs_rows_and_rounds(tmp_path):
    cfg = dagger.Config(name="t", rounds=2, lineages=3, methods=("bc", "hg_dagger", "fixed_4", "pooled", "zero_noise"))
    paper = report.paper_table(cfg)
    assert paper["hg_dagger"] == [(79.9, 0.5, 5), (81.9, 0.7, 5)] and paper["bc"] == [(68.0, 0.2, 1)]
    assert paper["fixed_4"][1] == (86.1, 0.7, 5) and "zero_noise" not in paper  # the control is not the paper's
    results = {"bc": {"all": [60.0]}, "hg_dagger": {"0": [62.0, 65.0], "1": [64.0, 61.0], "2": [63.0, 66.0]},
               "fixed_4": {"0": [66.0, 60.0], "1": [65.0, 61.0], "2": [67.0, 62.0]},
               "pooled": {"0": [65.0, 67.0], "1": [66.0, 66.0], "2": [64.0, 68.0]},
               "zero_noise": {"0": [60.0, 60.0], "1": [61.0, 61.0], "2": [62.0, 62.0]}}
    table, stats = report.summarize(cfg, results)
    ours, theirs = report.format_table(cfg, table, stats).split("The paper's Table I")
    assert "| Pooled Sigma-bar^alpha (Ours) | 82.0 ± 0.6 (5) | 86.2 ± 0.8 (5) |" in theirs
    assert "| HG-DAgger | 63.0 ± 0.6 (3) | 64.0 ± 1.5 (3) |" in ours and "82.0" not in ours
    lever = dagger.Config(name="t", env="engine3d", rounds=2, lineages=3, methods=("bc", "hg_dagger", "fixed_4", "pooled"))
    assert report.paper_table(lever) == {"bc": [(58.0, 1.2, 1)], "hg_dagger": [(57.4, 5.6, 3), (58.1, 4.0, 3)],
                                         "pooled": [(68.8, 4.2, 3), (63.4, 4.8, 3)]}
    five = replace(cfg, rounds=5)
    assert report.paper_table(five)["pooled"][4] == (89.3, 0.5, 5)
    assert report.paper_table(replace(lever, rounds=3))["pooled"][2] is None  # the paper ran 2 rounds there
    path = str(tmp_path / "success_vs_round.png")
    report.plot_success_vs_round(cfg, table, path)
    image = matplotlib.image.imread(path)
    assert image.shape[1] > 1.4 * image.shape[0]  # two panels side by side: this run and the paper's


def test_failure_time_histogram_bins_collisions_by_the_second_they_happen(monkeypatch, capsys, load_benchmark):
    """benchmarks/bc_failures.py's histogram: a collision at step T happened at (T - 1) dt s; the first-second
    share counts collisions only; a checkpoint without a label is refused before anything rolls out."""
    import sys
    failures = load_benchmark("bc_failures")
    rows = [("success", "", 120, 0.01), ("timeout", "", 333, 0.3), ("collision: obstacle", "link 2", 1, 0.5),
            ("collision: obstacle", "palm", 10, 0.5), ("collision: self", "link 1-link 3", 11, 0.4),
            ("collision: obstacle", "palm", 31, 0.4), ("collision: other", "", 250, 0.2)]
    h = failures.failure_times(rows, dt=0.1)
    assert (h["success"], h["timeout"], h["collisions"], h["episodes"]) == (1, 1, 5, 7)
    assert [h[b] for b in failures.TIME_BINS] == [2, 1, 1, 1]  # steps 1, 10 | 11 (1.0 s) | 31 (3.0 s) | 250
    assert h["first_second"] == pytest.approx(2 / 5)
    monkeypatch.setattr(sys, "argv", ["bc_failures.py", "a.pt", "b.pt", "--labels", "BC"])
    with pytest.raises(SystemExit):
        failures.main()
    assert "2 checkpoints" in capsys.readouterr().err


def test_failure_rollout_runs_in_groups_and_closes_each_group_before_the_next(monkeypatch, tmp_path, load_benchmark):
    """bc_failures.roll_out holds at most the env's max_parallel simulators at once (engine3d: one pybullet
    client each; holding every policy's 300 made the 24 GB machine thrash) and classifies every episode."""
    import argparse
    import diffusion
    import envs
    failures = load_benchmark("bc_failures")
    open_now, most = [0], [0]
    make = environments.make_env

    def tracked(name, **kw):
        e = make(name, episode_seconds=0.5, **kw)  # 5 steps: the untrained policy's episodes end fast

        def close():
            open_now[0] -= 1
        e.close = close
        open_now[0] += 1
        most[0] = max(most[0], open_now[0])
        return e
    monkeypatch.setattr(environments, "make_env", tracked)
    monkeypatch.setattr(envs, "eval_seeds", lambda: [10_000, 10_001, 10_002])
    monkeypatch.setattr(envs.PlanarReacher, "max_parallel", 2)
    e = make("planar")
    policy = diffusion.DiffusionPolicy(diffusion.PolicyConfig(obs_dim=e.obs_dim, dof=e.dof, horizon=4, n_act=2, K=5,
                                                              down_dims=(16, 32), n_groups=4, step_embed_dim=32))
    path = str(tmp_path / "p.pt")
    checkpoints.save_policy(policy, path)
    args = argparse.Namespace(env="planar", repeats=2, seed=0)
    rows, angles, scene = failures.roll_out(path, args)
    assert len(rows) == 6 and all(r[0] in ("success", "timeout") or r[0].startswith("collision") for r in rows)
    assert most[0] == 2 and open_now[0] == 0  # groups of 2, every simulator closed
    assert scene["dt"] == e.cfg.dt and not scene["angle_rule"] and len(angles) == 0
