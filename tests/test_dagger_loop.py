"""dagger.py end to end on a tiny config: every output file, resume after an interruption, CLI errors."""
import csv
import dataclasses
import json
import os
import signal
import sys
import time
from dataclasses import replace

import matplotlib.image
import numpy as np
import pytest
import torch

import dagger
import diffusion
import envs
from helpers import straight_line_episode  # tests/helpers.py
import relabel
from experiment import cli, controls, environments, profiles, report, run_folder

TINY = dagger.Config(name="tiny", n_demos=4, rounds=1, lineages=1, K=5, down_dims=(8, 16),
                     bc_steps=30, finetune_steps=12, batch_size=32,
                     methods=("bc", "hg_dagger", "fixed_4", "pooled", "per_step", "closed_loop"),
                     eval_scenarios=3, eval_repeats=1)

OUTPUTS = ["config.json", "log.txt", "results.json", "results.csv", "table.md", "data/D0.npz",
           "checkpoints/bc.pt", "eval/bc.json", "lineage_0/round_1/D.npz",
           "lineage_0/round_1/calibration.json",
           *[f"lineage_0/round_1/checkpoints/{m}.pt" for m in TINY.methods if m != "bc"],
           *[f"lineage_0/round_1/eval/{m}.json" for m in TINY.methods if m != "bc"],
           *[f"figures/{f}.png" for f in ("fig1_recovery", "fig2_method_overview", "fig3_partial_denoising",
                                          "fig4_blend_fit", "fig5_environment", "success_vs_round")]]


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    root = str(tmp_path_factory.mktemp("full"))
    report.run_experiment(TINY, root)
    return root


@pytest.mark.slow
def test_every_output_file(full_run):
    """Every output file is there and holds what it should: the config, D0, pi_0 with its optimizer state, the
    evaluations on the right scenarios, interventions >= H, a usable calibration, results that agree with the
    evaluation files, table.md's cells, CSV rows, figures that are images, a report that shows them."""
    missing = [f for f in OUTPUTS if not os.path.isfile(os.path.join(full_run, f))]
    assert not missing
    at = lambda name: os.path.join(full_run, name)  # noqa: E731
    saved = json.load(open(at("config.json")))
    assert {k: tuple(v) if isinstance(v, list) else v for k, v in saved.items()} == dataclasses.asdict(TINY)
    demos = run_folder.load_episodes(at("data/D0.npz"))
    assert len(demos) == TINY.n_demos and all(ep["expert"].all() and len(ep["obs"]) == len(ep["q"]) for ep in demos)
    pi0 = torch.load(at("checkpoints/bc.pt"), weights_only=True)
    assert pi0["train_state"]["step"] == TINY.bc_steps  # 'continue': the arms go on from pi_0's optimizer
    eval_seeds = envs.eval_seeds()[:TINY.eval_scenarios]
    success = {}
    for method in TINY.methods:
        name = "eval/bc.json" if method == "bc" else f"lineage_0/round_1/eval/{method}.json"
        e = json.load(open(at(name)))
        assert e["seeds"] == eval_seeds and np.shape(e["success"]) == (TINY.eval_scenarios, TINY.eval_repeats)
        success[method] = 100.0 * np.mean(e["success"])
    results = json.load(open(at("results.json")))
    assert results["success"]["bc"]["all"] == [pytest.approx(success["bc"])]
    assert {m: rows["0"] for m, rows in results["success"].items() if m != "bc"} == \
        {m: [pytest.approx(v)] for m, v in success.items() if m != "bc"}
    for ep in run_folder.load_episodes(at("lineage_0/round_1/D.npz")):  # every kept episode teaches: a run >= H
        assert any(end - start >= TINY.horizon for start, end in diffusion.expert_runs(ep["expert"], 1))
    cal = run_folder.calibration_from_json(json.load(open(at("lineage_0/round_1/calibration.json"))))
    assert cal.W > 0 and np.allclose(cal.pooled, cal.pooled.T) and np.all(np.linalg.eigvalsh(cal.pooled) >= 0)
    table = open(at("table.md")).read()
    for method in TINY.methods:
        cell = f"{success[method]:.1f} (1)" + (", all K" if method == "bc" else "")
        assert f"| {report.method_label(method)} | {cell} |" in table
    rows = list(csv.DictReader(open(at("results.csv"))))
    assert {r["method"]: float(r["success_pct"]) for r in rows} == pytest.approx(success)
    report_md = open(at("report.md")).read()
    for name in [f for f in OUTPUTS if f.startswith("figures/")] + ["figures/table_i.png"]:
        image = matplotlib.image.imread(at(name))
        assert image.ndim == 3 and min(image.shape[:2]) > 100 and image.std() > 0  # a drawing, not a blank
        assert f"![{os.path.basename(name)}]({name})" in report_md
    assert "done in" in open(at("log.txt")).read()


@pytest.mark.slow
def test_interrupted_run_resumes_to_the_same_results(full_run, tmp_path, monkeypatch):
    root = str(tmp_path / "interrupted")
    real = dagger.fine_tune

    def crash_on_pooled(cfg, lineage, k, method, *args, **kwargs):
        if method == "pooled":
            raise KeyboardInterrupt("stopped by the test")
        return real(cfg, lineage, k, method, *args, **kwargs)

    monkeypatch.setattr(dagger, "fine_tune", crash_on_pooled)
    with pytest.raises(KeyboardInterrupt):
        report.run_experiment(TINY, root)
    # what finished before the stop is on disk, what did not is not
    assert os.path.isfile(os.path.join(root, "lineage_0/round_1/eval/fixed_4.json"))
    assert not os.path.exists(os.path.join(root, "lineage_0/round_1/eval/pooled.json"))
    monkeypatch.setattr(dagger, "fine_tune", real)
    report.run_experiment(TINY, root)
    a = json.load(open(os.path.join(full_run, "results.json")))["success"]
    b = json.load(open(os.path.join(root, "results.json")))["success"]
    assert a == b
    # identical data, too
    ca = json.load(open(os.path.join(full_run, "lineage_0/round_1/calibration.json")))
    cb = json.load(open(os.path.join(root, "lineage_0/round_1/calibration.json")))
    assert np.allclose(ca["pooled"], cb["pooled"])


@pytest.mark.slow
def test_run_folder_refuses_a_different_config(full_run):
    with pytest.raises(ValueError, match="made with another config"):
        run_folder.Run(full_run, replace(TINY, bc_steps=31))


