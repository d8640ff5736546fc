"""What the noised rows' labels change at σ = 0: the relabelled chunk beside the recorded chunk it replaces.

At σ = 0 a noised row differs from HG-DAgger only in its intervention rows' labels and velocities: the state is the
recorded one, the label is a return chunk instead of the expert's recorded chunk. This tool makes that label once at
every labelable step of a set of episodes, the way the noised rows' sampler makes a pair with Σ = 0 (its table of
steps; `perturb_states` with zero factors, which keeps the recorded state and drops it where it is in collision; the
velocity q_t - q_{t-1} plus `velocity_noise_std` noise; `monotone_projection`; the sampler's `return_chunks`; and its
rejections: a state projecting within `near_end_steps` of its segment's end, a label with no step in the loss, for
the servo fewer than `min_moving_steps`), and measures at each chunk step k the distance ‖label_k − recorded_k‖₂ over
the joints, in median steps m (`DemoStats.median_step`: D0's per-joint median step of the run, the unit of the noise
levels). The recorded chunk is HG-DAgger's label (`diffusion.chunk_dataset`: action[t .. t+H-1], the last action
repeated past the episode's end).

Rows: the label (PD: relabel.AugmentationSampler, `pd_return_chunk`, the paper's Sec. IV-E and every profile's label;
servo: experiment/servo.py's ServoSampler, the authors' servo with its knobs in their units) and the velocity noise
(on: the run's RelabelConfig; off: velocity_noise = 0). Columns: rows kept of the labelable steps; masked, the share
of the kept rows' chunk steps out of the loss (the servo's held tail; the PD masks none); the distance's mean,
median and 90th percentile over the steps in the loss (a masked step teaches nothing). Both labels of one velocity
setting see the same draws.

Usage:
  python benchmarks/relabel_diagnostic.py [--demos 20] [--figure PATH]   # oracle demonstrations, every step
  python benchmarks/relabel_diagnostic.py --episodes RUN/lineage_L/round_K/D.npz [--d0 RUN/data/D0.npz] [--figure PATH]
  python benchmarks/relabel_diagnostic.py --collect-table1-strong L --episodes PATH.npz [--figure PATH]
      # first writes the D_1 that lineage L of table1_strong collects from its committed start (~1 min of a core)

A run's episodes are labelled with its D0's statistics (DemoStats: median step, clamps) and its horizon
(RUN/config.json), as the run labels them; oracle demonstrations with their own statistics and --horizon.
Seconds on a laptop core for 20 demonstrations (planning them ~8 s).
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
import diffusion  # noqa: E402
import envs  # noqa: E402
import relabel  # noqa: E402
from experiment import environments, profiles, servo  # noqa: E402

# each label's sampler and its config: the core's (the paper's PD) and the variant's (the authors' servo)
SAMPLERS = {"pd": (relabel.AugmentationSampler, relabel.RelabelConfig),
            "servo": (servo.ServoSampler, servo.ServoConfig)}
LABELS = tuple(SAMPLERS)
LABEL_NAMES = {"pd": "PD (Sec. IV-E, the default)", "servo": "the authors' servo (experiment/servo.py)"}
START = os.path.join(HERE, "results", "table1_strong", "start")  # the committed D0, pi_0 and its evaluation


@dataclass
class Relabelled:
    """Every labelable step of a set of episodes, relabelled as a noised row at σ = 0 labels it."""
    label: str  # 'pd' or 'servo'
    velocity_noise: float  # RelabelConfig.velocity_noise used (0: off)
    recorded: np.ndarray  # (N, H, dof) float32: HG-DAgger's chunk of each step
    chunks: np.ndarray  # (N, H, dof) float32: the relabelled chunk (as the sampler hands it to training)
    mask: np.ndarray  # (N, H) bool: True = the step is in the loss
    kept: np.ndarray  # (N,) bool: the sampler keeps the row (free state, not near the end, enough steps in the loss)
    # (N,) bool: t + H >= the segment's end: the recorded chunk's last targets lie past the segment's last recorded
    # state (the target the expert handed back at, or the episode's last one repeated), where the label holds
    reaches_end: np.ndarray
    median_step: float  # rad: m, the unit of the distances


def relabel_every_step(episodes, make_env, stats, label, horizon, velocity_noise=None, seed=0):
    """Relabelled: the chunk `label` ('pd' or 'servo', SAMPLERS) makes at every labelable step of `episodes` (σ = 0),
    beside the recorded one. stats: relabel.DemoStats (the run's D0's); velocity_noise: RelabelConfig's (None: the
    run's default)."""
    make_sampler, make_config = SAMPLERS[label]
    cfg = make_config(horizon=horizon, **({} if velocity_noise is None else {"velocity_noise": velocity_noise}))
    rng = np.random.default_rng(seed)
    table = make_sampler(episodes, make_env, stats, "isotropic", 0.0, cfg)  # its table of steps and its labels
    _, recorded = diffusion.chunk_dataset(episodes, cfg.horizon)  # (N, H, dof): the same steps, in the same order
    if len(recorded) != len(table.center):
        raise ValueError(f"{len(recorded)} recorded chunks for {len(table.center)} labelable steps")
    q_tilde, free = np.empty_like(table.center), np.zeros(len(table.center), bool)
    limits = None
    for scenario in np.unique(table.seeds):  # q̃ = q_t + 0 z, dropped where in collision (one env per scenario)
        env = make_env()
        env.reset(seed=int(scenario))
        limits = env.joint_limits
        rows = table.seeds == scenario
        q_tilde[rows], free[rows] = relabel.perturb_states(table.center[rows], table.factors[rows], rng, env,
                                                           cfg.max_tries)
    v = table.velocity + relabel.velocity_noise_std(cfg, stats) * rng.standard_normal(q_tilde.shape)  # (N, dof)
    t_proj = relabel.monotone_projection(q_tilde, table.trajectory, table.t_glob, window=cfg.projection_window,
                                         t_end=table.end_glob)
    chunks, mask = table.return_chunks(np.arange(len(q_tilde)), q_tilde, v, t_proj, limits)
    kept = free & (t_proj < table.end_glob - cfg.near_end_steps) & mask.any(axis=1)  # the sampler's redraws
    reaches_end = table.t_glob + cfg.horizon >= table.end_glob
    return Relabelled(label, cfg.velocity_noise, recorded, chunks.astype(np.float32), mask, kept, reaches_end,
                      stats.median_step)


