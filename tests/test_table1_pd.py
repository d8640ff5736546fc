"""benchmarks/table1_pd.py (Table I again with the paper's PD label, a stated study): its stated tests on hand-made
lineage files -- each lineage's mean over rounds, P1 and P2 one-sided, P3 a TOST at +-2 against the best fixed sigma
in hindsight, Holm over the three --, the table, the figure, the "no lineage yet" message, the design's power
analysis and lineage count, the new-scenario evaluation and the policies it commits, and the per-round collection
table from the calibrations (checked against the episodes themselves)."""
import gzip
import json
import math
import os
from types import SimpleNamespace

import numpy as np
import pytest

import calibrate
import dagger
import diffusion

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
START = os.path.join(ROOT, "benchmarks", "results", "table1", "start")


@pytest.fixture(scope="module")
def t1(load_benchmark):
    return load_benchmark("table1_pd")


# ---- hand-made lineage files --------------------------------------------------------------------------------------
def _table(points, scenarios, repeats=3):
    """A (scenarios, repeats) success table whose mean is `points` % (a whole number of episodes)."""
    count = round(points / 100.0 * scenarios * repeats)
    assert abs(count - points / 100.0 * scenarios * repeats) < 1e-6, f"{points} points is no count of episodes"
    flat = np.zeros(scenarios * repeats, bool)
    flat[:count] = True
    return flat.reshape(repeats, scenarios).T.tolist()


def _lineage_files(t1, lineage, collected, new, label="pd", bc=(52.0, 54.0)):
    """A lineage file's 'files': collected / new {row: [points at K = 1..5]} (rows not given: 60 / 55 points at
    every round), BC's (collected, new) points; lineage.json with the return label and the start's pi_0."""
    eval_seeds = list(range(10_000, 10_100))
    new_seeds = list(t1.relabel_cost.new_seeds(lineage))
    record = {"config": {"horizon": 20}, "pi0_sha256": t1.START_PI0}
    if label is not None:
        record["return_label"] = label
    files = {"eval/bc.json": {"success": _table(bc[0], 100), "seeds": eval_seeds},
             "eval/pi0.json": {"success": _table(44.0, 100), "seeds": eval_seeds},
             f"lineage_{lineage}/lineage.json": record,
             f"lineage_{lineage}/{t1.NEW}/bc.json": {"success": _table(bc[1], 300), "seeds": new_seeds},
             f"lineage_{lineage}/{t1.NEW}/pi0.json": {"success": _table(50.0, 300), "seeds": new_seeds}}
    for row in t1.ROWS:
        for k in range(1, t1.ROUNDS + 1):
            files[f"lineage_{lineage}/round_{k}/eval/{row}.json"] = {
                "success": _table(collected.get(row, [60.0] * 5)[k - 1], 100), "seeds": eval_seeds}
            files[f"lineage_{lineage}/{t1.NEW}/round_{k}/{row}.json"] = {
                "success": _table(new.get(row, [55.0] * 5)[k - 1], 300), "seeds": new_seeds}
    return files


# per lineage, pooled - HG-DAgger at K = 1..5 on the collected set (multiples of 1/3 point) and on the new set (1/9):
# means over rounds 0.6 / 1.2 / 1.8 (P1) and 2.0 / 2.6 / 3.2 (P2)
P1_DIFFS = {5: [3, 0, 0, 0, 0], 6: [0, 3, 0, 3, 0], 7: [0, 0, 6, 0, 3]}
P2_DIFFS = {5: [2, 2, 2, 2, 2], 6: [3, 3, 2, 2, 3], 7: [3, 3, 3, 4, 3]}
# the fixed sweep on the collected set: fixed_8 has the best mean over rounds (61), fixed_2 the best K = 1 (63),
# fixed_12 the best K = 5 (64), fixed_4 the best on the new set; pooled - fixed_8 over rounds -0.4 / +0.2 / +0.8
FIXED = {"fixed_2": [63, 58, 58, 58, 58], "fixed_4": [59] * 5, "fixed_8": [61] * 5, "fixed_12": [57, 57, 57, 57, 64],
         "fixed_16": [58] * 5}


def _three(t1, p1=P1_DIFFS, p2=P2_DIFFS, fixed=FIXED):
    lineages = {}
    for l in (5, 6, 7):
        collected = {"hg_dagger": [60.0] * 5, "pooled": [60.0 + d for d in p1[l]], **fixed}
        new = {"hg_dagger": [55.0] * 5, "pooled": [55.0 + d for d in p2[l]], "fixed_4": [58.0] * 5}
        lineages[l] = _lineage_files(t1, l, collected, new)
    return lineages