@pytest.mark.parametrize("argv,message", [
    (["--profile", "huge"], "invalid choice"),
    (["--env", "mars"], "invalid choice"),
    (["--methods", "bc,magic"], "unknown method(s) ['magic']; valid: bc, hg_dagger"),
    (["--profile", "quick", "--lineage", "3"], "valid lineages are 0..0"),
    (["--rounds", "0"], "rounds must be >= 1"),
    (["--device", "tpu"], "use cpu or cuda"),
    (["--image-obs"], "unrecognized arguments"),
])
def test_bad_cli_arguments(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.parse_args(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_config_rejects_unknown_method():
    """Fails if a config naming no method this code runs reaches the run (the check where a config enters)."""
    with pytest.raises(ValueError, match="unknown method"):
        profiles.check_config(dagger.Config(methods=("bc", "dart")))
    with pytest.raises(ValueError, match="unknown method"):
        report.run_experiment(dagger.Config(methods=("bc", "dart")), "/nonexistent/never-made")


def test_a_negative_seed_is_refused_before_the_run_folder_is_made(tmp_path, capsys):
    """Bug: --seed -1 passed the command line, wrote config.json, log.txt and data/ and only then died in numpy's
    SeedSequence with a traceback. Now the config's check refuses it (run_experiment too), naming the value and the
    valid range, and the command exits 2 before anything is written."""
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["--profile", "smoke", "--seed", "-1", "--out", str(out)])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "Traceback" not in err
    assert "seed must be an integer >= 0" in err and "got -1" in err
    assert not out.exists() or not any(out.iterdir())
    with pytest.raises(ValueError, match=r"seed must be an integer >= 0 .*got -1"):
        report.run_experiment(replace(TINY, seed=-1), str(out))
    assert not out.exists() or not any(out.iterdir())


def test_summarize_paired_statistics():
    cfg = replace(TINY, rounds=2, lineages=3, methods=("bc", "hg_dagger", "fixed_2", "fixed_8", "pooled"))
    results = {"bc": {"all": [60.0]},
               "hg_dagger": {"0": [70, 72], "1": [71, 73], "2": [69, 74]},
               "fixed_2": {"0": [73, 75], "1": [74, 76], "2": [72, 77]},
               "fixed_8": {"0": [71, 72], "1": [70, 73], "2": [70, 74]},
               "pooled": {"0": [73, 76], "1": [74, 75], "2": [73, 77]}}
    table, stats = report.summarize(cfg, results)
    assert table["hg_dagger"][0][0] == pytest.approx(70.0) and table["hg_dagger"][0][2] == 3
    assert stats["best_fixed"] == "fixed_2"
    assert stats["paired_vs_hg_dagger"]["pooled"]["diff"] == pytest.approx(
        np.mean([74.5 - 71, 74.5 - 72, 75 - 71.5]))
    assert stats["paired_vs_hg_dagger"]["pooled"]["df"] == 2
    assert stats["tost_vs_best_fixed"]["pooled"]["vs"] == "fixed_2"
    text = report.format_table(cfg, table, stats)
    assert "| HG-DAgger | 70.0 ± 0.6 (3) | 73.0 ± 0.6 (3) |" in text
    # per round: K=1 pairs each lineage's first cells only (pooled 73, 74, 73 vs 70, 71, 69), and the round's
    # best fixed sigma (fixed_2 at K=1: 73.0 vs fixed_8 70.3); K=2 its second cells
    k1, k2 = stats["per_round"]["1"], stats["per_round"]["2"]
    assert k1["paired_vs_hg_dagger"]["pooled"]["diff"] == pytest.approx(np.mean([73 - 70, 74 - 71, 73 - 69]))
    assert k2["paired_vs_hg_dagger"]["pooled"]["diff"] == pytest.approx(np.mean([76 - 72, 75 - 73, 77 - 74]))
    assert k1["best_fixed"] == "fixed_2" and k1["tost_vs_best_fixed"]["pooled"]["diff"] == pytest.approx(
        np.mean([73 - 73, 74 - 74, 73 - 72]))
    t, df, p = dagger.paired_ttest([73, 74, 73], [70, 71, 69])
    assert k1["paired_vs_hg_dagger"]["pooled"]["p"] == pytest.approx(p) and df == 2
    assert "Per round (paired over the lineages that finished it)" in text and "- K=2: " in text
    # a lineage that finished round 1 only counts in round 1's pairs, not in the average over rounds
    partial = {m: {**rows, "3": rows["0"][:1]} for m, rows in results.items() if m != "bc"} | {"bc": results["bc"]}
    _, partial_stats = report.summarize(cfg, partial)
    assert partial_stats["per_round"]["1"]["paired_vs_hg_dagger"]["pooled"]["df"] == 3
    assert partial_stats["per_round"]["2"]["paired_vs_hg_dagger"]["pooled"]["df"] == 2
    assert partial_stats["paired_vs_hg_dagger"]["pooled"]["df"] == 2
    # the sigma = 0 control is paired with HG-DAgger but never the "best fixed noise"
    cfg = replace(cfg, methods=cfg.methods + ("zero_noise",))
    results["zero_noise"] = {"0": [90, 90], "1": [91, 91], "2": [92, 92]}
    _, stats = report.summarize(cfg, results)
    assert stats["best_fixed"] == "fixed_2" and "zero_noise" in stats["paired_vs_hg_dagger"]
    assert "zero_noise" not in stats["tost_vs_best_fixed"]


def test_zero_noise_control_is_the_pipeline_without_noise():
    """Fails if zero_noise's rows are not the noised pipeline at sigma = 0, or the core knows the control's name."""
    D = [straight_line_episode(envs.make_env("planar"), seed, expert_from=2) for seed in (1, 2)]
    stats = relabel.demo_stats(D, envs.median_step(D), 0.05)
    (zero,) = controls.Rows()(replace(TINY, methods=("bc", "hg_dagger", "zero_noise")), "zero_noise", [D], None,
                              stats, envs.make_env).samplers
    assert isinstance(zero, relabel.AugmentationSampler) and zero.noise == "isotropic"
    assert np.all(np.asarray(zero.factors) == 0)  # every state relabelled where it was recorded: no noise
    with pytest.raises(ValueError, match="no noise model for method 'zero_noise'"):
        dagger.noise_model("zero_noise", None)
    assert dagger.noise_model("fixed_8", None) == ("isotropic", 8.0)  # no units given: our median steps
    assert "zero_noise" not in dagger.Config().methods  # the paper profile runs Table I's rows only
    assert "zero_noise" in profiles.ALL_METHODS  # experiment/controls.py's row, selectable with --methods


def test_table2_profile_is_the_engine_lever_env_with_table_ii_rows(load_benchmark):
    _, cfg = cli.parse_args(["--profile", "table2"])
    assert cfg.env == "engine3d" and cfg.name == "table2"  # the profile's own env adds no suffix
    assert {"bc", "hg_dagger", "pooled"} <= set(cfg.methods) and (cfg.rounds, cfg.lineages) == (2, 3)  # Table II
    assert {"fixed_4", "fixed_8"} <= set(cfg.methods)  # 8: the authors' calibrated size in radians, beside 4
    # the epsilon network chosen by benchmarks/lever_networks.py (unet16_b256), continued as the planar recipe
    chosen = load_benchmark("lever_networks").CANDIDATES["unet16_b256"]
    assert {k: getattr(cfg, k) for k in chosen} == chosen
    _, cfg = cli.parse_args(["--profile", "table2", "--env", "planar"])
    assert cfg.env == "planar" and cfg.name == "table2_planar"  # never the engine3d run's folder
    _, cfg = cli.parse_args(["--profile", "mid", "--env", "engine3d"])
    assert cfg.name == "mid_engine3d"


def test_the_default_worker_count_is_the_cores_this_process_may_use(monkeypatch):
    """On a machine with more cores the default run uses them (a round's arms side by side), as many as
    taskset or a cgroup lets this process use, not the machine's count; one with --lineage (lineages side by side
    are the user's own processes); an explicit --workers wins."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3, 4, 5}, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    assert cli.parse_args([])[0].workers == 6
    assert cli.parse_args(["--lineage", "0"])[0].workers == 1
    assert cli.parse_args(["--workers", "3"])[0].workers == 3
    monkeypatch.delattr(os, "sched_getaffinity")                    # macOS, Windows: the machine's count
    assert cli.parse_args([])[0].workers == 64


@pytest.mark.slow
def test_run_folder_accepts_fields_added_later_at_their_default(full_run, tmp_path):
    old = json.load(open(os.path.join(full_run, "config.json")))
    del old["mlp_width"], old["mlp_blocks"]  # a run folder written before these fields existed
    root = tmp_path / "older"
    root.mkdir()
    json.dump(old, open(root / "config.json", "w"))
    run_folder.Run(str(root), TINY)  # no error: the new fields have their defaults
    with pytest.raises(ValueError, match="mlp_width"):
        run_folder.Run(str(root), replace(TINY, mlp_width=128))


@pytest.mark.slow
def test_a_retired_field_is_dropped_at_the_value_that_remains_and_another_value_is_refused(full_run, tmp_path):
    """A config stored before an option was deleted (run_folder.RETIRED_FIELDS: config.json, a lineage record, a
    --join file, a --copy-from folder all compare through check_same_config) still matches where the field holds
    the behaviour that remains; another value ran deleted code and is refused, naming the field."""
    assert run_folder.RETIRED_FIELDS
    stored = json.load(open(os.path.join(full_run, "config.json")))
    for field, allowed in run_folder.RETIRED_FIELDS.items():
        for value in ((17, "anything") if allowed is run_folder.ANY_VALUE else allowed):
            run_folder.check_same_config("older", {**stored, field: value}, TINY)
        if allowed is not run_folder.ANY_VALUE:
            with pytest.raises(run_folder.ConfigMismatch, match=rf"older was made with {field} = 'gone'"):
                run_folder.check_same_config("older", {**stored, field: "gone"}, TINY)
    root = tmp_path / "older"
    root.mkdir()
    field, allowed = next((f, a) for f, a in run_folder.RETIRED_FIELDS.items() if a is not run_folder.ANY_VALUE)
    json.dump({**stored, field: allowed[0]}, open(root / "config.json", "w"))
    run_folder.Run(str(root), TINY)  # an old folder's config.json loads as before
    json.dump({**stored, field: "gone"}, open(root / "config.json", "w"))
    with pytest.raises(run_folder.ConfigMismatch, match=field):
        run_folder.Run(str(root), TINY)


# benchmarks/results/<folder>: the options of the command that reports it (benchmarks/README.md)
COMMITTED_RESULTS = {
    "mid": ["--profile", "mid"], "table1": ["--profile", "table1"], "table2": ["--profile", "table2"],
    "table1_strong": ["--profile", "table1_strong"],
    "table2_authors_finetune": ["--profile", "table2", "--recipe", "authors_lever"],
    "table2_authors_finetune_seeds": ["--profile", "table2", "--recipe", "authors_lever_seeds",
                                      "--methods", "hg_dagger,pooled"],
    "noise_transfer": ["--profile", "table1_strong", "--methods", "hg_dagger,zero_noise,fixed_4,fixed_8,fixed_16,pooled",
                       "--lineages", "13"],
}
# relabel_cost's lineages (rows zero_noise ... made with the old servo, zero_noise_pd ... with the PD) name rows that
# are gone since the PD became every row's label: its table is `python benchmarks/relabel_cost.py`, from the files
# (tests/test_relabel_cost.py); they joined a folder with the command of its README at 6192871.


def test_every_committed_lineage_file_says_the_return_label_it_was_made_with():
    """Every committed results file was made before the label was recorded: each reads as the old servo's
    (run_folder.label_of), and a report of its join says so -- none passes for the PD's."""
    where = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks", "results")
    labels = {}
    for folder in sorted(os.listdir(where)):
        for name in sorted(os.listdir(os.path.join(where, folder))):
            if name.endswith(".json.gz"):
                data = run_folder.load_stage_file(os.path.join(where, folder, name), run_folder._read_lineage_file)
                labels[f"{folder}/{name}"] = run_folder.label_of(data)
    assert len(labels) > 30 and set(labels.values()) == {run_folder.OLD_SERVO}
    assert "half the authors'" in run_folder.LABEL_WORDS[run_folder.OLD_SERVO]


@pytest.mark.parametrize("folder", sorted(COMMITTED_RESULTS))
def test_every_committed_results_file_matches_the_config_of_the_command_that_reports_it(folder):
    """--join compares each file's stored config with the command's (a deleted option's field dropped at the
    value that remains): a change to a profile or an option must leave the committed results joinable."""
    _, cfg = cli.parse_args(COMMITTED_RESULTS[folder])
    where = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks", "results", folder)
    paths = sorted(p for p in os.listdir(where) if p.endswith(".json.gz"))
    assert paths
    for name in paths:
        data = run_folder.load_stage_file(os.path.join(where, name), run_folder._read_lineage_file)
        run_folder.check_same_config(name, data["config"], cfg)
    start = os.path.join(where, "start")
    if os.path.isdir(start):  # a committed start is the shared stages of the same config and pi_0 as the lineages
        run_folder.check_same_config(start, run_folder.read_json(os.path.join(start, "config.json")), cfg)
        pi0 = run_folder.weights_sha256(os.path.join(start, "checkpoints", "bc.pt"))
        assert all(run_folder.load_stage_file(os.path.join(where, name), run_folder._read_lineage_file)["pi0_sha256"]
                   == pi0 for name in paths)



def test_evaluate_runs_groups_of_at_most_max_parallel_in_scenario_order(monkeypatch):
    """Each group is one lockstep rollout; results land in (scenario, repeat) order whatever the grouping."""
    groups = []

    def fake_rollout(env_list, policy, n_act, generator, oracle=None, log=None):
        groups.append(len(env_list))
        return [{"success": e.seed % 3 == 0} for e in env_list]

    monkeypatch.setattr(dagger, "rollout", fake_rollout)
    policy = type("NoPolicy", (), {"device": "cpu"})()
    seeds = list(range(10_000, 10_007))
    expected = np.array([[s % 3 == 0] * 2 for s in seeds])
    for max_parallel, sizes in ((None, [14]), (4, [4, 4, 4, 2]), (7, [7, 7])):
        groups.clear()
        ok = dagger.evaluate(policy, "planar", seeds, 2, 8, 0, max_parallel=max_parallel)
        assert groups == sizes and np.array_equal(ok, expected)
    monkeypatch.setattr(envs.PlanarReacher, "max_parallel", 3)  # the env's own bound, read from the first env
    groups.clear()
    assert np.array_equal(dagger.evaluate(policy, "planar", seeds, 2, 8, 0), expected) and groups == [3, 3, 3, 3, 2]


class DriftPolicy:
    """A stand-in policy: every chunk drifts slowly in one fixed joint direction (it never reaches the goal)."""
    device = "cpu"

    def __init__(self, dof, H=20, speed=0.01):
        self.dof, self.H, self.speed = dof, H, speed

    def sample(self, obs, generator=None):
        q = np.asarray(obs)[:, :self.dof].astype(np.float64)
        steps = np.arange(1, self.H + 1)[None, :, None] * self.speed
        return q[:, None, :] + steps * np.array([1.0, -0.5, 0.5])[None, None, :self.dof]


def test_hg_dagger_rollout_rewinds_hands_back_and_keeps_a_consistent_record():
    """The authors' gate in the loop: stall/time triggers rewind (the dropped policy steps leave no gap in the
    record: every recorded step is the env's step rule applied to the previous one), the expert drives 20-67
    steps (or its whole plan), at most max_interventions per episode."""
    import envs
    import oracle as oracle_mod
    oracle = oracle_mod.Oracle(oracle_mod.OracleConfig(n_attempts=1, stall_window=20))
    env_list = []
    # the 4 of 20 scenes whose goal lies farthest from the start in joint space: every plan is longer than the
    # hand-back range (where the goal is a few steps away the oracle's whole plan is a shorter intervention)
    def steps_to_goal(seed):
        e = envs.make_env("planar")
        e.reset(seed=int(seed))
        return np.abs(e.goal_configurations() - e.q).max(axis=1).min() / e.max_step

    for s in sorted(envs.make_env("planar").eval_seeds()[:20], key=steps_to_goal)[-4:]:
        e = envs.make_env("planar")
        e.reset(seed=int(s))
        env_list.append(e)
    episodes = dagger.rollout(env_list, DriftPolicy(3), 10, None, oracle=oracle, seed=0)
    probe = envs.make_env("planar")
    lo, hi = oracle.cfg.handback_steps
    rewound = 0
    for ep in episodes:
        probe.reset(seed=ep["seed"])
        assert np.allclose(ep["q"][0], probe.q)
        for t in range(len(ep["q"]) - 1):  # q[t+1] = step rule(q[t], action[t]): no gap at a rewind
            nxt = np.clip(ep["q"][t] + np.clip(ep["action"][t] - ep["q"][t], -probe.max_step, probe.max_step),
                          *probe.joint_limits)
            assert np.allclose(ep["q"][t + 1], nxt, atol=1e-12), (ep["seed"], t)
        assert 1 <= ep["interventions"] <= oracle.cfg.max_interventions
        e = ep["expert"].astype(int)
        starts, ends = np.flatnonzero(np.diff(np.r_[0, e]) == 1), np.flatnonzero(np.diff(np.r_[e, 0]) == -1) + 1
        for a, b in zip(starts, ends):
            assert b - a >= lo
            assert b - a <= hi * oracle.cfg.max_interventions
            assert b - a <= hi or b == len(e)  # back-to-back takeovers join, else within the range
        # policy steps before the first intervention: a stall needs stall_window steps, a rewind removes some
        first = starts[0]
        rewound += first < oracle.cfg.stall_window + 1
    assert rewound >= 1  # at least one takeover came after a rewind


@pytest.mark.parametrize("methods, message", [(",", "an empty item"), ("pooled,,fixed_4", "an empty item"),
                                              ("pooled,pooled", "pooled listed twice"), ("nope", "unknown")])
def test_methods_option_rejects_empty_duplicate_and_unknown_items(methods, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.parse_args(["--methods", methods])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_another_set_of_methods_gets_its_own_folder():
    _, cfg = cli.parse_args(["--methods", "pooled,per_step"])
    assert cfg.name == "quick_pooled-per_step"
    _, same = cli.parse_args(["--methods", ",".join(profiles.PROFILES["quick"].methods)])
    assert same.name == "quick"


def test_a_config_mismatch_names_the_fields_and_exits_without_a_traceback(tmp_path, capsys):
    root = str(tmp_path / "run")
    run_folder.Run(root, TINY)
    with pytest.raises(run_folder.ConfigMismatch, match=r"bc_steps = 30 there, 31 now"):
        run_folder.Run(root, replace(TINY, bc_steps=31))
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["--profile", "smoke", "--out", root])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "Traceback" not in err
    assert "--out" in err and "delete" in err and "n_demos = 4 there, 16 now" in err


def test_degenerate_statistics_say_why_instead_of_a_p_value():
    cfg = dagger.Config(name="t", rounds=1, lineages=3, methods=("bc", "hg_dagger", "fixed_4", "pooled"))
    results = {"bc": {"all": [50.0]}, "hg_dagger": {"0": [60.0], "1": [61.0], "2": [62.0]},
               "fixed_4": {"0": [60.0], "1": [61.0], "2": [62.0]}, "pooled": {"0": [60.0], "1": [61.0], "2": [62.0]}}
    table, stats = report.summarize(cfg, results)
    text = report.format_table(cfg, table, stats)
    assert "no spread" in text and "p = 0 " not in text and "p = 1 " not in text
    assert report.format_cell((55.0, 0.0, 1)) == "55.0 (1)" and report.format_cell((55.0, 1.5, 3)) == "55.0 ± 1.5 (3)"


@pytest.mark.slow
def test_ctrl_c_stops_with_one_line_and_status_130_and_the_run_resumes(tmp_path):
    """SIGINT during a smoke run: exit status 130, no traceback, one line saying how to resume; the same
    command then continues from the finished stages (D0 is not made again)."""
    import signal
    import subprocess
    import sys
    import time
    out = str(tmp_path / "smoke")
    cmd = [sys.executable, "dagger.py", "--profile", "smoke", "--out", out, "--prepare"]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    # a background shell (nohup, CI) starts children with SIGINT ignored, and Python then installs no handler:
    # give the child the default disposition so that it raises KeyboardInterrupt as in a terminal
    proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    log = os.path.join(out, "log.txt")
    while time.time() < deadline and not (os.path.exists(log) and "BC:" in open(log).read()):
        time.sleep(0.2)  # D0 is on disk once BC starts
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "run the same command again to resume" in stderr
    assert len([line for line in stderr.splitlines() if line.strip() and "pybullet build time" not in line]) == 1
    again = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert "oracle demonstrations" not in again.stdout  # D0 was loaded, not made again


def test_a_ctrl_c_that_lands_in_a_finalizer_still_stops_the_run(capsys):
    """Python ignores an exception raised in a finalizer (pymunk frees its bodies in callbacks that the garbage
    collector runs at any time: the smoke run above lost its Ctrl-C so about one time in two); run_command asks for
    the interrupt again, so the command stops with status 130 all the same, and puts the default hook back."""
    hook = sys.unraisablehook

    class Freed:
        def __del__(self):
            raise KeyboardInterrupt  # what a Ctrl-C landing in a finalizer becomes: ignored by Python

    def work():
        Freed()
        deadline = time.time() + 10
        while time.time() < deadline:
            time.sleep(0.01)
        return "finished"  # only if the interrupt was lost

    # a background shell (nohup, CI) starts pytest with SIGINT ignored: Python's own handler, as in a terminal
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(SystemExit) as stop:
            cli.run_command(work)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert stop.value.code == 130 and "run the same command again to resume" in capsys.readouterr().err
    assert sys.unraisablehook is hook


def test_every_readme_command_parses_and_none_is_refused_by_another_commands_folder():
    """Every `python dagger.py ...` line of the README's command blocks is a valid command line, and two
    commands that share a run folder share its config, so running them in any order never hits the
    "made with another config" refusal (e.g. the --methods example right after the default run)."""
    import re
    import shlex
    readme = open(os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "README.md")).read()
    blocks = re.findall(r"```bash\n(.*?)```", readme, flags=re.S)
    commands = []
    for block in blocks:
        for line in block.splitlines():
            if "python dagger.py" in line and "$" not in line:
                argv = shlex.split(line.split("python dagger.py", 1)[1].split("#", 1)[0].strip().strip('"'))
                commands.append(argv)
    assert len(commands) >= 8
    folders = {}
    for argv in commands:
        if "--help" in argv:
            continue
        args, cfg = cli.parse_args(argv)
        folder = args.out or os.path.join("runs", cfg.name)
        seen = folders.setdefault(folder, cfg)
        changed = [f.name for f in dataclasses.fields(dagger.Config) if getattr(seen, f.name) != getattr(cfg, f.name)
                   and f.name not in run_folder.FOLDER_FREE_FIELDS]
        assert not changed, f"{argv} would be refused in {folder}: {changed} differ"


