"""The command line of `python dagger.py`: profiles, overrides, the run folder's name, and the modes.

Modes: the whole run (default); --prepare (the shared stages: D0, BC and its evaluation, the BC row; copied from
benchmarks/results/<profile>/start/ where the repository holds them for this config, as every mode does);
--lineage i (one lineage, e.g. one task of a cluster job array); --report (merge finished lineages into
the table and figures); --join / --export-lineages (a lineage's results as one file, to merge elsewhere).
`python dagger.py` hands over to main here.
"""
from __future__ import annotations

import argparse
import os
import _thread
import sys
import threading
from dataclasses import replace

import torch

from experiment.environments import ENVIRONMENTS
from experiment.profiles import ALL_METHODS, PROFILES, RECIPES, check_config
from experiment.report import run_experiment
from experiment.run_folder import PI0_THREADS, ConfigMismatch, RunFolderError, committed_start, export_start

SMOKE_TIME = "about 1 min on 2 idle cores"  # measured: benchmarks/README.md, 'What each profile costs' (the same words there and in README)


def parse_args(argv):
    """(args, cfg): the profile's config with the command line's overrides (checked: check_config) and a
    run-folder name that says what differs from the profile."""
    profiles, methods, recipes = PROFILES, ALL_METHODS, RECIPES
    p = argparse.ArgumentParser(
        prog="dagger.py",
        description="Policy-Calibrated DAgger end to end (Wang & Kantor): data, BC, HG-DAgger rounds, "
                    "calibration, augmentation, every method of Table I, evaluation, table and figures.")
    p.add_argument("--profile", default="quick", choices=sorted(profiles),
                   help="run size (README, 'Profiles and options'): smoke (every stage at tiny sizes, CI's run; "
                        f"{SMOKE_TIME}), quick (the default: the whole loop, one lineage, one round, four rows; about "
                        "5-10 min on a 2-core laptop CPU), mid (Table I's analogue for 2 cores: 500 demos, 5 lineages "
                        "x 2 rounds, the fixed sweep and pooled; hours), table1 (all of Table I: 5 lineages x 5 rounds, "
                        "ten rows; run a lineage at a time), table1_strong (table1 with 3x the gradient steps, one "
                        "round, seven rows: the studies' profile), table2 (the engine-lever env with Table II's rows), "
                        "paper (Table I's protocol at the authors' sizes: a GPU or a cluster)")
    p.add_argument("--env", default=None, choices=sorted(ENVIRONMENTS),
                   help="environment (default planar): planar, engine3d, or a research variant's: engine3d_image "
                        "(experiment/image_obs.py: the UR5 policy sees a camera image through a small CNN instead of "
                        "the obstacle list), engine3d_oriented (experiment/oriented_goal.py: success also needs the "
                        "tool's orientation within the authors' 10 degrees)")
    p.add_argument("--methods", default=None,
                   help=f"comma-separated subset of: {', '.join(methods)} (BC and HG-DAgger always run)")
    p.add_argument("--recipe", default=None, choices=sorted(recipes),
                   help="how pi_0 and every arm train: paper (the authors' planar runs: every arm continues pi_0's "
                        "optimizer along one cosine), or a research variant's, e.g. authors_lever (experiment/lever.py: "
                        "their lever runs' constant lr, padded short interventions, frame shares; authors_lever_seeds: "
                        "training seeds on lineage 0's interventions); default: the profile's")
    p.add_argument("--rounds", type=int, default=None, help="HG-DAgger rounds K")
    p.add_argument("--lineages", type=int, default=None, help="number of lineages")
    p.add_argument("--lineage", type=int, default=None,
                   help="run only this lineage (0-based), e.g. as one task of a cluster job array")
    p.add_argument("--prepare", action="store_true", help="only the shared stages: D0, BC and its evaluation")
    p.add_argument("--seed", type=int, default=None, help="master seed")
    p.add_argument("--device", default=None, help="torch device: cpu (default) or cuda")
    p.add_argument("--out", default=None, help="run folder (default runs/<profile>[_<env>])")
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads of this process's stages (default 1: the networks are small, and more "
                        "threads than free cores slow torch down many times on a shared machine; pi_0's training, "
                        f"which runs alone, always takes {PI0_THREADS})")
    p.add_argument("--workers", type=int, default=None,
                   help="processes for the arms of a round (and the BC row beside the rounds; never more than a "
                        "round has arms); default: the cores this process may use (taskset, a cgroup's cpuset), "
                        "1 with --lineage (lineages side by side use the cores)")
    p.add_argument("--report", action="store_true", help="merge finished lineages into the table and figures")
    p.add_argument("--join", nargs="+", default=(), metavar="FILE",
                   help="lineage results files (written by --export-lineages, e.g. benchmarks/results/<profile>/"
                        "lineage_<l>.json.gz) to unpack into the run folder first, so --report merges them; refused "
                        "if made with another config or pi_0")
    p.add_argument("--export-lineages", default=None, metavar="FOLDER",
                   help="after the mode, write FOLDER/lineage_<l>.json.gz: each lineage's results (evaluations, "
                        "calibrations, timings; no checkpoints), for --join in another folder or a commit")
    p.add_argument("--copy-from", default=None, metavar="FOLDER",
                   help="first copy in the finished stages of FOLDER, a run of the same config with fewer methods "
                        "(e.g. runs/table2 for --methods ...,zero_noise), so only the added methods train; from "
                        "--recipe authors_lever to authors_lever_seeds or back, only lineage 0 (the same in both)")
    p.add_argument("--export-start", default=None, metavar="FOLDER",
                   help="after the mode, write FOLDER/start/: the run's shared stages (D0, pi_0 with its optimizer "
                        "state, the BC row, their evaluations). A run of the profile copies "
                        "benchmarks/results/<profile>/start/ into a new folder of the same config first (committed "
                        "for table1), so lineages run anywhere continue from one pi_0 and join")
    p.add_argument("--no-eval-unseen", action="store_true",
                   help="skip the second evaluation of every policy on the unseen scenarios (never trained on)")
    args = p.parse_args(argv)
    cfg = profiles[args.profile]
    over = {}
    if args.env:
        over["env"] = args.env
    if args.methods:
        over["methods"] = parse_methods(p, args.methods, methods)
    if args.recipe:
        over["recipe"] = args.recipe
    if args.no_eval_unseen:
        over["eval_unseen"] = False
    for key in ("rounds", "lineages", "seed"):
        if getattr(args, key) is not None:
            over[key] = getattr(args, key)
    if args.device:
        if args.device not in ("cpu", "cuda") and not args.device.startswith("cuda:"):
            p.error(f"--device: {args.device!r} is not valid; use cpu or cuda")
        if args.device.startswith("cuda") and not torch.cuda.is_available():
            p.error(f"--device {args.device}: no CUDA device is available here; use --device cpu")
        over["device"] = args.device
    over["name"] = folder_name(cfg, over)
    try:
        cfg = check_config(replace(cfg, **over))
    except ValueError as err:
        p.error(str(err))
    if args.threads < 1:
        p.error(f"--threads {args.threads}: must be >= 1")
    if args.workers is None:
        args.workers = 1 if args.lineage is not None else usable_cores()
    if args.workers < 1:
        p.error(f"--workers {args.workers}: must be >= 1")
    if args.lineage is not None and not 0 <= args.lineage < cfg.lineages:
        p.error(f"--lineage {args.lineage}: valid lineages are 0..{cfg.lineages - 1}")
    args.out = args.out or os.path.join("runs", cfg.name)
    if args.copy_from is None and not args.report:  # the profile's committed shared stages, where they fit this run
        args.copy_from = committed_start(args.profile, cfg, args.out)
    return args, cfg