def _write_folder(folder, lineages):
    os.makedirs(folder, exist_ok=True)
    for l, files in lineages.items():
        with gzip.open(os.path.join(folder, f"lineage_{l}.json.gz"), "wt") as fh:
            json.dump({"format": "pcdagger-lineage-results-1", "lineage": l, "files": files}, fh)


# ---- the stated tests -------------------------------------------------------------------------------------------
def test_p1_and_p2_are_one_sided_t_over_lineages_of_each_lineages_mean_over_rounds(t1):
    """P1 (collected) and P2 (new): each lineage's pooled - HG-DAgger averaged over K = 1..5, then a one-sided t over
    the 3 lineages (df 2, not the 15 cells' 14); p = P(T > t), half the two-sided p (a two-sided p, a t over the
    cells or a single round would each give another number)."""
    tests = {r["name"]: r for r in t1.stated_tests(_three(t1))}
    for name, expected in (("P1", [0.6, 1.2, 1.8]), ("P2", [2.0, 2.6, 3.2])):
        r = tests[name]
        assert r["values"] == pytest.approx(expected) and r["df"] == 2 and r["side"] == "> 0"
        se = np.std(expected, ddof=1) / math.sqrt(3)
        assert r["mean"] == pytest.approx(np.mean(expected)) and r["t"] == pytest.approx(np.mean(expected) / se)
        assert r["p"] == pytest.approx(1.0 - dagger.student_t_cdf(r["t"], 2))
        assert r["p"] == pytest.approx(dagger.paired_ttest(expected, [0, 0, 0])[2] / 2)
    assert tests["P1"]["set"] == "collected" and tests["P2"]["set"] == "new"
    assert tests["P1"]["p"] == pytest.approx(0.0371, abs=1e-4) and tests["P1"]["p"] < 0.05 < 2 * tests["P1"]["p"]
    # the stated side: pooled below HG-DAgger gives a p above one half, not a small one
    below = t1.stated_tests(_three(t1, p1={l: [-d for d in v] for l, v in P1_DIFFS.items()}))
    assert below[0]["p"] == pytest.approx(1.0 - tests["P1"]["p"])


def test_p3_is_a_tost_at_2_points_against_the_best_fixed_sigma_over_rounds(t1):
    """P3: the best fixed sigma in hindsight is the fixed row with the highest mean over lineages of its success
    averaged over rounds on the collected set (fixed_8 here: not the best at K = 1, fixed_2, nor at K = 5, fixed_12,
    nor on the new set, fixed_4); pooled - fixed_8 over rounds (-0.4 / +0.2 / +0.8) is tested by TOST at +-2, its p
    the larger one-sided p -- equivalence at +-2 (p 0.018), not at +-1 (p 0.074)."""
    lineages = _three(t1)
    assert t1.hindsight(lineages)[0] == "fixed_8"
    p3 = t1.stated_tests(lineages)[2]
    assert p3["name"] == "P3" and p3["side"] == "within ±2" and "fixed_8" in p3["words"]
    pooled = t1.round_table(lineages, "pooled", "collected").mean(axis=1)
    best = t1.round_table(lineages, "fixed_8", "collected").mean(axis=1)
    assert p3["values"] == pytest.approx([-0.4, 0.2, 0.8]) and t1.MARGIN == 2.0
    assert p3["p"] == pytest.approx(dagger.tost(pooled, best, 2.0)[0]) and p3["p"] == pytest.approx(0.0176, abs=2e-4)
    assert dagger.tost(pooled, best, 1.0)[0] > 0.05  # the margin matters
    # the upper one-sided test binds: 0.2 - 2 is nearer 0 than 0.2 + 2
    assert p3["p"] == pytest.approx(dagger.student_t_cdf((0.2 - 2.0) / (0.6 / math.sqrt(3)), 2))
    # a tie in the mean over rounds goes to the first of 2, 4, 8, 12, 16 (report.paired_statistics' max)
    tie = dict(FIXED, fixed_2=[61] * 5, fixed_16=[61] * 5)
    assert t1.hindsight(_three(t1, fixed=tie))[0] == "fixed_2"


