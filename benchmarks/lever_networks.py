"""Which epsilon network can the lever learn at CPU cost? BC success against training CPU-minutes.

Table II needs a BC policy (pi_0) on the UR5 engine lever in the paper's band (BC 58 %; we ask 45-70 %) at a
cost the 2-core machine can pay for every cell of the table. The planar recipe (residual MLP, chunk 20, batch 256,
continued) stays at 15-20 % there; the U-Net (32, 64, 128) at batch 64 reaches 49 % but needs 48 min of one core
for pi_0 and ~20 min for each fine-tuned cell (benchmarks/HISTORY.md, "The mid recipe on the lever").

Each candidate is a profile (default table2) with some dagger.Config fields changed -- the network, the chunk
(H and the steps executed), the widths, the batch, the steps, the fine-tuning mode -- run as
`python dagger.py --prepare` in its own folder OUT/<candidate>/: D0 (collected once in OUT/D0/ and copied into
every candidate's folder, so all of them learn from the same demonstrations), pi_0 and its evaluation on the
evaluation scenarios; then the table's BC row (dagger.bc_row_arm: under the paper's recipe pi_0 continued on
D0 alone for finetune_steps more, the budget every cell of the table trains; under authors_lever pi_0 itself). Every stage is a
file: a stopped benchmark resumes where it stopped.

Prints a markdown table: the candidate's fields, its parameter count, training steps per CPU-second and the
CPU-minutes of pi_0's training (one torch thread; the CPU time of TIMED_STEPS steps of a fresh policy, so other
processes on the cores do not inflate it), pi_0's and the BC row's success, success points per CPU-minute, an
evaluation's wall minutes (inflated when the cores are shared), and whether pi_0 is in the band.

Usage:  python benchmarks/lever_networks.py [--candidates mlp_h10,unet16_b256 | all] [--jobs 2]
                                            [--out runs/lever_networks] [--base table2]
"""
import argparse
import os
import shutil
import sys
import time
from dataclasses import asdict, replace

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import dagger  # noqa: E402
import diffusion  # noqa: E402
from experiment import cpu_kernels, environments, profiles, report  # noqa: E402
from experiment.run_folder import Run, read_json, timing_name, without_retired_fields, write_json  # noqa: E402
from experiment.workers import in_parallel  # noqa: E402

# dagger.Config fields each candidate changes in the base profile. The continued ones train pi_0 for bc_steps of
# one cosine of bc_steps + finetune_steps (the mid recipe, and the table2 profile's since unet16_b256 was chosen).
CONTINUED = dict(batch_size=256, lr=1e-3, bc_steps=10_000, finetune_steps=10_000, recipe="paper")
# (The earlier table2 recipe, U-Net (32, 64, 128), batch 64, BC 30k with its fine-tuning restarted -- measured:
# pi_0 49.0 %, 48 min -- is gone with finetune='restart': benchmarks/HISTORY.md keeps its numbers.)
CANDIDATES = {
    # the planar mid recipe: residual MLP 256 x 3, chunk 20, 10 executed (measured: pi_0 15.0 %, BC row 20.0 %)
    "mlp_h20": dict(network="mlp", **CONTINUED),
    # the same MLP on a chunk of 10, 5 executed: half the action numbers to learn, twice the policy calls
    "mlp_h10": dict(network="mlp", horizon=10, n_act=5, **CONTINUED),
    # the U-Net's temporal convolutions at half the widths, batch 256, continued
    "unet16_b256": dict(network="unet", down_dims=(16, 32, 64), **CONTINUED),
    # the same U-Net with pi_0 at the end of its own cosine: the pi_0 of the authors' lever fine-tuning
    # (recipe authors_lever, experiment/lever.py: every arm continues it at a constant lr / 10; the BC row is pi_0)
    "unet16_b256_constant": dict(network="unet", down_dims=(16, 32, 64), **{**CONTINUED, "recipe": "authors_lever"}),
}
DEFAULT_CANDIDATES = ("mlp_h10", "unet16_b256")  # the two new ones (measured: benchmarks/HISTORY.md, "ε-networks ...")
TIMED_STEPS = 200  # training steps timed for the CPU cost of a step
BAND = (45.0, 70.0)  # pi_0 success, %: around the paper's BC (Table II: 58.0)


def candidate_config(base, name, seed=0):
    """The dagger.Config of candidate `name`: profile `base` with the candidate's fields and its own folder name."""
    if name not in CANDIDATES:
        raise SystemExit(f"unknown candidate {name!r}; valid: {', '.join(CANDIDATES)} (or all)")
    if base not in profiles.PROFILES:
        raise SystemExit(f"unknown --base {base!r}; valid: {', '.join(profiles.PROFILES)}")
    fields = {**asdict(profiles.PROFILES[base]), **CANDIDATES[name], "name": f"{base}_{name}", "seed": seed,
              "eval_unseen": False}  # the unseen scenarios do not choose a network
    try:
        return dagger.Config(**fields)
    except ValueError as err:
        raise SystemExit(f"candidate {name!r} on --base {base}: {err}") from None


def shared_demos(out, base, seed=0):
    """OUT/D0/data/D0.npz: the base profile's oracle demonstrations, collected once (a stage: resumable)."""
    run = Run(os.path.join(out, "D0"), replace(profiles.PROFILES[base], seed=seed))
    run.memo("data/D0.npz", dagger.oracle_demonstrations, run.cfg, log=run.log)
    return run.path("data", "D0.npz")