@pytest.mark.slow
@pytest.mark.parametrize("stage_file", ["data/D0.npz", "checkpoints/bc.pt", "eval/bc.json",
                                        "lineage_0/round_1/calibration.json", "lineage_0/round_1/D.npz"])
def test_a_damaged_stage_file_is_named_and_never_reused(full_run, tmp_path, stage_file, capsys):
    """A truncated stage file: a clear error naming it and the way forward (delete it, run again), exit 2."""
    import shutil
    root = str(tmp_path / "copy")
    shutil.copytree(full_run, root)
    path = os.path.join(root, stage_file)
    data = open(path, "rb").read()
    with open(path, "wb") as f:
        f.write(data[: len(data) // 2])
    with pytest.raises(run_folder.RunFolderError, match="damaged") as err:
        report.run_experiment(TINY, root)
    assert path in str(err.value) and "Delete it and run the same command again" in str(err.value)
    os.remove(path)  # the way forward works: the stage is made again
    report.run_experiment(TINY, root)
    assert json.load(open(os.path.join(root, "results.json")))["success"] == \
        json.load(open(os.path.join(full_run, "results.json")))["success"]


def test_an_out_folder_that_cannot_be_made_is_a_clear_error(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["--profile", "smoke", "--out", str(blocker / "run")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "cannot use" in err and str(blocker / "run") in err and "--out" in err and "Traceback" not in err


def readme_commands():
    """Every `python dagger.py ...` command of the README, in order: the command blocks and the inline ones
    (a line that uses a shell variable, e.g. the Slurm example, is not a command a reader types)."""
    import re
    import shlex
    readme = open(os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "README.md")).read()
    commands = []
    for block in re.findall(r"```bash\n(.*?)```|`(python dagger\.py[^`]*)`", readme, flags=re.S):
        for line in (block[0] or block[1]).splitlines():
            if "python dagger.py" in line and "$" not in line:
                tail = line.split("python dagger.py", 1)[1].split("#", 1)[0].strip().strip('"').rstrip("&").strip()
                commands.append(shlex.split(tail))
    return commands


@pytest.mark.slow
def test_the_readme_commands_run_in_order_on_the_smoke_profile(tmp_path, monkeypatch, capsys):
    """Each README command, as written but with its profile (and the profile's folder runs/<profile>) swapped
    for a shrunken smoke profile, runs to the end in the order the README gives them, in one working folder:
    none is refused by a folder another command made (e.g. --methods right after the default run), --help
    prints the options. A command that the swap makes the same as an earlier one runs once (the README's
    `python dagger.py` and `--profile mid` are both the smoke run then): its second run would only redo a
    finished folder, which `--workers 1` and `--report` below still do."""
    smoke = replace(TINY, name="smoke", methods=("bc", "hg_dagger", "fixed_4", "pooled"), eval_scenarios=2,
                    n_demos=2, bc_steps=10, finetune_steps=6)
    monkeypatch.setitem(profiles.PROFILES, "smoke", smoke)
    monkeypatch.chdir(tmp_path)
    commands, swapped = readme_commands(), []
    assert len(commands) >= 10 and [] in commands and any("--report" in c for c in commands)
    for argv in commands:
        if "--profile" in argv:
            i = argv.index("--profile")
            argv = [a.replace(f"runs/{argv[i + 1]}", "runs/smoke") for a in argv[:i] + argv[i + 2:]]
        if argv not in swapped:
            swapped.append(argv)
    assert ["--workers", "1"] in swapped and ["--report"] in swapped  # a finished folder is still run again
    for argv in swapped:
        if "--help" in argv:
            with pytest.raises(SystemExit) as done:
                cli.main(argv)
            assert done.value.code == 0 and "--methods" in capsys.readouterr().out
            continue
        root = cli.main(argv + ["--profile", "smoke"])
        if "--prepare" not in argv:
            assert os.path.isfile(os.path.join(root, "report.md")), argv


def test_fixed_sigma_is_in_the_papers_median_steps():
    """Table I's sigma = 4 is 4 of the authors' median steps (envs.paper_median_step, rad) per joint, whatever
    our own unit: the noise the sampler draws (relabel.noise_factors) has the same std in radians for two runs
    whose median steps differ 2x, and that is not 4 of our steps. An env without the paper's unit keeps ours."""
    paper = envs.PlanarReacher.paper_median_step
    drawn = []
    for ours in (0.02, 0.04):  # two runs' own median steps, rad
        kind, sigma = dagger.noise_model("fixed_4", None, None, ours, paper)
        L = relabel.noise_factors(sigma, np.array([0]), 3, median_step=ours)[0]  # (dof, dof), L L^T = Sigma
        drawn.append(np.sqrt(np.diag(L @ L.T)))                                  # per-joint std, rad
        assert kind == "isotropic" and not np.allclose(drawn[-1], 4 * ours)
    np.testing.assert_allclose(drawn[0], drawn[1])
    np.testing.assert_allclose(drawn[0], 4 * paper)
    assert dagger.noise_model("fixed_16", None, None, 0.0245, None) == ("isotropic", 16.0)
    assert "paper's unit" in report.method_label("fixed_4")
    # the sweep in radians per joint as the authors' unit gives it (0.0176 rad: benchmarks/SETUP.md §1), from a run
    # whose own unit is the per-joint median step (0.0282 rad on 20 planar oracle demonstrations)
    for sigma, rad in ((2, 0.035), (4, 0.070), (8, 0.141), (12, 0.211), (16, 0.282)):
        _, ours = dagger.noise_model(f"fixed_{sigma}", None, None, 0.0282, paper)
        assert ours * 0.0282 == pytest.approx(rad, abs=6e-4)


def test_demo_statistics_carry_the_units_the_authors_set_knobs_in():
    env = envs.make_env("planar")
    demos = [straight_line_episode(env, seed) for seed in env.train_seeds(3)]
    stats = dagger.demo_statistics(TINY, demos)
    assert stats.paper_median_step == 0.0176 and stats.frames_per_step == pytest.approx(3.0)  # 10 Hz env
    assert relabel.velocity_noise_std(relabel.RelabelConfig(horizon=16), stats) == pytest.approx(0.3 * 0.0176 * 3)
    # the authors' N(0, (0.3 m_p)²) per joint per 30 Hz frame (m_p = 0.0176 rad, benchmarks/SETUP.md §6) is 0.158 rad/s
    # whatever the env's rate: 0.0158 rad a 10 Hz step, not 0.3 of our per-joint median step
    assert relabel.velocity_noise_std(relabel.RelabelConfig(horizon=16), stats) / 0.1 == pytest.approx(0.1584)


@pytest.mark.slow
def test_every_policy_is_also_evaluated_on_unseen_scenarios(full_run):
    unseen = envs.unseen_seeds()[:TINY.eval_scenarios]
    paths = ["eval/bc_unseen.json", *[f"lineage_0/round_1/eval/{m}_unseen.json" for m in TINY.methods if m != "bc"]]
    for path in paths:
        saved = json.load(open(os.path.join(full_run, path)))
        assert saved["seeds"] == unseen and np.shape(saved["success"]) == (TINY.eval_scenarios, TINY.eval_repeats)
    results = json.load(open(os.path.join(full_run, "results.json")))
    assert set(results["success_unseen"]) == set(TINY.methods) and "paired_vs_hg_dagger" in results["stats_unseen"]
    table = open(os.path.join(full_run, "table.md")).read()
    assert "the 3 evaluation scenarios, on which HG-DAgger collected (the authors' protocol)" in table
    assert "held-out" not in table
    assert "**Unseen scenarios.**" in table and "3 unseen scenarios (never trained on)" in table
    assert table.count("| Method |") == 3           # the run's table, the paper's for the same rows, the unseen one
    assert "| Method |" in table.split("**Unseen scenarios.**")[1] and "The paper's Table I" in table
    bc_unseen = 100.0 * np.mean(json.load(open(os.path.join(full_run, "eval/bc_unseen.json")))["success"])
    assert results["success_unseen"]["bc"]["all"] == [pytest.approx(bc_unseen)]
    rows = open(os.path.join(full_run, "results.csv")).read().splitlines()
    assert rows[0] == "method,lineage,round,success_pct,unseen_success_pct"
    assert all(row.split(",")[-1] != "" for row in rows[1:])               # every cell has its unseen number
    assert "unseen scenarios (never trained on)" in open(os.path.join(full_run, "report.md")).read()


@pytest.mark.slow
def test_calibration_is_reported_in_the_papers_unit_radians_beside(full_run):
    results = json.load(open(os.path.join(full_run, "results.json")))
    cal = results["stats"]["calibration"]["1"]["0"]
    saved = json.load(open(os.path.join(full_run, "lineage_0/round_1/calibration.json")))
    assert cal["W_rad"] == pytest.approx(saved["W"]) and cal["W"] == pytest.approx(saved["W"] / saved["median_step"])
    assert cal["W_paper"] == pytest.approx(saved["W"] / 0.0176)
    np.testing.assert_allclose(cal["sigma_per_joint_paper"], np.sqrt(np.diag(saved["pooled"])) / 0.0176)
    table = open(os.path.join(full_run, "table.md")).read()
    one_unit = f"W = {saved['W'] / 0.0176:.2f} paper median steps ({saved['W']:.3f} rad)"  # one unit, rad beside
    assert one_unit + " (the paper: 8.0)" in table
    assert "(the paper: 3.9–5.1)" in table
    assert one_unit in open(os.path.join(full_run, "log.txt")).read()     # the calibration's log


def test_more_lineages_can_join_an_existing_run_folder(tmp_path):
    root = str(tmp_path / "run")
    run_folder.Run(root, TINY)
    run_folder.Run(root, replace(TINY, lineages=TINY.lineages + 2))  # adds lineage folders only: no mismatch
    assert run_folder.read_json(os.path.join(root, "config.json"))["lineages"] == TINY.lineages + 2  # the record
    run_folder.Run(root, TINY)  # a report over fewer lineages reads the same folder
    assert run_folder.read_json(os.path.join(root, "config.json"))["lineages"] == TINY.lineages + 2
    with pytest.raises(run_folder.ConfigMismatch, match="rounds"):
        run_folder.Run(root, replace(TINY, lineages=TINY.lineages + 2, rounds=TINY.rounds + 1))


def test_eval_unseen_switch():
    _, cfg = cli.parse_args(["--profile", "smoke", "--no-eval-unseen"])
    assert not cfg.eval_unseen and profiles.PROFILES["smoke"].eval_unseen


@pytest.mark.slow
def test_eval_unseen_can_change_on_an_existing_run_folder(full_run, tmp_path):
    """eval_unseen may differ from the folder's config: off, the run re-makes no stage and adds no unseen
    evaluation; on again, it adds exactly the unseen evaluations, equal to the ones made in the first place."""
    import shutil
    root = str(tmp_path / "copy")
    shutil.copytree(full_run, root)
    unseen = sorted(os.path.relpath(os.path.join(d, f), root) for d, _, fs in os.walk(root) for f in fs
                    if f.endswith("_unseen.json") and os.path.basename(d) == "eval")
    assert len(unseen) == len(TINY.methods)
    for name in unseen:
        os.remove(os.path.join(root, name))
    stages = {os.path.join(d, f): os.stat(os.path.join(d, f)).st_mtime_ns for d, _, fs in os.walk(root) for f in fs
              if f.endswith((".pt", ".npz")) or (f.endswith(".json") and os.sep + "eval" + os.sep in os.path.join(d, f))}
    report.run_experiment(replace(TINY, eval_unseen=False), root)
    assert not [n for n in unseen if os.path.exists(os.path.join(root, n))]
    report.run_experiment(TINY, root)
    for name in unseen:
        assert json.load(open(os.path.join(root, name))) == json.load(open(os.path.join(full_run, name)))
    assert {p: os.stat(p).st_mtime_ns for p in stages} == stages  # nothing else was made again


@pytest.mark.slow
def test_a_lineage_run_elsewhere_joins_a_run_folder_made_like_it(full_run, tmp_path):
    """A lineage records the config and the pi_0 it was made with (lineage_<l>/lineage.json); a lineage folder
    copied in from another run folder with the same shared stages joins the report (--lineages N), and one made
    with another config or from another pi_0 is refused, naming what differs."""
    import shutil
    record = json.load(open(os.path.join(full_run, "lineage_0", "lineage.json")))
    assert record["pi0_sha256"] == run_folder.weights_sha256(os.path.join(full_run, "checkpoints", "bc.pt"))
    assert {k: tuple(v) if isinstance(v, list) else v for k, v in record["config"].items()} == dataclasses.asdict(TINY)
    root = str(tmp_path / "joined")
    shutil.copytree(full_run, root)
    shutil.copytree(os.path.join(full_run, "lineage_0"), os.path.join(root, "lineage_1"))  # "run on another machine"
    report.run_experiment(replace(TINY, lineages=2), root, report_only=True)
    results = json.load(open(os.path.join(root, "results.json")))
    assert set(results["success"]["hg_dagger"]) == {"0", "1"}
    assert "| HG-DAgger | " in open(os.path.join(root, "table.md")).read() and "(2) |" in open(
        os.path.join(root, "table.md")).read()
    other = os.path.join(root, "lineage_1", "lineage.json")
    json.dump({**record, "config": {**record["config"], "bc_steps": 31}}, open(other, "w"))
    with pytest.raises(run_folder.ConfigMismatch, match=r"lineage_1 holds a run made with another config: bc_steps = 31"):
        report.run_experiment(replace(TINY, lineages=2), root, report_only=True)
    json.dump({**record, "pi0_sha256": "0" * 64}, open(other, "w"))
    with pytest.raises(run_folder.ConfigMismatch, match="lineage_1 was made from another pi_0"):
        report.run_experiment(replace(TINY, lineages=2), root, report_only=True)


@pytest.mark.slow
def test_closed_loop_row_is_its_own_chain_collected_and_measured_by_its_calibrated_policy(tmp_path, monkeypatch):
    """Table I's closed-loop pooled row: round 1 shares pi_0's interventions and HG-DAgger's round-1
    calibration; from round 2 on, the previous round's closed_loop policy collects (skipping what its own
    evaluation solved), is measured on the chain's interventions, and the row trains with that pooled noise."""
    calls, made = [], {}
    for name in ("collect_interventions", "calibrate_noise", "fine_tune", "evaluate_policy"):
        real = getattr(dagger, name)

        def spy(*args, _real=real, _name=name, **kwargs):
            out = _real(*args, **kwargs)  # lists as they were at the call (rounds_data grows later)
            calls.append((_name, tuple(list(a) if isinstance(a, list) else a for a in args), kwargs, out))
            return out
        monkeypatch.setattr(dagger, name, spy)
    cfg = replace(TINY, rounds=2, methods=("bc", "hg_dagger", "closed_loop"))
    report.run_experiment(cfg, str(tmp_path))
    for name, args, kwargs, out in calls:
        if name == "fine_tune":
            made[(args[2], args[3])] = (out, args[6], args[7])  # (k, method): policy, data, calibration
        if name == "evaluate_policy":
            made[args[2]] = out
        if name == "collect_interventions" and len(args[1]) > 2:  # keys (lineage, k, chain)
            chain_collect = args
        if name == "calibrate_noise" and len(args[1]) > 2:
            chain_cal = (args, args[3], out)
    cl1, data1, cal1 = made[(1, "closed_loop")]
    hg1_data = made[(1, "hg_dagger")][1]
    assert len(data1) == 1 and data1[0] is hg1_data[0]  # round 1: pi_0's interventions, as HG-DAgger's
    main_cal1 = run_folder.calibration_from_json(json.load(open(tmp_path / "lineage_0/round_1/calibration.json")))
    np.testing.assert_array_equal(cal1.pooled, main_cal1.pooled)
    # round 2: collected by the round-1 closed_loop policy with its own evaluation as the skip list
    assert chain_collect[2] is cl1 and chain_collect[1] == (0, 2, "closed_loop")
    np.testing.assert_array_equal(chain_collect[3], made["lineage_0/round_1/eval/closed_loop.json"])
    cal_args, cal_data, chain_calibration = chain_cal
    assert cal_args[2] is cl1 and len(cal_data) == 2 and cal_data[0] is data1[0]
    cl2, data2, cal2 = made[(2, "closed_loop")]
    assert cal2 is chain_calibration and len(data2) == 2 and all(a is b for a, b in zip(data2, cal_data))
    assert dagger.noise_model("closed_loop", cal2)[1] is cal2.pooled
    for f in ("lineage_0/round_2/closed_loop/D.npz", "lineage_0/round_2/closed_loop/calibration.json",
              "lineage_0/round_2/eval/closed_loop.json", "lineage_0/round_2/checkpoints/closed_loop.pt"):
        assert (tmp_path / f).is_file(), f
    assert not (tmp_path / "lineage_0/round_1/closed_loop").exists()
    timings = sorted(os.listdir(tmp_path / "timings"))  # the chain's stages timed apart from the main chain's
    for kind in ("collect", "calibrate"):
        assert {f"{kind}__lineage_0__round_2.json", f"{kind}__lineage_0__round_2__closed_loop.json"} <= set(timings)
    assert "train_closed_loop__lineage_0__round_2.json" in timings
    # the main chain's round 2 is HG-DAgger's: its own folder, collected by HG-DAgger's round-1 policy
    main_collect = [a for n, a, kw, _ in calls if n == "collect_interventions" and a[1] == (0, 2)]
    assert main_collect[0][2] is made[(1, "hg_dagger")][0]
    table = open(tmp_path / "table.md").read()
    assert "Closed-loop pooled" in table
    assert "- the closed-loop row's own chain" in table and "  - K=2: 0: W " in table  # its calibration, reported


def test_table1_profile_is_all_of_table_i_and_its_cost_counts_every_stage_of_a_lineage(tmp_path, load_benchmark):
    """The table1 profile: the mid recipe with the paper's five rounds and all ten rows. benchmarks/table1_cost.py
    counts a lineage's stages as the loop runs them and projects unmeasured rounds from the measured ones."""
    cfg, mid = profiles.PROFILES["table1"], profiles.PROFILES["mid"]
    assert cfg.rounds == 5 and cfg.lineages == 5 and cfg.methods == dagger.TABLE_I_METHODS
    assert {f.name for f in dataclasses.fields(cfg) if getattr(cfg, f.name) != getattr(mid, f.name)} == {
        "name", "rounds", "methods"}
    cost = load_benchmark("table1_cost")
    run = run_folder.Run(str(tmp_path), mid)
    seconds = {"demos": 80, "train_bc": 150, "bc": 150}
    for stage, s in seconds.items():
        run.record_time(stage, s)
    run.record_time("evaluate/eval/pi0.json", 10)
    for lineage in (0, 1):
        for k, calib in ((1, 10), (2, 16)):  # calibration grows with the rounds' interventions
            where = f"lineage_{lineage}/round_{k}"
            run.record_time(f"collect/{where}", 50)
            run.record_time(f"calibrate/{where}", calib)
            run.record_time(f"train_hg_dagger/{where}", 200)
            for m in ("fixed_2", "pooled"):
                run.record_time(f"train_{m}/{where}", 300)
                run.record_time(f"evaluate/{where}/eval/{m}.json", 10)
    timings = cost.read_timings(str(tmp_path), None)
    wall1, rows = cost.lineage_wall(cfg, timings, 1)
    counts = {name: n for name, (n, _, _) in rows.items()}
    assert counts == {"collect": 5, "cell: HG-DAgger (train + evaluations)": 5, "calibrate": 5,
                      "cell: a noised arm (train + evaluations)": 35, "closed-loop chain: cell": 5,
                      "closed-loop chain: collect": 4, "closed-loop chain: calibrate": 4}
    assert rows["calibrate"][1] == pytest.approx(10 + 16 + 22 + 28 + 34)  # a line through rounds 1 and 2
    assert not rows["calibrate"][2] and cost.per_round(timings, "calibrate", 2, grow=True) == (16, True)
    cell = 300 + 2 * 10  # training and the two evaluations (eval + unseen)
    assert rows["cell: a noised arm (train + evaluations)"][1] == pytest.approx(35 * cell)
    assert wall1 == pytest.approx(sum(s for _, s, _ in rows.values()))
    wall7, _ = cost.lineage_wall(cfg, timings, 7)  # the 7 noised arms of a round in one wave
    assert wall1 - wall7 == pytest.approx(5 * 6 * cell)


@pytest.mark.slow
def test_lever_networks_benchmark_trains_every_candidate_on_the_same_demonstrations(tmp_path, monkeypatch,
                                                                                      load_benchmark):
    """benchmarks/lever_networks.py: D0 collected once and copied into every candidate's folder; each candidate's
    pi_0 trained with its own fields (a continued one also gets the BC row, pi_0 continued on D0); the table's
    steps per CPU-second and points per CPU-minute come from the measured CPU time of a step and the evaluations;
    a rerun trains nothing."""
    bench = load_benchmark("lever_networks")
    monkeypatch.setattr(bench, "CANDIDATES", {
        "unet": dict(recipe="authors_lever"),  # the smoke profile's U-Net (16, 32), pi_0 at the end of its own cosine
        "mlp_h8": dict(network="mlp", mlp_width=32, mlp_blocks=1, horizon=8, n_act=4,
                       bc_steps=40, finetune_steps=20)})
    fields = dict(n_demos=6, bc_steps=40, finetune_steps=20, eval_scenarios=4, K=5)
    monkeypatch.setitem(profiles.PROFILES, "smoke", replace(profiles.PROFILES["smoke"], **fields))
    out = str(tmp_path / "nets")
    with pytest.raises(SystemExit, match="unknown candidate 'lstm'"):
        bench.main(["--base", "smoke", "--out", out, "--candidates", "unet,lstm"])
    assert not os.path.exists(out)  # every name is checked before anything runs
    text = bench.main(["--base", "smoke", "--out", out, "--candidates", "unet,mlp_h8"])
    d0 = open(os.path.join(out, "D0", "data", "D0.npz"), "rb").read()
    for name in ("unet", "mlp_h8"):
        assert open(os.path.join(out, name, "data", "D0.npz"), "rb").read() == d0
    mlp = dagger.Config(**run_folder.read_json(os.path.join(out, "mlp_h8", "config.json")))
    assert (mlp.network, mlp.horizon, mlp.n_act, mlp.eval_unseen) == ("mlp", 8, 4, False)
    assert os.path.exists(os.path.join(out, "mlp_h8", "checkpoints", "bc_continued.pt"))  # the BC row, continued
    assert not os.path.exists(os.path.join(out, "unet", "checkpoints", "bc_continued.pt"))  # constant: pi_0 itself
    rows = {r["candidate"]: r for r in (bench.result_row(out, n) for n in ("unet", "mlp_h8"))}
    seconds = 40 * run_folder.read_json(os.path.join(out, "mlp_h8", "cpu_per_step.json"))["seconds"]
    assert 0 < seconds < 60
    pi0 = 100 * np.mean(run_folder.read_json(os.path.join(out, "mlp_h8", "eval", "pi0.json"))["success"])
    assert rows["mlp_h8"]["steps_per_s"] == pytest.approx(40 / seconds)
    assert rows["mlp_h8"]["pi0"] == pytest.approx(pi0)
    assert rows["mlp_h8"]["points_per_minute"] == pytest.approx(pi0 / (seconds / 60))
    assert rows["unet"]["pi0"] == rows["unet"]["bc_row"]  # constant: the BC row is pi_0
    assert rows["mlp_h8"]["chunk"] == "8 / 4" and "MLP 32 x 1" in text and "U-Net (16, 32)" in text
    assert len(text.splitlines()) == 4
    stamp = os.path.getmtime(os.path.join(out, "mlp_h8", "checkpoints", "bc.pt"))
    assert bench.main(["--base", "smoke", "--out", out, "--candidates", "unet,mlp_h8"]) == text  # resumed: done
    assert os.path.getmtime(os.path.join(out, "mlp_h8", "checkpoints", "bc.pt")) == stamp


@pytest.mark.slow
def test_a_lineage_results_file_exported_here_joins_another_folder_and_is_refused_where_it_does_not_belong(
        full_run, tmp_path):
    """--export-lineages writes one small file per lineage (its evaluations, calibrations, timings and the shared
    evaluations it pairs with; no checkpoints or data); --join unpacks it into another folder of the same config,
    whose report then has the lineage's numbers exactly. Another config, another pi_0, clashing results or a file
    that is not one are refused with what differs."""
    out = str(tmp_path / "results")
    run = run_folder.Run(full_run, TINY)
    (path,) = run_folder.export_lineages(run, out)
    first = open(path, "rb").read()
    time.sleep(1.1)  # a gzip header's time has 1 s resolution
    assert run_folder.export_lineages(run, out) == [path] and open(path, "rb").read() == first  # same bytes again
    import gzip
    data = json.load(gzip.open(path, "rt"))
    assert os.path.basename(path) == "lineage_0.json.gz" and data["rounds_finished"] == 1
    assert "lineage_0/round_1/eval/hg_dagger.json" in data["files"] and "eval/bc.json" in data["files"]
    assert "lineage_0/round_1/calibration.json" in data["files"] and "lineage_0/lineage.json" in data["files"]
    assert any(f.startswith("timings/train_pooled__lineage_0") for f in data["files"])
    assert not any(f.endswith((".pt", ".npz")) for f in data["files"])
    assert data["pi0_sha256"] == run_folder.weights_sha256(os.path.join(full_run, "checkpoints", "bc.pt"))

    root = str(tmp_path / "joined")  # a folder of results files only: no D0, no pi_0 checkpoint
    report.run_experiment(TINY, root, report_only=True, join=[path])
    report.run_experiment(TINY, root, report_only=True, join=[path])  # joining the same file again changes nothing
    mine, theirs = (json.load(open(os.path.join(r, "results.json")))["success"] for r in (root, full_run))
    assert mine == theirs and set(mine["pooled"]) == {"0"}
    assert "| HG-DAgger | " in open(os.path.join(root, "table.md")).read()

    bad = str(tmp_path / "bad.json")
    json.dump({**data, "config": {**data["config"], "bc_steps": 31}}, open(bad, "w"))
    with pytest.raises(run_folder.ConfigMismatch, match=r"bad.json \(lineage 0\) holds a run made with another "
                                                        r"config: bc_steps = 31 there, 30 now"):
        report.run_experiment(TINY, str(tmp_path / "other"), report_only=True, join=[bad])
    json.dump({**data, "pi0_sha256": "0" * 64}, open(bad, "w"))
    with pytest.raises(run_folder.ConfigMismatch, match="was made from another pi_0"):
        report.run_experiment(TINY, root, report_only=True, join=[bad])
    files = dict(data["files"])
    files["lineage_0/round_1/eval/pooled.json"] = {**files["lineage_0/round_1/eval/pooled.json"], "success": [[True]]}
    json.dump({**data, "files": files}, open(bad, "w"))
    with pytest.raises(run_folder.ConfigMismatch, match=r"holds other results than .* lineage_0/round_1/eval/pooled"):
        report.run_experiment(TINY, root, report_only=True, join=[bad])
    json.dump({"success": []}, open(bad, "w"))
    with pytest.raises(run_folder.RunFolderError, match="not a lineage results file"):
        report.run_experiment(TINY, root, report_only=True, join=[bad])
    with pytest.raises(run_folder.RunFolderError, match="no such file"):
        report.run_experiment(TINY, root, report_only=True, join=[str(tmp_path / "missing.json")])
    assert not os.path.exists(os.path.join(str(tmp_path / "other"), "lineage_0"))  # a refused join leaves nothing


@pytest.mark.slow
def test_a_lineage_keeps_the_return_label_it_was_made_with(full_run, tmp_path):
    """The label is recorded per lineage (lineage.json, the results file; none recorded: the old servo's): a lineage
    of another label joins only a folder of that label, a report names it, a new lineage does not start in a folder
    of another label's lineages, and a stage of such a lineage is not computed with this code's label. Fails if the
    default rows' label changes under a run folder's finished stages unnoticed."""
    import gzip
    run = run_folder.Run(full_run, TINY)
    (path,) = run_folder.export_lineages(run, str(tmp_path / "results"))
    data = json.load(gzip.open(path, "rt"))
    assert data["return_label"] == "pd" and data["files"]["lineage_0/lineage.json"]["return_label"] == "pd"
    assert "the paper's PD" in open(os.path.join(full_run, "report.md")).read()
    old = {k: v for k, v in data.items() if k != "return_label"}  # a file of before the label was recorded
    old["files"] = {**data["files"], "lineage_0/lineage.json": {
        k: v for k, v in data["files"]["lineage_0/lineage.json"].items() if k != "return_label"}}
    old_path = str(tmp_path / "old.json")
    json.dump(old, open(old_path, "w"))
    root = str(tmp_path / "joined_old")
    report.run_experiment(TINY, root, report_only=True, join=[old_path])  # joins a folder of its own, and reports
    assert "the servo as converted up to commit 6192871" in open(os.path.join(root, "report.md")).read()
    new = {**data, "lineage": 1, "files": {k.replace("lineage_0", "lineage_1"): v for k, v in data["files"].items()}}
    new_path = str(tmp_path / "new.json")
    json.dump(new, open(new_path, "w"))
    with pytest.raises(run_folder.ConfigMismatch, match="one table holds one return label"):
        report.run_experiment(TINY, root, report_only=True, join=[new_path])
    import shutil
    os.makedirs(os.path.join(root, "checkpoints"))
    shutil.copyfile(os.path.join(full_run, "checkpoints", "bc.pt"), os.path.join(root, "checkpoints", "bc.pt"))
    with pytest.raises(run_folder.ConfigMismatch, match="another return label"):  # a new lineage beside them
        run_folder.Run(root, TINY).claim_lineage(1)
    with pytest.raises(run_folder.ConfigMismatch, match="does not continue across a change of label"):
        run_folder.Run(root, TINY).stage("lineage_0/round_2/D.npz", lambda: [])
    assert not os.path.exists(os.path.join(root, "lineage_0", "round_2", "D.npz"))


def files_and_times(root):
    """{path: (mtime_ns, size)} of every file under root: what a refused command must leave as it was (the folder's
    lock files aside: a command writes its PID into the lock it takes)."""
    return {os.path.join(top, n): (os.stat(os.path.join(top, n)).st_mtime_ns, os.stat(os.path.join(top, n)).st_size)
            for top, _, names in os.walk(root) for n in names
            if run_folder.LOCK_FOLDER not in os.path.relpath(top, root).split(os.sep)}


@pytest.mark.slow
@pytest.mark.parametrize("name,bad,expected", [
    # a cell's evaluation of another shape: was averaged into the table as if it were the cell's (100 % here)
    ("lineage_0/round_1/eval/pooled.json", {"success": [[True]], "seeds": [10_000]},
     "success of shape (1, 1); expected success of shape (3, 1) (eval_scenarios x eval_repeats of the run's "
     "config) on the evaluation scenarios' seeds 10000..10002 (3 seeds)"),
    # the right shape on the wrong scenarios: the evaluation scenarios in the BC row's unseen-scenarios file
    ("eval/bc_unseen.json", {"success": [[True], [False], [True]], "seeds": [10_000, 10_001, 10_002]},
     "seeds 10000..10002 (3 seeds); expected success of shape (3, 1) (eval_scenarios x eval_repeats of the "
     "run's config) on the unseen scenarios' seeds 20000..20002 (3 seeds)"),
])
def test_the_report_refuses_an_evaluation_of_another_shape_or_scenarios(full_run, tmp_path, name, bad, expected,
                                                                        capsys):
    """Bug: --report read any evaluation file with a success table, whatever its shape or scenarios, and printed
    its mean as the cell (e.g. 100 % from one episode). Now a file that is not (eval_scenarios x eval_repeats) on
    the run's scenarios is refused with its name and what was expected, exit 2, and nothing is written."""
    import shutil
    root = str(tmp_path / "copy")
    shutil.copytree(full_run, root)
    path = os.path.join(root, *name.split("/"))
    json.dump(bad, open(path, "w"))
    before = files_and_times(root)
    with pytest.raises(SystemExit) as exit_info:
        cli.run_command(report.run_experiment, TINY, root, None, False, True)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "Traceback" not in err
    assert f"{path} is not an evaluation of this run: {expected}" in err
    assert files_and_times(root) == before  # no table, no results, no figure written over


@pytest.mark.slow
def test_a_joined_results_file_with_an_evaluation_of_another_shape_is_refused_and_leaves_nothing(full_run, tmp_path):
    """Bug: --join unpacked a lineage results file whose evaluation had another shape than its config says, and
    the report then averaged it into the table. Now the join names the results file and the evaluation in it,
    and unpacks nothing."""
    import gzip
    (path,) = run_folder.export_lineages(run_folder.Run(full_run, TINY), str(tmp_path / "results"))
    data = json.load(gzip.open(path, "rt"))
    files = dict(data["files"])
    files["lineage_0/round_1/eval/hg_dagger.json"] = {"success": [[True]], "seeds": [10_000]}
    bad = str(tmp_path / "bad.json")
    json.dump({**data, "files": files}, open(bad, "w"))
    root = str(tmp_path / "joined")
    with pytest.raises(run_folder.RunFolderError, match=r"bad.json \(lineage 0\): its lineage_0/round_1/eval/"
                                                        r"hg_dagger.json is not an evaluation of this run: "
                                                        r"success of shape \(1, 1\); expected .*\(3, 1\)"):
        report.run_experiment(TINY, root, report_only=True, join=[bad])
    assert not os.path.exists(os.path.join(root, "lineage_0")) and not os.path.exists(os.path.join(root, "eval"))


@pytest.mark.slow
def test_copy_from_adds_a_method_to_a_finished_run_and_trains_only_that_method(full_run, tmp_path, trained_stages):
    """--copy-from FOLDER (the sigma = 0 control beside a finished table): the stages of a run with the same config
    and fewer methods are copied in, so only the added method trains, and the copied rows report the same numbers.
    A folder with another config, or with a method this run lacks, is refused before anything is copied."""
    cfg = replace(TINY, methods=TINY.methods + ("zero_noise",), name="tiny_zero")
    root = str(tmp_path / "control")
    report.run_experiment(cfg, root, copy_src=full_run)
    assert trained_stages == ["lineage_0/round_1/checkpoints/zero_noise.pt"]
    mine, theirs = (json.load(open(os.path.join(r, "results.json")))["success"] for r in (root, full_run))
    assert set(mine) == set(theirs) | {"zero_noise"} and all(mine[m] == theirs[m] for m in theirs)
    record = json.load(open(os.path.join(root, "lineage_0", "lineage.json")))
    assert record["config"]["methods"][-1] == "zero_noise" and record["config"]["name"] == "tiny_zero"

    with pytest.raises(run_folder.ConfigMismatch, match="bc_steps = 30 there, 31 now"):
        report.run_experiment(replace(cfg, bc_steps=31), str(tmp_path / "other"), copy_src=full_run)
    fewer = replace(TINY, methods=("bc", "hg_dagger", "fixed_4", "pooled", "per_step"), name="tiny_fewer")
    with pytest.raises(run_folder.ConfigMismatch, match="it runs closed_loop, which this run does not"):
        report.run_experiment(fewer, str(tmp_path / "fewer"), copy_src=full_run)
    with pytest.raises(run_folder.RunFolderError, match="not a run folder"):
        report.run_experiment(cfg, str(tmp_path / "third"), copy_src=str(tmp_path / "missing"))
    assert not os.path.exists(os.path.join(str(tmp_path / "other"), "data"))  # a refused copy leaves no stage
    args, _ = cli.parse_args(["--profile", "table2", "--methods", "hg_dagger,zero_noise", "--copy-from", root])
    assert args.copy_from == root


@pytest.mark.slow
def test_w_spread_recalibrates_a_finished_round_at_other_blend_ratios(full_run, load_benchmark, capsys):
    """benchmarks/bench_calibrate.py --run --betas (the authors' six lever ratios against our 13): the round's
    HG-DAgger policy recalibrated per seed with the ratios given; the first seed is the run's own, so with the run's
    ratios it gives the run's W; a malformed list is refused with the valid form."""
    bench = load_benchmark("bench_calibrate")
    bench.w_spread(full_run, 2, 0, 1)
    ours = capsys.readouterr().out
    saved = json.load(open(os.path.join(full_run, "lineage_0", "round_1", "calibration.json")))
    paper = environments.paper_median_step(TINY.env)
    assert f"| {saved['W'] / paper:.2f} |" in ours.splitlines()[3] and "/13 |" in ours
    bench.w_spread(full_run, 2, 0, 1, betas=bench.parse_betas("0.2,0.5,0.8"))
    theirs = capsys.readouterr().out
    assert "/3 |" in theirs and "/13 |" not in theirs and "W spread: mean" in theirs
    for bad in ("0.2,x", "0.2,0.5", "0.2,0.5,1.5"):
        with pytest.raises(SystemExit, match="--betas"):
            bench.parse_betas(bad)


@pytest.mark.slow
def test_a_committed_start_gives_every_lineage_the_same_pi0_and_another_config_computes_its_own(
        full_run, tmp_path, monkeypatch, trained_stages, capsys):
    """--export-start writes a run's shared stages (D0, pi_0 with its optimizer state, the BC row, their evaluations)
    as benchmarks/results/<profile>/start/; a new folder of the profile's config then copies them in first (in
    --prepare as in --lineage i), so no shared stage trains and its pi_0 is the committed one, whatever the machine.
    Fails if the start is not loaded, if a lineage's files or partial checkpoints travel with it, if it is loaded
    into a run of another config (another seed: another pi_0 must be computed), or over a folder's own pi_0."""
    results = tmp_path / "results"
    monkeypatch.setattr(run_folder, "RESULTS_ROOT", str(results))
    monkeypatch.setitem(profiles.PROFILES, "tiny", TINY)
    with pytest.raises(SystemExit) as refused:  # nothing to export before --prepare finished
        cli.main(["--profile", "tiny", "--report", "--out", str(tmp_path / "empty"),
                     "--export-start", str(results / "tiny")])
    assert refused.value.code == 2 and "--prepare first" in capsys.readouterr().err
    assert not os.path.exists(results / "tiny")
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.raises(run_folder.RunFolderError, match="cannot write"):
        run_folder.export_start(full_run, str(blocker / "results"))
    run_folder.export_start(full_run, str(results / "tiny"))
    start = results / "tiny" / "start"
    assert sorted(os.path.relpath(os.path.join(top, n), start) for top, _, names in os.walk(start) for n in names) \
        == sorted(["config.json", "data/D0.npz", "checkpoints/bc.pt", "checkpoints/bc_continued.pt", "eval/bc.json",
                   "eval/bc_unseen.json", "eval/pi0.json"])  # no lineage's file, no partial checkpoint, no timing
    pi0 = run_folder.weights_sha256(os.path.join(full_run, "checkpoints", "bc.pt"))

    root = str(tmp_path / "elsewhere")
    cli.main(["--profile", "tiny", "--prepare", "--out", root])
    assert trained_stages == []  # D0, pi_0 and the BC row came from the start: nothing trained
    assert run_folder.weights_sha256(os.path.join(root, "checkpoints", "bc.pt")) == pi0
    assert f"stage files from {start}" in open(os.path.join(root, "log.txt")).read()
    args, _ = cli.parse_args(["--profile", "tiny", "--lineage", "0", "--out", root])
    assert args.copy_from is None  # the start is in: a resumed lineage copies nothing again

    other = str(tmp_path / "seed1")
    args, _ = cli.parse_args(["--profile", "tiny", "--seed", "1", "--out", other])
    assert args.copy_from is None and "seed = 0 there, 1 now" in capsys.readouterr().out
    own = str(tmp_path / "own")
    os.makedirs(os.path.join(own, "checkpoints"))
    torch.save({"state_dict": {"w": torch.zeros(2)}}, os.path.join(own, "checkpoints", "bc.pt"))
    args, _ = cli.parse_args(["--profile", "tiny", "--out", own])
    assert args.copy_from is None and "has a pi_0 of its own" in capsys.readouterr().out
    args, _ = cli.parse_args(["--profile", "tiny", "--out", str(tmp_path / "new")])
    assert args.copy_from == str(start)


def test_collection_skips_only_the_scenarios_the_policy_always_solves(monkeypatch):
    """HG-DAgger collects on every evaluation scenario the policy does not ALWAYS solve (benchmarks/SETUP.md §4):
    with 3 repeats, a scenario solved 3 of 3 times is skipped, one solved 2, 1 or 0 times is rolled out (once each,
    in the evaluation's order), and the episodes with an intervention are kept. Fails if the skip rule is another
    one: skip when solved at least once, by a majority or by its first or last repeat, collect on every scenario, or
    read the success table along the wrong axis; or if the log's counts (skipped; solved alone, with the expert's
    help, failed; kept; expert steps) or its seconds are wrong."""
    import re
    cfg = replace(TINY, eval_scenarios=6, eval_repeats=3)
    policy_success = np.array([[1, 1, 1],   # always solved: skipped
                               [1, 1, 0],   # 2 of 3 (its first repeat solved, its last not)
                               [0, 1, 1],   # 2 of 3 (its last repeat solved, its first not)
                               [1, 0, 1],   # 2 of 3
                               [0, 0, 0],   # never
                               [1, 1, 1]],  # always solved: skipped
                              bool)
    # the four episodes' (success, interventions, expert steps): two solved alone, one with help, one failed
    outcomes = [(True, 0, 0), (True, 0, 0), (True, 2, 30), (False, 1, 25)]
    rolled_out = []

    def fake_rollout(env_list, policy, n_act, gen, oracle=None, log=None, seed=0):
        rolled_out.extend(int(env.seed) for env in env_list)  # the scenarios the collection was reset to
        return [{"obs": np.zeros((40, 4), np.float32), "q": np.zeros((40, 2)), "action": np.zeros((40, 2)),
                 "expert": np.arange(40) >= 40 - steps, "seed": int(env.seed), "success": ok, "interventions": n}
                for env, (ok, n, steps) in zip(env_list, outcomes)]
    monkeypatch.setattr(dagger, "rollout", fake_rollout)
    lines = []
    kept = dagger.collect_interventions(cfg, (0, 1), type("Stub", (), {"device": "cpu"})(), policy_success,
                                        log=lines.append)
    seeds = envs.eval_seeds()[:cfg.eval_scenarios]
    assert rolled_out == [seeds[i] for i in (1, 2, 3, 4)]
    assert [ep["seed"] for ep in kept] == rolled_out[2:]            # the two with an intervention of >= H steps
    assert "4 of 6 (2 skipped)" in lines[0]
    counts = re.search(r"4 episodes: (\d+) solved by the policy alone, (\d+) solved with the expert's help, (\d+) "
                       r"failed; (\d+) kept with interventions, (\d+) expert steps, (\d+) s", lines[1])
    assert counts and tuple(map(int, counts.groups()[:5])) == (2, 1, 1, 2, 55) and int(counts.group(6)) < 60


def test_no_spread_is_explained_once_however_many_tests_it_concerns():
    """When every lineage differs by the same amount, each paired test says "no spread" and the reason (t and p are
    undefined) is given once under the tables, not beside every test (a smoke report had it about 15 times). Fails
    if the reason is repeated per test, dropped, or printed for a table whose every test has a spread."""
    cfg = dagger.Config(name="t", rounds=2, lineages=2, methods=("bc", "hg_dagger", "fixed_4", "pooled"))
    same = {"0": [60.0, 62.0], "1": [61.0, 63.0]}
    results = {"bc": {"all": [50.0]}, "hg_dagger": same, "fixed_4": same, "pooled": same}
    table, stats = report.summarize(cfg, results)
    text = report.format_table(cfg, table, stats, (table, stats))
    words = "\n".join(report.paired_words(stats))
    assert text.count("no spread") >= 10 and words.count("no spread") == 3
    assert text.count(report.NO_SPREAD) == 1 and "t and p are undefined" not in words
    assert text.count("undefined") == 1
    fixed, pooled = {"0": [60.0, 62.0], "1": [65.0, 61.0]}, {"0": [61.0, 60.0], "1": [63.0, 66.0]}  # every test spread
    results = {"bc": {"all": [50.0]}, "hg_dagger": same, "fixed_4": fixed, "pooled": pooled}
    text = report.format_table(cfg, *report.summarize(cfg, results))
    assert "no spread" not in text and report.NO_SPREAD not in text