def label_distances(result):
    """(N, H): ‖label_k − recorded_k‖₂ over the joints at every chunk step, in median steps."""
    gap = result.chunks.astype(np.float64) - result.recorded.astype(np.float64)  # (N, H, dof) rad
    return np.linalg.norm(gap, axis=-1) / result.median_step


def summary(result, rows=None):
    """{'rows', 'kept', 'masked', 'mean', 'median', 'p90'}: the labelable steps, the share the sampler keeps, the
    share of the kept rows' chunk steps out of the loss, and the distance over the kept rows' steps in the loss.
    rows: (N,) bool, only these rows (default: all)."""
    rows = np.ones(len(result.kept), bool) if rows is None else np.asarray(rows, bool)
    kept = result.kept & rows
    in_loss = result.mask[kept]  # (kept, H)
    d = label_distances(result)[kept][in_loss]
    empty = float("nan")
    return {"rows": int(rows.sum()), "kept": float(kept.sum() / rows.sum()) if rows.any() else empty,
            "masked": float(1.0 - in_loss.mean()) if in_loss.size else empty,
            "mean": float(d.mean()) if d.size else empty, "median": float(np.median(d)) if d.size else empty,
            "p90": float(np.percentile(d, 90)) if d.size else empty}


def per_chunk_step(result):
    """(mean (H,), p90 (H,)): the distance at each chunk step over the kept rows where that step is in the loss."""
    d, m = label_distances(result)[result.kept], result.mask[result.kept]
    mean = np.array([d[m[:, k], k].mean() if m[:, k].any() else np.nan for k in range(d.shape[1])])
    p90 = np.array([np.percentile(d[m[:, k], k], 90) if m[:, k].any() else np.nan for k in range(d.shape[1])])
    return mean, p90


def diagnose(episodes, make_env, stats, horizon, seed=0):
    """[Relabelled] for the PD and the authors' servo, velocity noise on (the run's RelabelConfig) and off."""
    return [relabel_every_step(episodes, make_env, stats, label, horizon, noise, seed)
            for label in LABELS for noise in (relabel.RelabelConfig.velocity_noise, 0.0)]