def measure(out, name, cfg_fields, demos_path):
    """One candidate (a worker's job): D0 copied in, pi_0 trained and evaluated and the recipe's BC row (dagger.py
    --prepare), the CPU seconds of a training step."""
    root = os.path.join(out, name)
    target = os.path.join(root, "data", "D0.npz")
    if not os.path.exists(target):
        os.makedirs(os.path.dirname(target), exist_ok=True)
        shutil.copyfile(demos_path, target + ".part")
        os.replace(target + ".part", target)
    cfg = dagger.Config(**cfg_fields)
    report.run_experiment(cfg, root, prepare=True)  # the shared stages: D0, pi_0, its evaluation, the BC row
    path = os.path.join(root, "cpu_per_step.json")
    if not os.path.exists(path):
        write_json(path, {"seconds": cpu_seconds_per_step(cfg, Run(root, cfg).load("data/D0.npz"))})


def cpu_seconds_per_step(cfg, demos, steps=TIMED_STEPS):
    """CPU seconds (this process, one torch thread) of one training step of cfg's policy on demos' chunks: a
    fresh policy trained `steps` steps at cfg's batch, timed by time.process_time -- a count that other
    processes on the cores do not inflate, unlike the stage's wall seconds."""
    obs, chunks = diffusion.chunk_dataset(demos, cfg.horizon)
    policy = cpu_kernels.use_kernels(dagger.make_policy(cfg, environments.make_env(cfg.env)))  # as a run trains it
    tc = replace(dagger.train_config(replace(cfg, bc_steps=steps), policy, steps, seed=0), log_every=0)
    t0 = time.process_time()
    diffusion.train(policy, obs, chunks, tc, log=lambda m: None)
    return (time.process_time() - t0) / steps


def result_row(out, name):
    """The table row of a finished candidate, from its folder (config, CPU per step, evaluations, timings, pi_0)."""
    root = os.path.join(out, name)
    path = os.path.join(root, "config.json")
    cfg = dagger.Config(**without_retired_fields(path, read_json(path)))  # a folder may predate a deleted option
    pi0 = Run(root, cfg).load("checkpoints/bc.pt")
    seconds = cfg.bc_steps * read_json(os.path.join(root, "cpu_per_step.json"))["seconds"]  # pi_0's training, CPU
    # pi_0's own evaluation (a folder made before the recipes were named, under the lever recipe, has only the BC row's, the same)
    pi0_eval = "eval/pi0.json" if os.path.exists(os.path.join(root, "eval", "pi0.json")) else "eval/bc.json"
    success = {key: 100.0 * float(np.mean(read_json(os.path.join(root, *path.split("/")))["success"]))
               for key, path in (("pi0", pi0_eval), ("bc_row", "eval/bc.json"))}
    evaluation = read_json(os.path.join(root, "timings", timing_name(pi0_eval).replace("/", "__") + ".json"))
    net = (f"U-Net {tuple(cfg.down_dims)}" if cfg.network == "unet"
           else f"MLP {cfg.mlp_width} x {cfg.mlp_blocks}")
    return {"candidate": name, "network": net, "chunk": f"{cfg.horizon} / {cfg.n_act}", "batch": cfg.batch_size,
            "bc_steps": cfg.bc_steps, "finetune": cfg.recipe,
            "params": sum(p.numel() for p in pi0.net.parameters()),
            "steps_per_s": cfg.bc_steps / seconds, "bc_minutes": seconds / 60.0,
            "pi0": success["pi0"], "bc_row": success["bc_row"],
            "points_per_minute": success["pi0"] / (seconds / 60.0), "eval_minutes": evaluation["seconds"] / 60.0,
            "in_band": BAND[0] <= success["pi0"] <= BAND[1]}


def table(rows):
    """The markdown table of result_row dicts."""
    lines = ["| candidate | network | H / executed | batch | BC steps (fine-tuning) | parameters | steps per CPU-s "
             "| pi_0 CPU-min | pi_0 % | BC row % | pi_0 points per CPU-min | one evaluation, wall min | in "
             f"{BAND[0]:.0f}-{BAND[1]:.0f} % |",
             "|---" * 13 + "|"]
    for r in rows:
        lines.append(f"| {r['candidate']} | {r['network']} | {r['chunk']} | {r['batch']} | {r['bc_steps']:,} "
                     f"({r['finetune']}) | {r['params']:,} | {r['steps_per_s']:.1f} | {r['bc_minutes']:.1f} "
                     f"| {r['pi0']:.1f} | {r['bc_row']:.1f} | {r['points_per_minute']:.2f} "
                     f"| {r['eval_minutes']:.1f} | {'yes' if r['in_band'] else 'no'} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--candidates", default=",".join(DEFAULT_CANDIDATES),
                   help=f"comma-separated subset of {', '.join(CANDIDATES)}, or all "
                        f"(default: {','.join(DEFAULT_CANDIDATES)})")
    p.add_argument("--base", default="table2", help="the profile the candidates change (default table2: the lever)")
    p.add_argument("--out", default=os.path.join("runs", "lever_networks"), help="folder of the candidates' folders")
    p.add_argument("--jobs", type=int, default=1, help="candidates trained side by side, one process each "
                                                       "(no more than the cores: the evaluations' minutes are wall)")
    p.add_argument("--seed", type=int, default=0, help="master seed of D0 and of every candidate")
    args = p.parse_args(argv)
    if args.jobs < 1:
        raise SystemExit(f"--jobs must be >= 1, got {args.jobs}")
    names = list(CANDIDATES) if args.candidates == "all" else [n for n in args.candidates.split(",") if n]
    configs = {name: candidate_config(args.base, name, args.seed) for name in names}  # every name checked first
    demos_path = shared_demos(args.out, args.base, args.seed)
    in_parallel(measure, [(args.out, name, asdict(cfg), demos_path) for name, cfg in configs.items()], args.jobs,
                print)
    text = table([result_row(args.out, name) for name in names])
    print(text)
    return text


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