def test_holm_steps_down_from_the_smallest_of_the_three_p(t1, monkeypatch):
    """Holm over P1-P3 at 0.05: the smallest p against 0.05 / 3, the next against 0.05 / 2, the last against 0.05,
    stopping at the first miss. The hand-made lineages give P2 0.0087, P3 0.018, P1 0.037: Holm rejects all three
    (Bonferroni only P2; taken in the listed order none). Then p 0.03 / 0.02 / 0.04: Holm none (0.02 > 0.0167),
    where no correction or Hochberg's step-up would reject all three."""
    res = t1.stated_tests(_three(t1))
    p = [r["p"] for r in res]
    assert p[1] < 0.05 / 3 < p[2] < 0.05 / 2 < p[0] < 0.05
    assert [r["rejected"] for r in res] == [True, True, True]
    assert [r["holm_level"] for r in res] == pytest.approx([0.05, 0.05 / 3, 0.025])

    fake = iter([(1.0, 0.5, 2.0, 2, 0.03), (1.0, 0.5, 2.0, 2, 0.02)])
    monkeypatch.setattr(t1.noise_transfer, "one_sided", lambda values, side: next(fake))
    monkeypatch.setattr(t1.dagger, "tost", lambda a, b, margin: (0.04, 5.0, -5.0))
    res = t1.stated_tests(_three(t1))
    assert [r["p"] for r in res] == [0.03, 0.02, 0.04] and not any(r["rejected"] for r in res)
    assert [r["holm_level"] for r in res] == pytest.approx([0.025, 0.05 / 3, 0.05])


def test_the_verdicts_wait_for_the_stated_lineage_count(t1, monkeypatch):
    """Before N_LINEAGES lineages the tests table gives the numbers and no verdict; at the count, Holm's."""
    lines = t1.tests_table(_three(t1))
    assert all(f"none before {t1.N_LINEAGES} lineages" in line for line in lines[2:5])
    monkeypatch.setattr(t1, "N_LINEAGES", 3)
    lines = t1.tests_table(_three(t1))
    assert [line.split("|")[1].strip() for line in lines[2:5]] == ["P1", "P2", "P3"]
    assert all(line.rstrip(" |").endswith("rejected") and "not" not in line for line in lines[2:5])


def test_the_table_gives_each_round_and_the_mean_over_rounds(t1):
    """Every row at K = 1..5 and over rounds (the mean of the lineages' means over rounds), mean ± SE over lineages,
    a block a set; pi_0 and BC one value for every K."""
    lines = t1.table(_three(t1))
    pooled = next(line for line in lines if line.startswith("| pooled |"))
    cells = [c.strip() for c in pooled.split("|")[2:-1]]
    # K = 1: 63 / 60 / 60, K = 3: 60 / 60 / 66; over rounds 60.6 / 61.2 / 61.8
    assert cells[0] == "61.0 ± 1.0" and cells[2] == "62.0 ± 2.0" and cells[5] == "61.2 ± 0.3"
    assert next(line for line in lines if line.startswith("| bc |")).split("|")[2].strip() == "52.0 ± 0.0"
    assert sum(line.startswith("| pooled |") for line in lines) == 2  # collected, new


def test_the_secondary_results_are_two_sided_by_round_and_set(t1):
    """Each row - HG-DAgger at every round and over rounds on both sets, two-sided; HG-DAgger's K = 5 - K = 1."""
    lines = t1.secondary(_three(t1))
    pooled = [line for line in lines if line.startswith("| pooled |")]
    assert len(pooled) == 2
    over_rounds = pooled[0].split("|")[-2].strip()
    assert over_rounds == f"+1.2 ± 0.3 (p {dagger.paired_ttest([0.6, 1.2, 1.8], [0, 0, 0])[2]:.2g})"
    assert any(line.startswith("| zero_noise |") for line in lines)
    assert any(line.startswith("| per_step |") for line in lines) and any("K = 5 − K = 1" in line for line in lines)


def test_a_lineage_of_another_label_or_pi0_or_missing_a_file_is_left_out(t1):
    """complete(): the old servo's lineage (no return label recorded), another pi_0, or a missing evaluation is
    left out, and the line says why."""
    lineages = _three(t1)
    lineages[8] = _lineage_files(t1, 8, {}, {}, label=None)
    lineages[9] = _lineage_files(t1, 9, {}, {})
    lineages[9]["lineage_9/lineage.json"]["pi0_sha256"] = "0" * 64
    lineages[10] = _lineage_files(t1, 10, {}, {})
    del lineages[10][f"lineage_10/{t1.NEW}/round_3/closed_loop.json"]
    said = []
    assert sorted(t1.complete(lineages, log=said.append)) == [5, 6, 7]
    assert "the PD label (made with 'servo up to 6192871')" in said[0]
    assert "the committed start's pi_0" in said[1] and "round_3/closed_loop.json" in said[2]


