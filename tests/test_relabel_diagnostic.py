"""benchmarks/relabel_diagnostic.py: the relabelled chunk at σ = 0 beside the recorded chunk it replaces. The distance
is the joints' L2 in median steps; only kept rows' steps in the loss count; the masked share is of the kept rows'
chunk steps; the PD returns the recorded chunk exactly where nothing is to correct; the rows are the ones the
noised rows' sampler trains on."""
import dataclasses
import os
import sys

import numpy as np
import pytest

import envs
import relabel
from helpers import straight_line_episode

H = 8  # a short chunk: the tests' episodes are 20-40 steps


@pytest.fixture(scope="module")
def rd():
    import importlib.util
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks",
                        "relabel_diagnostic.py")
    spec = importlib.util.spec_from_file_location("relabel_diagnostic", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["relabel_diagnostic"] = module  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def episodes():
    """Stand-in interventions (smoothstep lines that end at rest, the expert from step 5 to the episode's end)."""
    env = envs.make_env("planar")
    return [straight_line_episode(env, seed) for seed in (0, 1, 2, 3)]


@pytest.fixture(scope="module")
def stats(episodes):
    """The episodes' statistics as a run makes them, the PD's clamp above every acceleration of these paths (the
    99th percentile would clamp the top 1 % of their own steps)."""
    env = envs.make_env("planar")
    base = relabel.demo_stats(episodes, envs.median_step(episodes), env.max_step,
                              paper_median_step=env.paper_median_step,
                              frames_per_step=env.dt / envs.PAPER_FRAME_DT)
    steepest = max(np.abs(np.diff(ep["q"], 2, axis=0)).max() for ep in episodes)
    return dataclasses.replace(base, accel_max=np.full(3, 2.0 * steepest))


def make_env():
    return envs.make_env("planar")


def hand_made(rd, recorded, chunks, mask, kept, median_step=0.5, reaches_end=None):
    """A Relabelled of given arrays (no labelling)."""
    recorded, chunks = np.asarray(recorded, np.float32), np.asarray(chunks, np.float32)
    reaches_end = np.zeros(len(kept), bool) if reaches_end is None else np.asarray(reaches_end, bool)
    return rd.Relabelled("servo", 0.0, recorded, chunks, np.asarray(mask, bool), np.asarray(kept, bool),
                         reaches_end, median_step)


def test_distance_is_the_joints_l2_in_median_steps(rd):
    """(3m, 4m, 0) apart is 5 median steps, (0, 0, -2m) is 2 (a max or L1 norm gives 4 / 7, radians 2.5, a missing
    square root 25): the unit of the table."""
    m = 0.5
    recorded = np.zeros((1, 2, 3))
    chunks = np.array([[[3 * m, 4 * m, 0.0], [0.0, 0.0, -2 * m]]]) + recorded
    r = hand_made(rd, recorded + 1.0, chunks + 1.0, np.ones((1, 2)), [True], median_step=m)
    assert rd.label_distances(r) == pytest.approx(np.array([[5.0, 2.0]]))


def test_summary_counts_the_kept_rows_steps_in_the_loss(rd):
    """Row 0 kept with its last step masked (and 50 m off there), row 1 kept, row 2 dropped (100 m off): the masked
    share is 1 of the 8 kept steps (not 5 of 12 over every row, nor the 7 / 8 in the loss); the distances are the
    7 kept steps in the loss."""
    recorded = np.zeros((3, 4, 3))
    gap = np.zeros((3, 4))
    gap[0] = [1, 2, 3, 50]
    gap[1] = [0, 0, 4, 6]
    gap[2] = 100
    chunks = recorded.copy()
    chunks[..., 0] = gap  # median step 1: the gap is the distance
    mask = np.ones((3, 4), bool)
    mask[0, 3] = False
    mask[2] = False
    r = hand_made(rd, recorded, chunks, mask, [True, True, False], median_step=1.0)
    s = rd.summary(r)
    in_loss = np.array([1, 2, 3, 0, 0, 4, 6], float)
    assert s["rows"] == 3 and s["kept"] == pytest.approx(2 / 3)
    assert s["masked"] == pytest.approx(1 / 8)
    assert s["mean"] == pytest.approx(in_loss.mean())
    assert s["median"] == pytest.approx(np.median(in_loss))
    assert s["p90"] == pytest.approx(np.percentile(in_loss, 90))
    only_row_1 = rd.summary(r, rows=[False, True, True])
    assert only_row_1["rows"] == 2 and only_row_1["kept"] == pytest.approx(0.5)
    assert only_row_1["masked"] == 0.0 and only_row_1["mean"] == pytest.approx(2.5)


def test_per_chunk_step_leaves_out_masked_steps_and_dropped_rows(rd):
    """The figure's curves: at each chunk step the mean (and 90th percentile) over kept rows where it is in the
    loss; a step no kept row has in the loss is NaN, not 0."""
    recorded = np.zeros((3, 3, 3))
    chunks = recorded.copy()
    chunks[:, :, 1] = [[1, 2, 9], [3, 4, 9], [70, 80, 90]]
    mask = np.array([[1, 1, 0], [1, 0, 0], [1, 1, 1]], bool)
    r = hand_made(rd, recorded, chunks, mask, [True, True, False], median_step=1.0)
    mean, p90 = rd.per_chunk_step(r)
    assert mean[:2] == pytest.approx([2.0, 2.0]) and np.isnan(mean[2])
    assert p90[:2] == pytest.approx([np.percentile([1, 3], 90), 2.0]) and np.isnan(p90[2])


def test_pd_without_velocity_noise_returns_the_recorded_chunk(rd, episodes, stats):
    """Where nothing is to correct (σ = 0, the recorded velocity, no clamp binding) the PD label is the recorded
    chunk to float32's grain at every kept row, the padded steps past the episode's end included: a recorded chunk
    of another step (one step early or late), another unit or the velocity noise left on would not be."""
    r = rd.relabel_every_step(episodes, make_env, stats, "pd", H, velocity_noise=0.0)
    assert r.kept.sum() > 50 and r.reaches_end[r.kept].any() and (~r.reaches_end[r.kept]).any()
    assert rd.label_distances(r)[r.kept].max() < 1e-4
    s = rd.summary(r)
    assert s["mean"] < 1e-5 and s["p90"] < 1e-5 and s["masked"] == 0.0
    noisy = rd.relabel_every_step(episodes, make_env, stats, "pd", H)
    assert rd.summary(noisy)["mean"] > 0.05  # the velocity noise moves the label: the test above could fail


def test_the_velocity_noise_has_the_runs_spread(rd, episodes, stats):
    """Velocity noise on: the PD's first target is the recorded one moved by (1 − Kd) times the noise (no error to
    close, clamps far), so its distance's mean square is 3 (1 − Kd)² std² / m² with std = relabel.velocity_noise_std,
    the run's (a std divided instead of multiplied, or another std, would not give it)."""
    loose = dataclasses.replace(stats, accel_max=stats.accel_max * 100)
    cfg = relabel.RelabelConfig(horizon=H)
    r = rd.relabel_every_step(episodes, make_env, loose, "pd", H)
    inside = r.kept & ~r.reaches_end
    _, kd = relabel.critically_damped_gains(cfg.settle_steps)
    std = relabel.velocity_noise_std(cfg, loose)
    first = rd.label_distances(r)[inside, 0] * loose.median_step / (1 - kd)  # ‖noise‖, rad
    assert inside.sum() > 60
    assert np.mean(first ** 2) == pytest.approx(3 * std ** 2, rel=0.25)


def test_pd_returns_the_recorded_chunk_at_an_episodes_first_step(rd, stats):
    """Interventions from step 0 (the expert drives from the episode's start): the PD label of every episode's first
    step returns the recorded chunk. Fails if pd_return_chunk, in the sampler's table of episodes laid end to end,
    takes the previous episode's last state for its reference r_-1 at an episode's first step (the bug the
    diagnostic found: 9 rows of table1_strong lineage 5's D_1 off by that jump)."""
    env = envs.make_env("planar")
    from_start = [straight_line_episode(env, seed, expert_from=0) for seed in (0, 1)]
    r = rd.relabel_every_step(from_start, make_env, stats, "pd", H, velocity_noise=0.0)
    assert r.kept.sum() > 20
    assert rd.label_distances(r)[r.kept].max() < 1e-4


def test_the_rows_are_what_the_noised_rows_sampler_trains_on(rd, episodes, stats):
    """At σ = 0 without velocity noise the sampler's pairs are deterministic: every pair AugmentationSampler makes
    is the chunk and mask of a row the diagnostic keeps, and no row it drops (near the segment's end, too few steps
    in the loss) is ever served -- for both labels."""
    for label in ("servo", "pd"):
        make_sampler, make_config = rd.SAMPLERS[label]
        r = rd.relabel_every_step(episodes, make_env, stats, label, H, velocity_noise=0.0)
        assert (~r.kept).sum() >= 3 * len(episodes)  # the near-end rows at least: the drop is exercised
        kept = {c.tobytes(): m for c, m in zip(r.chunks[r.kept], r.mask[r.kept])}
        dropped = {c.tobytes() for c in r.chunks[~r.kept]} - set(kept)
        sampler = make_sampler(episodes, make_env, stats, "isotropic", 0.0, make_config(H, velocity_noise=0.0))
        _, chunks, masks = sampler.generate(6 * len(r.kept), np.random.default_rng(1))
        served = {c.tobytes() for c in chunks}
        assert served <= set(kept) and not served & dropped
        assert len(served) > 0.9 * len(kept)  # nearly every kept row was drawn: a kept row too many would show
        for c, m in zip(chunks, masks):
            assert np.array_equal(kept[c.tobytes()], m)


def test_the_servo_masks_only_its_held_tail_at_the_segments_end(rd, episodes, stats):
    """The servo's masked steps are a held tail: from its first masked step to the chunk's end, every step masked
    and standing still on the segment's last point, in rows near the segment's end (its cursor, one frame ahead of
    the state, may reach the end a few steps before the recorded chunk does); an inverted mask would put them
    everywhere. The PD masks none."""
    from experiment.servo import ServoConfig, segment_geometry
    hold = ServoConfig.hold_tol * max(segment_geometry(ep["q"][5:])[0] for ep in episodes) + 1e-6  # rad a step
    pd, servo = rd.diagnose(episodes, make_env, stats, H)[1::2]  # velocity noise off
    masked_rows = (~servo.mask).any(axis=1) & servo.kept
    assert masked_rows.any() and (masked_rows & servo.reaches_end).sum() >= 0.5 * masked_rows.sum()
    for mask, chunk in zip(servo.mask[masked_rows], servo.chunks[masked_rows]):
        first = int(np.argmin(mask))
        assert mask[:first].all() and not mask[first:].any()  # a tail
        still = np.abs(np.diff(chunk[max(first - 1, 0):], axis=0)).max(initial=0.0)
        assert still < hold  # held: every joint slower than the servo's hold tolerance
    assert 0.0 < rd.summary(servo)["masked"] < 0.5 and rd.summary(pd)["masked"] == 0.0


def test_diagnose_makes_the_four_rows_of_the_table(rd, episodes, stats):
    """PD and servo, each with the run's velocity noise (RelabelConfig's) and without, in that order; the table has
    a line for each, and the split by where the chunk ends partitions the kept rows."""
    results = rd.diagnose(episodes, make_env, stats, H)
    assert [(r.label, r.velocity_noise) for r in results] == [
        ("pd", relabel.RelabelConfig.velocity_noise), ("pd", 0.0),
        ("servo", relabel.RelabelConfig.velocity_noise), ("servo", 0.0)]
    assert relabel.RelabelConfig.velocity_noise > 0
    lines = rd.table(results)
    assert len(lines) == 6 and lines[2].startswith("| PD") and "| on (0.3" in lines[2] and "| off |" in lines[3]
    assert lines[4].startswith("| the authors' servo")
    split = rd.end_split(results)
    for r, line in zip(results, split[2:]):
        inside, end = (int(cell.split(",")[0]) for cell in line.split("|")[3:5])
        assert inside + end == r.kept.sum() and end == (r.kept & r.reaches_end).sum()


def test_the_command_on_a_run_folders_episodes(rd, episodes, tmp_path, capsys):
    """--episodes RUN/lineage_L/round_K/D.npz finds the run's config (H) and D0 (the statistics) and prints the
    table and the figure's path."""
    from experiment import run_folder
    run = tmp_path / "run"
    (run / "data").mkdir(parents=True)
    (run / "lineage_0" / "round_1").mkdir(parents=True)
    (run / "config.json").write_text('{"env": "planar", "horizon": 8}')
    run_folder.save_episodes(str(run / "data" / "D0.npz"), episodes)
    run_folder.save_episodes(str(run / "lineage_0" / "round_1" / "D.npz"), episodes[:2])
    assert rd.run_folder_of(str(run / "lineage_0" / "round_1" / "D.npz")) == str(run)
    assert rd.run_folder_of(str(tmp_path / "D.npz")) is None
    figure = tmp_path / "fig.png"
    rd.main(["--episodes", str(run / "lineage_0" / "round_1" / "D.npz"), "--figure", str(figure)])
    out = capsys.readouterr().out
    assert "H = 8" in out and "statistics of" in out and "data/D0.npz (4 demonstrations)" in out
    assert out.count("| PD (Sec. IV-E, the default) |") == 4
    assert out.count("| the authors' servo (experiment/servo.py) |") == 4
    assert figure.stat().st_size > 10_000