def parse_methods(parser, text, methods):
    """--methods 'a,b,c' as a tuple of distinct names (a clear error otherwise)."""
    names = [m.strip() for m in text.split(",")]
    if not all(names):
        parser.error(f"--methods {text!r}: an empty item; give comma-separated names, e.g. "
                     f"hg_dagger,fixed_4,pooled (valid: {', '.join(methods)})")
    dup = sorted({m for m in names if names.count(m) > 1})
    if dup:
        parser.error(f"--methods {text!r}: {', '.join(dup)} listed twice; name each method once")
    return tuple(names)  # an unknown name: check_config says which


def folder_name(cfg, over):
    """The run folder's name: the profile's, plus whatever the command line changed that changes results
    (another env, recipe, set of methods)."""
    env, recipe = over.get("env", cfg.env), over.get("recipe", cfg.recipe)
    name = cfg.name + ("" if env == cfg.env else f"_{env}")  # another env than the profile's: own folder
    name += "" if recipe == cfg.recipe else f"_{recipe}"
    if "methods" in over and set(over["methods"]) | {"bc", "hg_dagger"} != set(cfg.methods):
        name += "_" + "-".join(over["methods"])  # another set of methods gets its own folder
    return name


def main(argv=None):
    """`python dagger.py`: the command's mode on its run folder (report.run_experiment runs dagger's loop), then
    --export-start's files. Returns the run folder."""
    args, cfg = parse_args(sys.argv[1:] if argv is None else argv)
    torch.set_num_threads(args.threads)
    root = run_command(run_experiment, cfg, args.out, args.lineage, args.prepare, args.report, args.workers,
                       args.join, args.export_lineages, args.copy_from)
    for path in run_command(export_start, root, args.export_start) if args.export_start else []:
        print(f"wrote {path}")
    return root


def run_command(fn, *args):
    """fn(*args), with a stop (Ctrl-C) or a run-folder problem said in one line and an exit status instead
    of a traceback."""
    default_hook, sys.unraisablehook = sys.unraisablehook, _interrupt_again(sys.unraisablehook)
    try:
        return fn(*args)
    except KeyboardInterrupt:
        print("\nstopped; the finished stages are saved: run the same command again to resume", file=sys.stderr)
        sys.exit(130)
    except (ConfigMismatch, RunFolderError) as err:
        print(f"dagger.py: {err}", file=sys.stderr)
        sys.exit(2)
    finally:
        sys.unraisablehook = default_hook


def _interrupt_again(default_hook):
    """An unraisable-exception hook that does not lose a Ctrl-C: one landing in a finalizer (pymunk frees its
    bodies in callbacks, which the garbage collector runs at any time) is ignored there by Python, so it asks for
    the interrupt again 10 ms later, from a timer thread once this hook has returned (one landing in a finalizer
    again asks again); any other goes to default_hook."""
    def hook(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            timer = threading.Timer(0.01, _thread.interrupt_main)
            timer.daemon = True
            timer.start()
        else:
            default_hook(unraisable)
    return hook


def usable_cores():
    """The CPU cores this process may run on (taskset / a cgroup's cpuset narrow them), else the machine's."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no sched_getaffinity (macOS, Windows)
        return os.cpu_count() or 1


if __name__ == "__main__":  # `python dagger.py` (or python -m experiment.cli)
    main()