def test_a_new_set_evaluated_on_other_seeds_is_refused(t1):
    """Lineage L's new set is relabel_cost.new_seeds(L), 300 seeds of its own; another lineage's is refused."""
    files = _lineage_files(t1, 5, {}, {})
    assert t1.relabel_cost.new_seeds(5) == tuple(range(105_000, 105_300))
    files[f"lineage_5/{t1.NEW}/round_2/pooled.json"]["seeds"] = list(t1.relabel_cost.new_seeds(6))
    with pytest.raises(ValueError, match="not lineage 5's own new scenarios"):
        t1.per_scenario(files, 5, "pooled", 2, "new")


def test_the_command_says_no_lineage_yet_on_an_empty_folder(t1, tmp_path, capsys):
    """No lineage file (an empty folder, a missing one, a folder holding only the design's README, as this study's
    folder does before its first lineage): one line that says so, and a normal exit."""
    (tmp_path / "empty").mkdir()
    (tmp_path / "readme_only").mkdir()
    (tmp_path / "readme_only" / "README.md").write_text("the design\n")
    for folder in (tmp_path / "empty", tmp_path / "absent", tmp_path / "readme_only"):
        assert t1.main(["--results", str(folder)]) is None
        out = capsys.readouterr().out
        assert out.startswith(f"{folder}: no lineage file yet") and "the study has not run" in out


def test_the_command_prints_the_table_the_tests_and_draws_the_figure(t1, tmp_path, capsys):
    folder = tmp_path / "results"
    _write_folder(folder, _three(t1))
    t1.main(["--results", str(folder), "--figure", str(tmp_path / "fig.png")])
    out = capsys.readouterr().out
    assert "3 complete lineage(s) [5, 6, 7] of the stated 11" in out
    assert "| P1 | collected | pooled − HG-DAgger, over rounds | > 0 | +1.20 |" in out
    assert "(an interim look at 3 lineages" in out and "secondary (two-sided, uncorrected)" in out
    assert os.path.getsize(tmp_path / "fig.png") > 10_000


# ---- the design -------------------------------------------------------------------------------------------------
def test_tost_power_with_and_without_the_selection(t1):
    """P3's power: the level's size at a true difference on the margin, near 1 with many lineages and no
    difference, lower when the reference is the best of five chosen from the same draws than when it is named."""
    assert t1.tost_power(2.0, 1.0, 8, 0.05, selection=False, draws=20_000) <= 0.06
    assert t1.tost_power(0.0, 1.0, 40, 0.05, draws=20_000) > 0.99
    assert t1.tost_power(0.0, 1.0, 8, 0.05, draws=20_000) < t1.tost_power(0.0, 1.0, 8, 0.05, selection=False,
                                                                           draws=20_000)
    # the selection's bias: minus the mean of the largest of five N(0, SD^2 / n), halved at 4 n
    bias = t1.selection_bias(1.0, 4)
    assert bias == pytest.approx(-1.163 / 2, abs=0.01) and t1.selection_bias(1.0, 16) == pytest.approx(bias / 2,
                                                                                                       abs=0.01)


@pytest.fixture(scope="module")
def design_output(t1):
    import contextlib
    import io
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        t1.main(["--design"])
    return out.getvalue()