def table(results):
    """Markdown lines: a row per label and velocity noise."""
    lines = ["| label | velocity noise | rows kept | masked | mean | median | p90 |", "|---|---|---|---|---|---|---|"]
    for r in results:
        s = summary(r)
        noise = f"on ({r.velocity_noise:g}, the run's)" if r.velocity_noise else "off"
        lines.append(f"| {LABEL_NAMES[r.label]} | {noise} | {s['kept']:.1%} of {s['rows']} | {s['masked']:.1%} | "
                     f"{s['mean']:.2f} | {s['median']:.2f} | {s['p90']:.2f} |")
    return lines


def end_split(results):
    """Markdown lines: the same distances apart for the kept rows whose chunk stays inside its segment and those
    whose chunk runs to the segment's end (where the recorded chunk's last targets lie past the segment's last state)."""
    lines = ["| label | velocity noise | chunk inside its segment: rows, mean / median / p90 | chunk to the segment's "
             "end: rows, mean / median / p90 |", "|---|---|---|---|"]
    for r in results:
        cells = []
        for rows in (~r.reaches_end, r.reaches_end):
            s = summary(r, rows)
            cells.append(f"{int((r.kept & rows).sum())}, {s['mean']:.2f} / {s['median']:.2f} / {s['p90']:.2f}")
        noise = "on" if r.velocity_noise else "off"
        lines.append(f"| {LABEL_NAMES[r.label]} | {noise} | {cells[0]} | {cells[1]} |")
    return lines


