"""Evaluate one saved policy on any list of scenario seeds and print its success with a 95 % interval.

A policy file is what a run writes under checkpoints/ (e.g. lineage_5/round_1/checkpoints/pooled.pt) or one of the
committed policies under benchmarks/results/noise_transfer/policies/. The evaluation is the run's own
(dagger.evaluate: lockstep episodes, success = the goal reached without a collision within the step limit), with the
chunk length the policy was trained for:

    python benchmarks/evaluate_policy.py benchmarks/results/noise_transfer/policies/lineage_5/pooled.pt \\
        --seeds 30000-30299 --repeats 3

--seeds takes ranges and lists (30000-30299, 10000-10099,20000-20099, 7,8,9); the same --sample-seed gives the same
draws for every policy, so two policies' outputs pair scenario by scenario. The interval is a t interval over the
scenarios (each scenario's success averaged over its repeats), as the study's tables average them; a scenario seed
outside the training seeds 0..9999 was never trained on by any stage.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import dagger  # noqa: E402
from experiment import environments, run_folder  # noqa: E402


def parse_seeds(text):
    """'30000-30299,7' -> [30000, ..., 30299, 7]: ranges a-b (both ends included) and single seeds, comma-separated.
    ValueError naming the bad part."""
    seeds = []
    for part in filter(None, (p.strip() for p in str(text).split(","))):
        lo, dash, hi = part.partition("-")
        try:
            a, b = int(lo), int(hi) if dash else int(lo)
        except ValueError:
            raise ValueError(f"--seeds: {part!r} is not a seed or a range a-b of seeds (e.g. 30000-30299)") from None
        if a < 0 or b < a:
            raise ValueError(f"--seeds: {part!r} is not a range of seeds >= 0 with its start <= its end")
        seeds.extend(range(a, b + 1))
    if not seeds:
        raise ValueError(f"--seeds: {text!r} names no seed")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds: {text!r} names a seed twice")
    return seeds


def interval(success, level_t=None):
    """(mean, half-width of the 95 % t interval) in points over the scenarios of a (scenarios, repeats) table."""
    per = 100.0 * np.asarray(success, float).mean(axis=1)
    n = per.size
    if n < 2:
        return float(per.mean()), math.inf
    t = level_t or t_quantile(0.975, n - 1)
    return float(per.mean()), float(t * per.std(ddof=1) / math.sqrt(n))


def t_quantile(p, df):
    """Student's t quantile by bisection on dagger.student_t_cdf (0.5 < p < 1)."""
    lo, hi = 0.0, 1e3
    for _ in range(200):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if dagger.student_t_cdf(mid, df) < p else (lo, mid)
    return (lo + hi) / 2


def evaluate_file(path, seeds, repeats, sample_seed, env="planar", log=None):
    """(scenarios, repeats) bool success of the policy saved at `path` on `seeds` (dagger.evaluate, its n_act)."""
    policy = run_folder.load_policy(path, "cpu")
    return dagger.evaluate(policy, env, list(seeds), repeats, policy.cfg.n_act, sample_seed, log=log,
                           make_env=environments.make_env)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("policy", help="a policy file (.pt) written by a run")
    p.add_argument("--seeds", default="30000-30299", help="scenario seeds: ranges and lists, e.g. 30000-30299 "
                   "(default: the 300 new scenarios of benchmarks/noise_transfer.py)")
    p.add_argument("--repeats", type=int, default=3, help="evaluations of each scenario (default 3, the paper's)")
    p.add_argument("--sample-seed", type=int, default=0, help="seed of the policy's sampling draws (default 0)")
    p.add_argument("--env", default="planar", choices=sorted(environments.ENVIRONMENTS),
                   help="the env the policy was trained on (default planar)")
    a = p.parse_args(argv)
    try:
        seeds = parse_seeds(a.seeds)
    except ValueError as err:
        p.error(str(err))
    if a.repeats < 1:
        p.error(f"--repeats {a.repeats}: must be >= 1")
    if a.sample_seed < 0:
        p.error(f"--sample-seed {a.sample_seed}: must be >= 0")
    if not os.path.isfile(a.policy):
        p.error(f"{a.policy}: no such policy file (a .pt file under a run's checkpoints/)")
    t0 = time.time()
    ok = evaluate_file(a.policy, seeds, a.repeats, a.sample_seed, a.env)
    mean, half = interval(ok)
    print(f"{a.policy}: success {mean:.1f} % +- {half:.1f} (95 % t interval over {len(seeds)} scenarios, "
          f"{a.repeats} repeats each; {int(ok.sum())} of {ok.size} episodes; {time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