def test_design_prints_the_power_and_still_chooses_the_stated_count(t1, design_output):
    """--design: the pilots' SDs, the power of P1-P3 at 5..16 lineages (P1, P2 at +2.8 and +1.5, at Holm's first step
    and at 0.05; P3 with and without the selection), the sensitivity, the count and the cost. A changed pilot,
    effect, level or rule would choose another count than the stated N_LINEAGES, which the design README quotes
    with every line of this output."""
    lines = design_output.splitlines()
    assert f"lineages: {t1.N_LINEAGES} (the smallest n >= 5 with power >= 0.8 at 0.0167" in design_output
    assert t1.N_LINEAGES == 11 and "lineages 5..15" in design_output
    header = next(i for i, line in enumerate(lines) if line.startswith("   n  P1 +2.8"))
    table = [line.split() for line in lines[header + 1:header + 13]]
    assert [int(r[0]) for r in table] == list(range(5, 17))
    powers = np.array([[float(x) for x in r[1:]] for r in table])   # (n, 10)
    assert ((0 <= powers) & (powers <= 1)).all()
    assert (np.diff(powers[:, 2]) >= 0).all() and powers[:, 3].min() >= powers[:, 2].min()  # P1 +1.5: n, level
    chosen = [r for r in table if int(r[0]) == t1.N_LINEAGES][0]
    assert float(chosen[3]) >= 0.8 and float(chosen[6]) >= 0.8 and float(chosen[8]) >= 0.8
    before = [r for r in table if int(r[0]) == t1.N_LINEAGES - 1][0]
    assert min(float(before[3]), float(before[6]), float(before[8])) < 0.8
    assert "core-h a lineage" in design_output and "105000..105299" in design_output
    readme = open(os.path.join(t1.RESULTS, "README.md")).read()
    for line in lines:
        assert line in readme, line


def test_the_committed_start_is_the_pi0_the_study_names(t1):
    from experiment import run_folder
    assert run_folder.weights_sha256(os.path.join(START, "checkpoints", "bc.pt")) == t1.START_PI0


def test_a_study_lineages_cost_counts_its_cells_and_the_new_set(t1):
    """50 cells (ten rows x five rounds), two evaluations each, and 52 policies on the new set at 3 x an
    evaluation."""
    run, new = t1.study_lineage_seconds(train=100.0, evaluation=10.0, fixed=300.0)
    assert run == 300 + 50 * (100 + 20) and new == 52 * 3 * 10


# ---- the study's evaluation and its policies ----------------------------------------------------------------------
def _study_folder(t1, root, lineages=21):
    config = json.load(open(os.path.join(START, "config.json")))
    config.update(methods=["bc", *t1.ROWS], name="table1_" + "-".join(t1.ROWS), lineages=lineages)
    os.makedirs(root / "checkpoints")
    json.dump(config, open(root / "config.json", "w"))
    for rel in t1.study_policies(5).values():
        os.makedirs(os.path.dirname(root / rel), exist_ok=True)
        os.symlink(os.path.join(START, "checkpoints", "bc_continued.pt"), root / rel)
    return config


def test_evaluate_lineage_writes_every_policy_on_its_lineages_own_seeds_and_resumes(t1, tmp_path, monkeypatch):
    """--evaluate: pi_0, BC and the ten rows at K = 1..5 (52 files) on the lineage's own 300 new seeds, one sampling
    seed for all of them (stage_seed(cfg, 'eval_new', L)); a second call keeps every file. A folder of another
    config, a lineage outside the study or a missing policy is refused before anything is written."""
    root = tmp_path / "run"
    config = _study_folder(t1, root)
    calls = []

    def fake(path, seeds, repeats, sample_seed, env):
        calls.append((path, tuple(seeds), sample_seed))
        return np.ones((len(seeds), repeats), bool)
    monkeypatch.setattr(t1.relabel_cost, "evaluate_file", fake)  # the studies' shared write_new_evaluations
    t1.evaluate_lineage(str(root), 5, log=lambda m: None)
    new = root / "lineage_5" / t1.NEW
    written = sorted(os.path.relpath(os.path.join(d, f), new) for d, _, fs in os.walk(new) for f in fs)
    assert len(written) == 52 and "pi0.json" in written and "round_5/zero_noise.json" in written
    got = json.load(open(new / "round_3" / "pooled.json"))
    cfg = SimpleNamespace(seed=config["seed"])
    assert got["seeds"] == list(range(105_000, 105_300)) and got["policy"] == "lineage_5/round_3/checkpoints/pooled.pt"
    assert {c[2] for c in calls} == {got["sample_seed"]} == {dagger.stage_seed(cfg, "eval_new", 5)}
    t1.evaluate_lineage(str(root), 5, log=lambda m: None)
    assert len(calls) == 52  # resumed: nothing evaluated again
    with pytest.raises(SystemExit, match=r"--lineage 4: the study's lineages are 5\.\.20"):
        t1.evaluate_lineage(str(root), 4, log=lambda m: None)
    os.remove(root / "lineage_5" / "round_4" / "checkpoints" / "per_step.pt")
    with pytest.raises(SystemExit, match="1 policies missing"):
        t1.evaluate_lineage(str(root), 5, log=lambda m: None)
    config["methods"] = ["bc", "hg_dagger", "pooled"]
    json.dump(config, open(root / "config.json", "w"))
    with pytest.raises(SystemExit, match="not the study's run folder"):
        t1.evaluate_lineage(str(root), 5, log=lambda m: None)
    config.update(methods=["bc", *t1.ROWS], bc_steps=30_000)
    json.dump(config, open(root / "config.json", "w"))
    with pytest.raises(SystemExit, match="bc_steps differ"):
        t1.evaluate_lineage(str(root), 5, log=lambda m: None)