def figure(results, path, title):
    """The distance at each chunk step, both labels, velocity noise on (solid) and off (dashed): the mean and the
    90th percentile over the kept rows' steps in the loss. Writes a PNG to `path`."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharex=True)
    colors = {"pd": "tab:blue", "servo": "tab:red"}
    for r in results:
        mean, p90 = per_chunk_step(r)
        k = np.arange(1, len(mean) + 1)
        style = "-" if r.velocity_noise else "--"
        label = f"{LABEL_NAMES[r.label]}, velocity noise {'on' if r.velocity_noise else 'off'}"
        axes[0].plot(k, mean, style, color=colors[r.label], marker="o", ms=3, label=label)
        axes[1].plot(k, p90, style, color=colors[r.label], marker="o", ms=3, label=label)
    for ax, what in zip(axes, ("mean", "90th percentile")):
        ax.set_xlabel("chunk step k (env steps after the state)")
        ax.set_ylabel(f"{what}, median steps m")
        ax.set_title(f"‖relabelled − recorded‖₂ at chunk step k: {what}", fontsize=9)
        ax.set_xticks(np.arange(1, results[0].chunks.shape[1] + 1, 2 if results[0].chunks.shape[1] > 12 else 1))
        ax.axhline(0, color="k", lw=0.5)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# ---- the episodes: oracle demonstrations, a run's D_k, or table1_strong's D_1 collected from its committed start --
def oracle_demonstrations(env_name, n, first_seed=0, log=print):
    """n oracle demonstrations on training scenarios first_seed, first_seed + 1, ... (unplannable ones skipped)."""
    import oracle
    env, expert, demos, seed = environments.make_env(env_name), oracle.Oracle(), [], first_seed
    while len(demos) < n:
        try:
            demos.append(expert.demonstrate(env, envs.train_seeds(1, start=seed)[0]))
        except oracle.PlanningFailed:
            log(f"  training scenario {seed}: no plan, skipped")
        seed += 1
    return demos


def run_statistics(env_name, demos):
    """relabel.DemoStats of D0 as the run makes them (dagger.demo_statistics)."""
    import dagger
    return dagger.demo_statistics(SimpleNamespace(env=env_name), demos, environments.make_env)


def run_folder_of(episodes_path):
    """RUN for RUN/lineage_L/round_K/D.npz (the run folder's layout), else None."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(episodes_path))))
    return root if os.path.isfile(os.path.join(root, "config.json")) else None


def collect_table1_strong(lineage, path, log=print):
    """Write to `path` the D_1 that lineage `lineage` of the table1_strong profile collects from the committed start
    (pi_0 and its evaluation on the 100 collected scenarios; the lineage's own collection seeds), as the run does."""
    import dagger
    from experiment import run_folder
    cfg = profiles.PROFILES["table1_strong"]
    pi0 = run_folder.load_policy(os.path.join(START, "checkpoints", "bc.pt"), cfg.device)
    success = run_folder.read_json(os.path.join(START, "eval", "pi0.json"))["success"]
    episodes = dagger.collect_interventions(cfg, (lineage, 1), pi0, success, log=log)
    run_folder.save_episodes(path, episodes)
    return episodes


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", help="a run's D_k (.npz as the run folder writes it); default: oracle demonstrations")
    p.add_argument("--d0", help="the D0 whose statistics label the episodes (default: RUN/data/D0.npz of --episodes)")
    p.add_argument("--demos", type=int, default=20, help="oracle demonstrations when no --episodes (default 20)")
    p.add_argument("--horizon", type=int, default=None, help="H (default: the run's config.json, else 20)")
    p.add_argument("--env", default=None, help="environment (default: the run's, else planar)")
    p.add_argument("--collect-table1-strong", type=int, metavar="L", default=None,
                   help="first collect lineage L's D_1 of table1_strong from its committed start into --episodes")
    p.add_argument("--seed", type=int, default=0, help="the velocity noise's draws")
    p.add_argument("--figure", help="write the per-chunk-step figure to this PNG")
    args = p.parse_args(argv)
    t0 = time.time()
    run = run_folder_of(args.episodes) if args.episodes else None
    config = json.load(open(os.path.join(run, "config.json"))) if run else {}
    if args.collect_table1_strong is not None:
        if not args.episodes:
            p.error("--collect-table1-strong needs --episodes PATH.npz to write the D_1 to")
        config = json.load(open(os.path.join(START, "config.json")))
        print(f"collecting lineage {args.collect_table1_strong}'s D_1 of table1_strong from {os.path.relpath(START)}")
        collect_table1_strong(args.collect_table1_strong, args.episodes)
        args.d0 = args.d0 or os.path.join(START, "data", "D0.npz")
    env_name = args.env or config.get("env", "planar")
    horizon = args.horizon or config.get("horizon", 20)
    if args.episodes:
        from experiment.run_folder import load_episodes
        d0_path = args.d0 or (os.path.join(run, "data", "D0.npz") if run else None)
        if d0_path is None:
            p.error(f"{args.episodes} is not in a run folder (RUN/lineage_L/round_K/D.npz): name its D0 with --d0")
        episodes, d0 = load_episodes(args.episodes), load_episodes(d0_path)
        what = (f"{len(episodes)} episodes of {args.episodes} ({sum(int(e['expert'].sum()) for e in episodes)} "
                f"expert steps), labelled with the statistics of {d0_path} ({len(d0)} demonstrations)")
    else:
        print(f"planning {args.demos} oracle demonstrations on training scenarios ...")
        episodes = d0 = oracle_demonstrations(env_name, args.demos)
        what = (f"{len(episodes)} oracle demonstrations on training scenarios {episodes[0]['seed']}.."
                f"{episodes[-1]['seed']}, every step an intervention, labelled with their own statistics")
    stats = run_statistics(env_name, d0)
    results = diagnose(episodes, functools.partial(environments.make_env, env_name), stats, horizon, args.seed)
    paper = environments.paper_median_step(env_name)
    unit = (f"median step m = {stats.median_step:.4f} rad" + (f" = {stats.median_step / paper:.2f} of the paper's "
                                                                f"median step ({paper} rad)" if paper else ""))
    print(f"{what}; σ = 0, H = {horizon}; distance per chunk step ‖relabelled − recorded‖₂ in {unit}; "
          f"velocity noise draws of seed {args.seed}\n")
    print("\n".join(table(results)))
    print("\nThe same, apart by where the chunk ends:\n")
    print("\n".join(end_split(results)))
    if args.figure:
        title = (f"Relabelled vs recorded chunk at σ = 0, H = {horizon}: "
                 + (args.episodes if args.episodes else f"{len(episodes)} oracle demonstrations"))
        print(f"\nwrote {figure(results, args.figure, title)}")
    print(f"({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