def test_export_policies_copies_the_six_picked_for_sampling_only(t1, tmp_path):
    """HG-DAgger, pooled and fixed_4 at K = 1 and 5 (six files, ~38 MB), byte for byte; a policy holding its
    training state is refused before anything is written."""
    root = tmp_path / "run"
    _study_folder(t1, root)
    t1.export_policies(str(root), 5, str(tmp_path / "policies"))
    out = tmp_path / "policies" / "lineage_5"
    got = sorted(os.path.relpath(os.path.join(d, f), out) for d, _, fs in os.walk(out) for f in fs)
    assert got == sorted(f"round_{k}/{row}.pt" for k in (1, 5) for row in ("hg_dagger", "pooled", "fixed_4"))
    os.remove(root / "lineage_5" / "round_5" / "checkpoints" / "pooled.pt")
    os.symlink(os.path.join(START, "checkpoints", "bc.pt"), root / "lineage_5" / "round_5" / "checkpoints" /
               "pooled.pt")
    with pytest.raises(SystemExit, match="pooled.pt holds a training state"):
        t1.export_policies(str(root), 5, str(tmp_path / "again"))
    assert not (tmp_path / "again").exists()


# ---- why HG-DAgger levels off: the collection table ---------------------------------------------------------------
H = 4


def _episode(T, runs, success=True, seed=0):
    expert = np.zeros(T, bool)
    for start, end in runs:
        expert[start:end] = True
    return {"obs": np.zeros((T, 2), np.float32), "q": np.zeros((T, 2)), "action": np.zeros((T, 2)),
            "expert": expert, "seed": seed, "success": success, "interventions": len(runs) + 1}


def _calibration(episodes):
    """episode_index and timestep as calibrate.open_loop_sigma anchors them (a policy that samples zeros)."""
    policy = SimpleNamespace(cfg=SimpleNamespace(horizon=H, n_act=H),
                             sample=lambda obs, generator=None: np.zeros((len(obs), H, 2)))
    steps = calibrate.open_loop_sigma(policy, episodes, stride=2, n_samples=1)
    return {"episode_index": steps.episode_index.tolist(), "timestep": steps.timestep.tolist()}


D1 = [_episode(30, [(5, 12), (20, 30)]), _episode(25, [(10, 16)], success=False), _episode(9, [(0, 9)])]
D2 = [_episode(25, [(3, 9), (15, 21)]), _episode(40, [(2, 30)])]


def _collection_files(t1):
    """One lineage's files for rounds 1 and 2: pi_0 fails 3 of 3 on scenarios 0-59, and once on 60-69; HG-DAgger K = 1
    fails on 0-29 and once on 70-74; D_1, D_2 calibrated as the run calibrates them (D_1, then D_1 + D_2)."""
    def table(rows):  # {scenario: successes of 3}
        return [[i < rows.get(s, 3) for i in range(3)] for s in range(100)]
    files = _lineage_files(t1, 5, {"hg_dagger": [50.0] * 5}, {})
    files["eval/pi0.json"]["success"] = table({**{s: 0 for s in range(60)}, **{s: 2 for s in range(60, 70)}})
    files["lineage_5/lineage.json"]["config"]["horizon"] = H
    files["lineage_5/round_1/eval/hg_dagger.json"]["success"] = table({**{s: 0 for s in range(30)},
                                                                       **{s: 1 for s in range(70, 75)}})
    files["lineage_5/round_1/calibration.json"] = _calibration(D1)
    files["lineage_5/round_2/calibration.json"] = _calibration(D1 + D2)
    for k in (3, 4, 5):
        del files[f"lineage_5/round_{k}/eval/hg_dagger.json"]
    return files


def test_the_calibration_gives_each_rounds_kept_episodes_segments_and_chunk_starts(t1):
    """From round k's calibration.json alone: D_k's episodes and expert segments exactly, its labelled chunk starts
    within [2 A - S, 2 A] (A anchors, S segments), as the episodes themselves count them (diffusion's label rule)."""
    files = _collection_files(t1)
    for k, episodes in ((1, D1), (2, D2)):
        kept, segments, anchors = t1.anchors_in_round(files, 5, k)
        assert kept == len(episodes)
        assert segments == sum(len(diffusion.expert_runs(e["expert"], H)) for e in episodes)
        chunks = sum(int(diffusion.label_mask(e["expert"], H).sum()) for e in episodes)
        assert 2 * anchors - segments <= chunks <= 2 * anchors
    assert t1.anchors_in_round(files, 5, 3) is None


def test_the_collection_rows_split_each_round_at_the_collectors_own_evaluation(t1):
    """Round 1 collects on pi_0's 70 scenarios not solved 3 of 3, round 2 on HG-DAgger K = 1's 35 (30 of them
    collected on before); each round's HG-DAgger and BC on those scenarios and on the others."""
    files = _collection_files(t1)
    rows = t1.collection_rows({5: files})
    assert [(k, l) for k, l, _ in rows] == [(1, 5), (2, 5)]
    first, second = rows[0][2], rows[1][2]
    assert first["collected_on"] == 70 and first["before"] is None and second["collected_on"] == 35
    assert second["before"] == 30  # 0-29 were pi_0's too; 70-74 it solved 3 of 3
    hg1 = 100.0 * np.asarray(files["lineage_5/round_1/eval/hg_dagger.json"]["success"], float).mean(axis=1)
    assert first["hg_there"] == pytest.approx(hg1[:70].mean()) and first["hg_others"] == pytest.approx(hg1[70:].mean())
    assert first["collector_there"] == pytest.approx(100.0 * 20 / 210)  # 60 x 0 + 10 x 2 successes of 210
    bc = 100.0 * np.asarray(files["eval/bc.json"]["success"], float).mean(axis=1)
    assert second["bc_there"] == pytest.approx(np.r_[bc[:30], bc[70:75]].mean())
    assert first["episodes"] == 3 and second["segments"] == 3


def test_the_collection_table_adds_the_episodes_columns_from_a_run_folder(t1, tmp_path):
    """From a run folder the table reads the same JSON as the lineage file holds and D.npz's exact columns."""
    from experiment import run_folder
    files = _collection_files(t1)
    root = tmp_path / "run"
    for rel, content in files.items():
        os.makedirs(os.path.dirname(root / rel), exist_ok=True)
        json.dump(content, open(root / rel, "w"))
    json.dump({"methods": ["bc", *t1.ROWS]}, open(root / "config.json", "w"))
    for k, episodes in ((1, D1), (2, D2)):
        run_folder.save_episodes(str(root / "lineage_5" / f"round_{k}" / "D.npz"), episodes)
    lines = t1.collection_table(str(root))
    assert "expert frames" in lines[0] and "takeovers" in lines[0]
    first = [c.strip() for c in lines[2].split("|")[1:-1]]
    frames = sum(int(e["expert"].sum()) for e in D1)
    chunks = sum(int(diffusion.label_mask(e["expert"], H).sum()) for e in D1)
    # pi_0: 10 x 2 + 30 x 3 successes of 300 on the 100, 20 of 210 on the 70 it collected on
    assert first[:9] == ["1", "5", "π0", "36.7", "70", f"{100 * 20 / 210:.1f}", "3", "4", str(chunks)]
    assert first[9:12] == ["7", str(frames), f"{100 * 2 / 3:.1f}"]


def test_the_collection_table_of_lineage_files_gives_the_chunk_starts_as_a_range(t1, tmp_path):
    """Without D.npz (the committed lineage files) the chunk starts are the calibration's bounds, and the table
    ends with the mean over lineages of each round."""
    _write_folder(tmp_path / "files", {5: _collection_files(t1)})
    lines = t1.collection_table(str(tmp_path / "files"))
    assert "expert frames" not in lines[0]
    anchors, segments = t1.anchors_in_round(_collection_files(t1), 5, 1)[2], 4
    assert lines[2].split("|")[9].strip() == f"{2 * anchors - segments}–{2 * anchors}"
    assert lines[-2].split("|")[2].strip() == "mean of 1" and len(lines) == 2 + 2 + 3 + 2 + 2
