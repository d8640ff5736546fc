"""Policy-Calibrated DAgger end to end: the paper's loop, evaluation, statistics, tables and figures.

Paper map (paper.tex):
  Sec. IV-A, steps 1-6 ............ main / run_lineage: D0 from the oracle, BC pi_0, HG-DAgger rounds,
                                     calibration, augmentation, co-training, fine-tuning from pi_0
  Sec. IV-A step 2, Sec. V ......... stage_collect / rollout: expert-gated (HG-DAgger) data collection
                                     with the RRT oracle (oracle.Gate); interventions shorter than H are
                                     discarded (drop_short_interventions, Sec. IV-C)
  Sec. IV-D ........................ calibrate.calibrate, called once per round with the current policy
  Sec. IV-E ........................ relabel.AugmentationSampler, the on-the-fly augmented data D^_k
  Sec. V, Tables I and II .......... evaluate (100 scenarios x 3 evaluations, batched), paired_ttest,
                                     tost, write_report (table.md in Table I's layout)

Usage:
  python dagger.py                          # the 'quick' profile: the whole loop on the planar env
  python dagger.py --profile smoke          # about a minute; what CI runs
  python dagger.py --profile paper          # Table I's protocol (long; resumable; shardable)
  python dagger.py --profile paper --lineage 2     # one lineage alone (e.g. a Slurm array task)
  python dagger.py --profile paper --report        # merge finished lineages into table and figures

Every stage writes its result to runs/<name>/ before the next starts; running the same command
again skips what is finished, so a stopped run resumes from its last finished stage (the run folder's
plumbing, `Run`, is behind the "Beyond the paper" banner, before the command line).
"""
from __future__ import annotations

import argparse
import concurrent.futures
import csv
import json
import math
import multiprocessing
import os
import sys
import time
from dataclasses import asdict, dataclass, fields, replace

import numpy as np
import torch

import calibrate
import diffusion
import envs
import oracle as oracle_mod
import partial_denoise
import relabel

# ----------------------------------------------------------------------------------------------
# Configuration: one dataclass, three presets
# ----------------------------------------------------------------------------------------------
FIXED_SIGMAS = (2, 4, 8, 12, 16)  # Table I's sweep, in the paper's median steps (noise_model converts)
TABLE_I_METHODS = ("bc", "hg_dagger", *[f"fixed_{s}" for s in FIXED_SIGMAS],
                   "pooled", "per_step", "closed_loop")
# Not in the paper: the pipeline with sigma = 0 (intervention states relabelled with the return labels, no
# noise). It separates the effect of the noise from the effect of relabelling (a noised method never sees the
# recorded intervention chunks, HG-DAgger sees nothing else).
CONTROL_METHODS = ("zero_noise",)
ALL_METHODS = TABLE_I_METHODS + CONTROL_METHODS
METHOD_LABELS = {
    "bc": "BC (no aggregation)",
    "hg_dagger": "HG-DAgger",
    **{f"fixed_{s}": f"Fixed iso. noise (sigma={s}, paper's unit)" for s in FIXED_SIGMAS},
    "pooled": "Pooled Sigma-bar^alpha (Ours)",
    "per_step": "Per-step Sigma^alpha (Ours)",
    "closed_loop": "Closed-loop pooled Sigma-bar^alpha (Ours)",
    "zero_noise": "Co-training control (sigma=0; not in the paper)",
}


@dataclass
class Config:
    # --- the paper's experiment (Sec. V; the authors' values in PAPER_SETUP.md) ---
    env: str = "planar"  # 'planar' (Table I) or 'engine3d' (Table II)
    methods: tuple = TABLE_I_METHODS  # Table I's rows (BC and HG-DAgger always run: the others pair with them)
    n_demos: int = 500  # |D0|, oracle demonstrations on training scenarios (paper: 500)
    rounds: int = 5  # HG-DAgger rounds K (paper: 5 planar, 2 UR5)
    lineages: int = 5  # independent repeats of the rounds (paper: 5 planar, 3 UR5)
    # Where HG-DAgger collects (PAPER_SETUP.md §4): 'eval', the authors' protocol -- each round rolls the
    # lineage's current policy on the evaluation scenarios, skips those its evaluation solved every time,
    # and records interventions on the rest, so the evaluation scenarios enter the training data; or
    # 'train', the stricter variant -- episodes_per_round fresh training scenarios.
    collect_on: str = "eval"
    # The authors' chunks: 64 relative joint targets at 30 Hz, 32 executed (2.1 s and 1.1 s). The planar env
    # runs at 10 Hz by default (envs.PlanarConfig.dt): the same seconds are 20 and 10 steps.
    horizon: int = 20  # steps: H, actions per chunk (interventions shorter than H are discarded, Sec. IV-C)
    n_act: int = 10  # steps: actions executed per chunk before the policy is asked again
    K: int = 100  # diffusion steps (the authors: 100, all of them at inference)
    down_dims: tuple = (64, 128, 256)  # channels of the epsilon U-Net's levels (the authors: 128, 256, 512)
    bc_steps: int = 75_000  # BC training steps (paper: pi_0 = BC's 75k checkpoint)
    finetune_steps: int = 100_000  # fine-tuning steps of every method per round (paper: to 175k)
    batch_size: int = 256  # (state, chunk) pairs per training step
    lr: float = 1e-3  # peak learning rate
    # The authors' co-training (PAPER_SETUP.md §2): every fine-tuning batch is D0 and, in exactly this share,
    # intervention frames, split equally over rounds 1..k; the noised methods noise every intervention frame
    # they draw (relabel.AugmentationSampler) and never D0.
    intervention_fraction: float = 0.3
    # How every arm is fine-tuned from pi_0 (PAPER_SETUP.md §2): 'continue', the authors' run -- pi_0 is the
    # bc_steps point of one cosine schedule of bc_steps + finetune_steps, and every arm (the BC row too, on D0
    # alone) continues BC's AdamW state along its tail; or 'restart', a fresh optimizer with its own warm-up
    # and cosine over finetune_steps (the BC row is then pi_0 itself, with finetune_steps fewer steps).
    finetune: str = "continue"
    # The share of a noised arm's intervention rows taken as recorded (the expert's own chunks), the rest
    # noised and relabelled. The authors' code: 0 (every drawn intervention frame noised; their raw_mix knob);
    # the paper's text co-trains on the recorded interventions and their noised copies: 0.5. Measured on mid's
    # round 1 (benchmarks/README.md, "The co-training mix"): 0.5 gave fixed sigma = 2 +0.9 and pooled -2.4 points.
    raw_mix: float = 0.0
    # The authors' observation noise in training (PAPER_SETUP.md §2), raw units, labels unchanged:
    obs_noise_joints: float = 0.01  # rad, on q_t and q_{t-1}
    obs_noise_env: float = 0.005  # m, on the environment numbers (target, obstacles, end effector)
    calib_samples: int = 4  # policy samples per anchor of Sigma_hat (the authors: 4; Sec. IV-D)
    calib_rollouts_per_beta: int = 1  # blended rollouts per blend ratio (paper: 1; see calibrate.CalibrationConfig)
    eval_scenarios: int = 100  # the fixed held-out scenarios (Sec. V)
    eval_repeats: int = 3  # evaluations per scenario
    tost_margin: float = 2.0  # equivalence margin in success points (paper: +-2)
    # --- not in the paper ---
    name: str = "quick"  # run folder runs/<name>/ (default: the profile's name)
    image_obs: bool = False  # engine3d only: the policy sees a camera image (and the joints, the goal) instead
    #                          of the obstacle list, through a small CNN (the paper's UR5 policy sees images)
    image_size: int = 32  # pixels of the square camera image (with image_obs)
    # Where episodes start (an env option; None: the env's default). planar: 'random' (the authors' evaluation
    # starts: uniform over the joint limits, collision-free, often folded) or 'fixed' (their demonstration
    # config's q); engine3d: 'random' (the authors') or 'home' (near a home pose)
    start: str | None = None
    goal_angle: float | None = None  # deg, engine3d: success also needs the tool's orientation within this
    #   angle of the goal posture's (the authors' 10; envs.EngineConfig.goal_angle_tolerance); None: position only
    seed: int = 0  # master seed; every stage derives its own seed from it
    device: str = "cpu"  # torch device of the policy ('cuda' where a GPU exists)
    episodes_per_round: int = 100  # collect_on='train': HG-DAgger rollouts on fresh training scenarios per round
    oracle_attempts: int = 3  # RRT runs per plan; the shortest end-effector path wins (1 is ~3x faster)
    joint_obs: bool = True  # policy predicts chunks relative to the current joint position (and sees the
    #                         velocity): ~8x more precise first actions on held-out demos (diffusion.py)
    # The epsilon network (diffusion.PolicyConfig.network): 'unet', the authors' (down_dims), or 'mlp', a residual
    # MLP with the same FiLM conditioning (mlp_width, mlp_blocks), ~8x the training samples per CPU second
    network: str = "unet"
    mlp_width: int = 256
    mlp_blocks: int = 3
    finetune_lr: float | None = None  # finetune='restart': peak lr of every fine-tuning run (None: lr). Fine-tuning restarts the
    #   warm-up and cosine schedule from pi_0's converged weights; a peak below BC's keeps pi_0's skill
    calib_blend_episodes: int = 4  # intervention episodes that get the 13 blended rollouts
    # Every evaluated policy is also evaluated on envs.unseen_seeds(), scenarios no stage ever trains on (under
    # collect_on='eval' the evaluation scenarios are not held out): a second table; eval_scenarios x eval_repeats
    eval_unseen: bool = True

    def __post_init__(self):
        self.methods = tuple(self.methods)
        bad = [m for m in self.methods if m not in ALL_METHODS]
        if bad:
            raise ValueError(f"unknown method(s) {bad}; valid: {', '.join(ALL_METHODS)}")
        # BC and HG-DAgger anchor every comparison (paired design): always present, listed first.
        self.methods = ("bc", "hg_dagger") + tuple(m for m in self.methods if m not in ("bc", "hg_dagger"))
        if self.env not in envs.ENVIRONMENTS:
            raise ValueError(f"unknown env {self.env!r}; valid: {', '.join(sorted(envs.ENVIRONMENTS))}")
        self.down_dims = tuple(int(d) for d in self.down_dims)
        for key in ("n_demos", "rounds", "lineages", "episodes_per_round", "horizon", "n_act", "K",
                    "bc_steps", "finetune_steps", "batch_size", "eval_scenarios", "eval_repeats",
                    "calib_rollouts_per_beta"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} must be >= 1, got {getattr(self, key)}")
        if self.image_obs and self.env != "engine3d":
            raise ValueError(f"image_obs: image observations are an option of the engine3d env only, "
                             f"got env={self.env!r}")
        if self.goal_angle is not None and (self.env != "engine3d" or not 0.0 < self.goal_angle <= 180.0):
            raise ValueError(f"goal_angle: {self.goal_angle!r} is an option of the engine3d env only, in degrees "
                             f"within (0, 180] (the authors' 10), or None for position-only success")
        starts = envs.PLANAR_STARTS if self.env == "planar" else envs.ENGINE_STARTS
        if self.start is not None and self.start not in starts:
            raise ValueError(f"start: {self.start!r} is not a start of the {self.env} env; valid: "
                             f"{', '.join(starts)}")
        if self.finetune not in ("continue", "restart"):
            raise ValueError(f"finetune must be 'continue' (the authors' run) or 'restart', got {self.finetune!r}")
        if self.finetune == "continue" and self.finetune_lr is not None:
            raise ValueError(f"finetune_lr={self.finetune_lr} is for finetune='restart'; 'continue' follows BC's "
                             f"own schedule (lr)")
        if not 0.0 <= self.raw_mix < 1.0:
            raise ValueError(f"raw_mix must be in [0, 1) (the share of recorded intervention rows in a noised "
                             f"arm), got {self.raw_mix}")
        if self.network not in diffusion.NETWORKS:
            raise ValueError(f"network must be one of {', '.join(diffusion.NETWORKS)}, got {self.network!r}")
        if self.image_size < 8:
            raise ValueError(f"image_size must be >= 8 pixels, got {self.image_size}")
        if self.collect_on not in ("eval", "train"):
            raise ValueError(f"collect_on must be 'eval' (the paper's protocol) or 'train', got {self.collect_on!r}")
        if not 0.0 < self.intervention_fraction < 1.0:
            raise ValueError(f"intervention_fraction must be in (0, 1), got {self.intervention_fraction}")
        if self.eval_scenarios > 100:
            raise ValueError(f"eval_scenarios must be <= 100 (the fixed set), got {self.eval_scenarios}")


PROFILES = {
    # CI: every stage and every output file, tiny sizes (about a minute).
    "smoke": Config(name="smoke", n_demos=16, rounds=1, lineages=1, episodes_per_round=8, K=10,
                    down_dims=(16, 32), bc_steps=300, finetune_steps=150, batch_size=64, lr=1e-3,
                    methods=("bc", "hg_dagger", "fixed_4", "pooled", "per_step", "closed_loop"),
                    calib_blend_episodes=1, calib_samples=4, eval_scenarios=8, eval_repeats=1),
    # The default of `python dagger.py`: the whole loop on the planar env, the mid recipe at a student's scale
    # (one lineage, one round): 9 min 14 s wall on the 2-core development machine with --workers 2
    # (benchmarks/README.md, "The quick profile on the new recipe").
    "quick": Config(name="quick", n_demos=300, rounds=1, lineages=1, episodes_per_round=30, oracle_attempts=1,
                    network="mlp", K=20, batch_size=256, lr=1e-3, bc_steps=6000, finetune_steps=6000,
                    start="random", finetune="continue",
                    methods=("bc", "hg_dagger", "fixed_4", "pooled"), eval_scenarios=100, eval_repeats=3),
    # Between quick and paper, for this 2-core machine (benchmarks/README.md, "Table I where DAgger has something
    # to fix"): the authors' 5 lineages for the paired statistics, 2 rounds, the fixed sweep at the paper's
    # 2 / 4 / 8, the sigma = 0 control. The authors' evaluation starts (random, often folded: from their fixed
    # demonstration start DAgger had little to fix), their fine-tuning (every arm continues pi_0's optimizer along
    # one cosine of bc_steps + finetune_steps; their pi_0 sits at 43 % of it, ours at 50 %), and the residual-MLP
    # epsilon network, which trains ~8x more samples per CPU second than the (32, 64, 128) U-Net.
    # Lineages run side by side: --prepare, then --lineage i, then --report (README). Measured: prepare 14 min,
    # lineages 0-2 side by side 116 min, 3-4 side by side 74 min, the cores shared with probes for about half of
    # it (benchmarks/README.md, "The mid run on the new recipe").
    "mid": Config(name="mid", n_demos=500, rounds=2, lineages=5, episodes_per_round=100,
                  network="mlp", K=20, batch_size=256, lr=1e-3, bc_steps=10_000, finetune_steps=10_000,
                  start="random", finetune="continue",
                  methods=("bc", "hg_dagger", "fixed_2", "fixed_4", "fixed_8", "pooled", "zero_noise"),
                  eval_scenarios=100, eval_repeats=3),
    # The Table II analogue for this machine: the earlier mid recipe (U-Net, fine-tuning restarted) on the UR5
    # engine-lever env with Table II's rows (BC, HG-DAgger, pooled Sigma-bar^alpha; the paper's 2 rounds and 3
    # lineages) and fixed sigma = 4 as a reference. --prepare (D0 + BC, ~55 min of one core), --lineage 0/1/2
    # side by side (~50 min), --report (measured: 1 h 45 min end to end on 2 cores; benchmarks/README.md, "The
    # Table II analogue").
    "table2": Config(name="table2", env="engine3d", n_demos=500, rounds=2, lineages=3, episodes_per_round=100,
                     K=20, down_dims=(32, 64, 128), batch_size=64, lr=3e-4, bc_steps=30_000,
                     finetune_steps=2_500, methods=("bc", "hg_dagger", "fixed_4", "pooled"),
                     finetune="restart", eval_scenarios=100, eval_repeats=3),  # measured so; the mid recipe
    #   (residual MLP, batch 256, BC 10k + 10k continued) gave pi_0 15.0 % and the BC row 20.0 % here: not used
    # Table I's protocol at the authors' sizes (PAPER_SETUP.md §2): their U-Net widths, 100 diffusion
    # steps, batch 32, lr 1e-5, BC 75k steps, every cell fine-tuned +100k (for a GPU or a cluster).
    "paper": Config(name="paper", down_dims=(128, 256, 512), K=100, batch_size=32, lr=1e-5),
}


# ----------------------------------------------------------------------------------------------
# Rollouts: many episodes in lockstep, one policy call per decision for all of them
# ----------------------------------------------------------------------------------------------
def rollout(envs_list, policy, n_act, generator, oracle=None, log=None, seed=0):
    """Run one episode in each (already reset) env until all end. Returns episode dicts.

    Without an oracle: the policy drives (evaluation). With one: HG-DAgger (Sec. IV-A step 2) with the
    authors' gate (PAPER_SETUP.md §3, oracle.Gate): before every policy step the gate looks at the
    pending actions; on a predicted collision the oracle plans from the current state and velocity, on
    a stall or a time trigger the episode is first rewound a few steps (the rewound policy steps are
    dropped from the record), and the expert drives (expert=True) a random 20-67 steps, then hands
    back; at most max_interventions per episode. `seed` seeds the gates' random draws. Each episode
    dict also gets 'interventions' (how many times the expert drove).
    """
    E = len(envs_list)
    rec = [{"obs": [], "q": [], "action": [], "expert": []} for _ in range(E)]
    start = [(e.q.copy(), e.q_prev.copy()) for e in envs_list]  # for a rewind to step 0
    obs_now = [e.make_obs(e.q, e.q_prev) for e in envs_list]
    queue = [[] for _ in range(E)]  # pending (action, by_expert) per episode, executed in order
    pending = [np.zeros((0,)) for _ in range(E)]  # the policy's whole remaining chunk (the gate's lookahead)
    done = np.zeros(E, bool)
    success = np.zeros(E, bool)
    gates = None
    if oracle is not None:
        gates = [oracle.gate(e, np.random.default_rng([seed, int(e.seed)])) for e in envs_list]
    triggers = {"collision": 0, "stall": 0, "time": 0, "unplanned": 0}

    def take_over(i, reason):
        """The expert's actions after a trigger (None if no plan was found)."""
        env, gate, r = envs_list[i], gates[i], rec[i]
        gate.interventions += 1  # a failed plan counts too: no re-planning at every step
        if reason in ("stall", "time"):  # rewind, but never into the expert's own data
            policy_tail = len(r["expert"]) - (max(np.flatnonzero(r["expert"]), default=-1) + 1)
            n = gate.rewind_steps(policy_tail)
            if n:
                q, q_prev = r["q"][-n], (r["q"][-n - 1] if len(r["q"]) > n else start[i][1])  # state n steps ago
                for key in r:
                    del r[key][-n:]
                env.set_state(q, q_prev, step_count=env.step_count)  # the episode clock keeps running
                obs_now[i] = env.make_obs(env.q, env.q_prev)
                gate.rewound(n)
        try:
            plan = oracle.intervention(env, rng=gate.rng)
        except oracle_mod.PlanningFailed:
            triggers["unplanned"] += 1
            return None
        triggers[reason] += 1
        return plan

    t_log, step = time.time(), 0
    while not done.all():
        step += 1
        if log is not None and time.time() - t_log >= 10.0:  # a progress line at least every 10 s
            log(f"  step {step}: {int(done.sum())}/{E} episodes finished")
            t_log = time.time()
        need = [i for i in range(E) if not done[i] and not queue[i]]
        if need:
            chunks = policy.sample(np.stack([obs_now[i] for i in need]), generator=generator)  # (B, H, dof)
            for i, chunk in zip(need, chunks):
                queue[i] = [(a, False) for a in chunk[:n_act]]
                pending[i] = np.asarray(chunk)
        for i in range(E):
            if done[i]:
                continue
            if gates is not None and not queue[i][0][1]:  # the policy is about to drive: ask the gate
                reason = gates[i].should_intervene(envs_list[i], pending[i])
                if reason is not None:
                    plan = take_over(i, reason)
                    if plan is not None:
                        queue[i], pending[i] = [(a, True) for a in plan], np.zeros((0,))
                    elif reason != "collision":  # rewound, no plan: the policy decides afresh
                        chunk = policy.sample(obs_now[i][None], generator=generator)[0]
                        queue[i], pending[i] = [(a, False) for a in chunk[:n_act]], np.asarray(chunk)
            action, by_expert = queue[i].pop(0)
            if not by_expert:
                pending[i] = pending[i][1:]
            r = rec[i]
            r["obs"].append(obs_now[i])
            r["q"].append(envs_list[i].q)
            r["action"].append(np.asarray(action, dtype=np.float64))
            r["expert"].append(by_expert)
            obs_now[i], _, terminated, truncated, info = envs_list[i].step(action)
            if gates is not None:
                gates[i].record(envs_list[i], by_expert)
            if terminated or truncated:
                done[i], success[i], queue[i] = True, info["success"], []
    episodes = []
    for i, (e, r, ok) in enumerate(zip(envs_list, rec, success)):
        episodes.append({"obs": np.asarray(r["obs"], np.float32).reshape(len(r["obs"]), -1),
                         "q": np.asarray(r["q"]).reshape(len(r["q"]), -1),
                         "action": np.asarray(r["action"]).reshape(len(r["action"]), -1),
                         "expert": np.asarray(r["expert"], bool), "seed": int(e.seed), "success": bool(ok),
                         # expert takeovers that drove (a trigger without a plan is not one)
                         "interventions": int(np.sum(np.diff(np.r_[0, np.asarray(r["expert"], int)]) == 1))})
    if log is not None and oracle is not None:
        log(f"  {sum(triggers[k] for k in ('collision', 'stall', 'time'))} interventions in {E} episodes "
            f"(predicted collision {triggers['collision']}, stall {triggers['stall']}, time {triggers['time']}; "
            f"{triggers['unplanned']} triggers found no plan)")
    return episodes


def drop_short_interventions(expert, H):
    """Sec. IV-C: interventions shorter than H steps teach nothing with chunks of H; mark them False
    (diffusion.expert_runs, the paper's label rule)."""
    kept = np.zeros(len(expert), bool)
    for start, end in diffusion.expert_runs(expert, H):
        kept[start:end] = True
    return kept


# Episodes run in lockstep at most this many at a time, per env. Each EngineReach3D holds its own pybullet
# client, ~30 MB (measured): 300 evaluation episodes at once would take 9 GB; 100 take 3 GB.
MAX_PARALLEL_ENVS = {"planar": None, "engine3d": 100}


def evaluate(policy, env_name, seeds, repeats, n_act, seed, env_options=None, max_parallel="env default",
             log=None):
    """Success (len(seeds), repeats) bool: goal reached without collision within the step limit.

    env_options: keyword arguments of envs.make_env (e.g. image_obs=True), the same as in training.

    The len(seeds) * repeats episodes run in lockstep (one policy call per decision), in groups of at most
    max_parallel (default MAX_PARALLEL_ENVS[env_name]; None = all at once) to bound memory. The sampling
    generator is seeded identically for every method, so methods face the same scenarios and the
    same draws where their policies agree (a paired comparison).
    """
    if max_parallel == "env default":
        max_parallel = MAX_PARALLEL_ENVS.get(env_name)
    jobs = [int(s) for _ in range(repeats) for s in seeds]
    group = max_parallel or max(1, len(jobs))
    gen = torch.Generator(device=policy.device).manual_seed(seed)
    ok = []
    for start in range(0, len(jobs), group):
        env_list = []
        for s in jobs[start:start + group]:
            e = envs.make_env(env_name, **(env_options or {}))
            e.reset(seed=s)
            env_list.append(e)
        ok += [ep["success"] for ep in rollout(env_list, policy, n_act, gen, log=log)]
        for e in env_list:
            if hasattr(e, "close"):
                e.close()  # free the simulator (a pybullet client) before the next group
    ok = np.array(ok, bool)
    return ok.reshape(repeats, len(seeds)).T


# ----------------------------------------------------------------------------------------------
# Statistics, self-written (no scipy): Student-t CDF, paired t-test, TOST
# ----------------------------------------------------------------------------------------------
def _betacf(a, b, x, max_iter=300, eps=1e-15):
    """Continued fraction of the regularized incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, max_iter + 1):
        # even step: d_{2m} = m (b - m) x / ((a + 2m - 1)(a + 2m))
        num = m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m))
        d = 1.0 + num * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + num / c
        c = c if abs(c) > tiny else tiny
        h *= d * c
        # odd step: d_{2m+1} = -(a + m)(a + b + m) x / ((a + 2m)(a + 2m + 1))
        num = -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))
        d = 1.0 + num * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + num / c
        c = c if abs(c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < eps:
            break
    return h


def incomplete_beta(a, b, x):
    """Regularized incomplete beta I_x(a, b) for a, b > 0 and 0 <= x <= 1."""
    if not 0.0 <= x <= 1.0:
        raise ValueError(f"incomplete_beta needs 0 <= x <= 1, got {x}")
    if x in (0.0, 1.0):
        return x
    log_front = (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
                 + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):  # the continued fraction converges fast here
        return math.exp(log_front) * _betacf(a, b, x) / a
    return 1.0 - math.exp(log_front) * _betacf(b, a, 1.0 - x) / b  # symmetry I_x(a,b) = 1 - I_{1-x}(b,a)


def student_t_cdf(t, df):
    """P(T <= t) for Student's t with df > 0 degrees of freedom: 1 - I_{df/(df+t^2)}(df/2, 1/2) / 2."""
    if df <= 0:
        raise ValueError(f"degrees of freedom must be > 0, got {df}")
    if math.isinf(t):
        return 1.0 if t > 0 else 0.0
    tail = 0.5 * incomplete_beta(df / 2.0, 0.5, df / (df + t * t))
    return 1.0 - tail if t > 0 else tail


def paired_ttest(a, b):
    """Two-sided paired t-test of mean(a - b) = 0. Returns (t, df, p). Needs >= 2 pairs."""
    d = np.asarray(a, float) - np.asarray(b, float)
    n = d.size
    if n < 2:
        raise ValueError(f"a paired t-test needs at least 2 pairs (lineages), got {n}")
    # >>> exercise 13: the paired t-test and TOST of Table I (Sec. V)
    mean, sd = d.mean(), d.std(ddof=1)
    if sd == 0:
        return (0.0 if mean == 0 else math.copysign(math.inf, mean)), n - 1, (1.0 if mean == 0 else 0.0)
    t = mean / (sd / math.sqrt(n))
    return t, n - 1, 2.0 * (1.0 - student_t_cdf(abs(t), n - 1))
    # <<< exercise 13


def tost(a, b, margin):
    """Two one-sided tests: is mean(a - b) within (-margin, +margin)? Returns (p, t_lower, t_upper).

    H0: the difference is <= -margin or >= +margin; equivalence is shown when p (the larger of the
    two one-sided p-values) is small. Needs >= 2 pairs.
    """
    d = np.asarray(a, float) - np.asarray(b, float)
    n = d.size
    if n < 2:
        raise ValueError(f"TOST needs at least 2 pairs (lineages), got {n}")
    if margin <= 0:
        raise ValueError(f"TOST margin must be > 0, got {margin}")
    # >>> exercise 13: the paired t-test and TOST of Table I (Sec. V)
    mean, se = d.mean(), d.std(ddof=1) / math.sqrt(n)
    if se == 0:
        p = 0.0 if abs(mean) < margin else 1.0
        return p, math.inf, -math.inf
    t_lower = (mean + margin) / se  # H0: mean <= -margin
    t_upper = (mean - margin) / se  # H0: mean >= +margin
    p_lower = 1.0 - student_t_cdf(t_lower, n - 1)
    p_upper = student_t_cdf(t_upper, n - 1)
    return max(p_lower, p_upper), t_lower, t_upper
    # <<< exercise 13


# ----------------------------------------------------------------------------------------------
# The stages of the loop (Sec. IV-A). Each one returns its result, or loads it if already on disk.
# ----------------------------------------------------------------------------------------------
def env_options(cfg):
    """envs.make_env keyword arguments of this run (image observations and the UR5's starts are env options)."""
    options = {"image_obs": True, "image_size": cfg.image_size} if cfg.image_obs else {}
    if cfg.start is not None:
        options["start"] = cfg.start
    if cfg.goal_angle is not None:
        options["goal_angle_tolerance"] = cfg.goal_angle
    return options


def make_run_env(cfg):
    """A fresh env of this run's kind (one per scenario in rollouts)."""
    return envs.make_env(cfg.env, **env_options(cfg))


def make_oracle(cfg, *keys):
    """The RRT expert; keys (e.g. lineage, round) give an intervention run its own planner seed."""
    return oracle_mod.Oracle(oracle_mod.OracleConfig(seed=stage_seed(cfg, "oracle", *keys), horizon=cfg.horizon,
                                                     n_attempts=cfg.oracle_attempts))


def stage_demos(run):
    """Step 1's data: D0, oracle demonstrations on training scenarios (skipping unplannable ones)."""
    cfg, path = run.cfg, run.path("data", "D0.npz")
    if os.path.exists(path):
        return load_episodes(path)
    env, expert = make_run_env(cfg), make_oracle(cfg)
    demos, seed, t0, failures = [], 0, time.time(), 0
    t_log = t0
    run.log(f"D0: {cfg.n_demos} oracle demonstrations on training scenarios")
    while len(demos) < cfg.n_demos:
        seed += 1
        try:
            demos.append(expert.demonstrate(env, env.train_seeds(1, start=seed - 1)[0]))
        except oracle_mod.PlanningFailed:
            failures += 1  # a scene the planner cannot solve in its budget is skipped
            continue
        if len(demos) % max(1, cfg.n_demos // 10) == 0 or time.time() - t_log >= 10.0:
            t_log = time.time()
            rate = len(demos) / (time.time() - t0)
            run.log(f"  demos {len(demos)}/{cfg.n_demos} | {rate * 60:.0f}/min | "
                    f"{(cfg.n_demos - len(demos)) / max(rate, 1e-9):.0f} s left | {failures} unplannable")
    envs.save_episodes(path, demos)
    run.record_time("demos", time.time() - t0)
    return demos


def make_policy(cfg, env):
    pc = diffusion.PolicyConfig(obs_dim=env.obs_dim, dof=env.dof, horizon=cfg.horizon, n_act=cfg.n_act,
                                K=cfg.K, down_dims=cfg.down_dims, joint_obs=cfg.joint_obs, image_shape=env.image_shape,
                                network=cfg.network, mlp_width=cfg.mlp_width, mlp_blocks=cfg.mlp_blocks,
                                seed=stage_seed(cfg, "init"))
    return diffusion.DiffusionPolicy(pc, device=cfg.device)


def observation_noise(cfg, policy_cfg):
    """Per-entry std (obs_dim,) of the training observation noise, raw units (PAPER_SETUP.md §2): the
    joints at t and t-1 get obs_noise_joints rad, the other low-dimensional numbers obs_noise_env m, image
    pixels none."""
    std = np.zeros(policy_cfg.obs_dim)
    std[:2 * policy_cfg.dof] = cfg.obs_noise_joints
    std[2 * policy_cfg.dof:policy_cfg.low_dim] = cfg.obs_noise_env
    return std


def train_resumable(run, policy, obs, chunks, steps, seed, final_path, sampler=None, aug_fraction=0.0, lr=None,
                    continue_from=None, schedule_steps=0, keep_state=False):
    """diffusion.train with checkpoints at quarters of the run; a stopped run resumes from the last.

    steps: the step to train to. continue_from: a checkpoint with training state (pi_0 under
    finetune='continue') whose optimizer and step count go on to `steps`; schedule_steps: where the cosine
    ends (0: steps); keep_state: the final file keeps the optimizer state, for runs that continue from it.
    """
    cfg = run.cfg
    first = 0
    if continue_from is not None:
        first = int(load_stage_file(continue_from, torch.load, map_location="cpu",
                                    weights_only=True)["train_state"]["step"])
    part = final_path.replace(".pt", "_step{step}.pt")
    marks = tuple(sorted({first + max(1, (steps - first) * i // 4) for i in (1, 2, 3)} | ({steps} if keep_state else set())))
    warmup = min(500, (schedule_steps or steps) // 10)
    tc = diffusion.TrainConfig(steps=steps, batch_size=cfg.batch_size, lr=lr or cfg.lr, seed=seed,
                               warmup_steps=warmup, schedule_steps=schedule_steps, aug_fraction=aug_fraction,
                               obs_noise=observation_noise(cfg, policy.cfg), log_every=max(1, (steps - first) // 5),
                               checkpoint_steps=marks, checkpoint_path=part)
    resume = next((part.format(step=m) for m in reversed(marks)
                   if m < steps and os.path.exists(part.format(step=m))), None)
    if resume:
        load_stage_file(resume, torch.load, map_location="cpu", weights_only=True)  # a damaged one is named
        run.log(f"  resuming from {os.path.relpath(resume, run.root)}")
    diffusion.train(policy, obs, chunks, tc, sampler=sampler, resume_from=resume,
                    continue_from=None if resume else continue_from, log=lambda m: run.log("  " + m))
    if keep_state:  # the last checkpoint holds the weights and the optimizer: it is the final file
        os.replace(part.format(step=steps), final_path)
    else:
        policy.save(final_path)
    for m in marks:  # the finished checkpoint supersedes the partial ones
        if os.path.exists(part.format(step=m)):
            os.remove(part.format(step=m))
    return policy


def stage_bc(run, demos):
    """Step 1: pi_0 = BC on D0. Under finetune='continue' it is the bc_steps point of a schedule of
    bc_steps + finetune_steps, saved with its optimizer state for the arms to continue."""
    cfg, path = run.cfg, run.path("checkpoints", "bc.pt")
    if os.path.exists(path):
        return load_policy(path, device=cfg.device)
    env = make_run_env(cfg)
    obs, chunks = diffusion.chunk_dataset(demos, cfg.horizon)
    run.log(f"BC: {cfg.bc_steps} steps on {len(obs)} chunks from {len(demos)} demonstrations")
    policy, t0 = make_policy(cfg, env), time.time()
    continuing = cfg.finetune == "continue"
    policy = train_resumable(run, policy, obs, chunks, cfg.bc_steps, stage_seed(cfg, "bc"), path,
                             schedule_steps=cfg.bc_steps + cfg.finetune_steps if continuing else 0,
                             keep_state=continuing)
    run.record_time("bc", time.time() - t0)  # of this process: a resumed run counts its last part only
    return policy


def finetune_from_pi0(run, obs, chunks, seed, path, sampler=None, aug_fraction=0.0):
    """Fine-tune pi_0 (checkpoints/bc.pt) into `path` by cfg.finetune: 'continue' goes on with pi_0's AdamW
    state along its cosine to bc_steps + finetune_steps (the authors' run); 'restart' runs finetune_steps more
    with a fresh optimizer, warm-up and cosine (peak finetune_lr or lr)."""
    cfg, pi0_path = run.cfg, run.path("checkpoints", "bc.pt")
    policy = load_policy(pi0_path, device=cfg.device)
    if cfg.finetune == "continue":
        total = cfg.bc_steps + cfg.finetune_steps
        return train_resumable(run, policy, obs, chunks, total, seed, path, sampler, aug_fraction,
                               continue_from=pi0_path, schedule_steps=total)
    return train_resumable(run, policy, obs, chunks, cfg.finetune_steps, seed, path, sampler, aug_fraction,
                           lr=cfg.finetune_lr)


def stage_bc_row(run, demos, pi0):
    """The table's BC row: under finetune='continue' pi_0 continued on D0 alone to bc_steps + finetune_steps
    (the authors' BC row: their schedule run to its end; every arm gets the same steps), else pi_0 itself.
    Returns (policy, evaluation file)."""
    cfg = run.cfg
    if cfg.finetune != "continue":
        return pi0, run.path("eval", "bc.json")
    path = run.path("checkpoints", "bc_continued.pt")
    if os.path.exists(path):
        return load_policy(path, device=cfg.device), run.path("eval", "bc.json")
    obs, chunks = diffusion.chunk_dataset(demos, cfg.horizon)
    run.log(f"BC row: pi_0 continued on D0 alone, {cfg.finetune_steps} steps (the arms' budget)")
    t0 = time.time()
    policy = finetune_from_pi0(run, obs, chunks, stage_seed(cfg, "train", "bc"), path)
    run.record_time("train_bc", time.time() - t0)
    return policy, run.path("eval", "bc.json")


def stage_bc_row_evaluated(run, demos, pi0):
    """stage_bc_row and its evaluation."""
    policy, path = stage_bc_row(run, demos, pi0)
    stage_evaluate(run, path, policy, "bc (pi_0 continued on D0 alone)" if policy is not pi0 else "bc (pi_0)")


def _bc_row_in_worker(root, cfg_fields):
    """run_experiment's background job: the BC row beside the rounds (one torch thread)."""
    torch.set_num_threads(1)
    cfg = Config(**cfg_fields)
    run = Run(root, cfg)
    stage_bc_row_evaluated(run, load_episodes(run.path("data", "D0.npz")),
                           load_policy(run.path("checkpoints", "bc.pt"), device=cfg.device))


def pi0_eval_path(run):
    """pi_0's evaluation: the table's BC row under finetune='restart', its own file under 'continue'."""
    return run.path("eval", "pi0.json" if run.cfg.finetune == "continue" else "bc.json")


def stage_collect(run, lineage, k, policy, policy_success):
    """Step 2: D_k, HG-DAgger rollouts of the lineage's current policy (PAPER_SETUP.md §4).

    collect_on='eval' (the authors' protocol): the evaluation scenarios, skipping those the policy's own
    evaluation (policy_success, (scenarios, repeats) bool) solved every time; 'train': fresh training
    scenarios. Interventions shorter than H are dropped (Sec. IV-C); episodes without any are not kept.
    """
    cfg, path = run.cfg, run.path(f"lineage_{lineage}", f"round_{k}", "D.npz")
    if os.path.exists(path):
        return load_episodes(path)
    env = make_run_env(cfg)
    if cfg.collect_on == "eval":
        seeds = env.eval_seeds()[: cfg.eval_scenarios]
        solved = np.asarray(policy_success, bool).all(axis=1)
        run.log(f"lineage {lineage} round {k}: HG-DAgger collection on the evaluation scenarios the policy "
                f"does not always solve: {int((~solved).sum())} of {len(seeds)} ({int(solved.sum())} skipped)")
        seeds = np.asarray(seeds)[~solved]
    else:  # fresh scenarios for every (lineage, round), after D0's seed range
        start = cfg.n_demos * 2 + (lineage * cfg.rounds + (k - 1)) * cfg.episodes_per_round
        seeds = env.train_seeds(cfg.episodes_per_round, start=start)
        run.log(f"lineage {lineage} round {k}: HG-DAgger collection on {len(seeds)} fresh training scenarios")
    t0 = time.time()
    env_list = []
    for s in seeds:
        e = make_run_env(cfg)
        e.reset(seed=int(s))
        env_list.append(e)
    gen = torch.Generator(device=policy.device).manual_seed(stage_seed(cfg, "collect", lineage, k))
    episodes = rollout(env_list, policy, cfg.n_act, gen, oracle=make_oracle(cfg, "collect", lineage, k),
                       log=run.log, seed=stage_seed(cfg, "gate", lineage, k)) if env_list else []
    for ep in episodes:
        ep["expert"] = drop_short_interventions(ep["expert"], cfg.horizon)
    kept = [ep for ep in episodes if diffusion.label_mask(ep["expert"], cfg.horizon).any()]
    n_expert = sum(int(ep["expert"].sum()) for ep in kept)
    alone = sum(ep["success"] and ep["interventions"] == 0 for ep in episodes)
    rescued = sum(ep["success"] and ep["interventions"] > 0 for ep in episodes)
    run.log(f"  {len(episodes)} episodes: {alone} solved by the policy alone, {rescued} solved with the "
            f"expert's help, {len(episodes) - alone - rescued} failed; {len(kept)} kept with interventions "
            f">= H, {n_expert} expert steps, {time.time() - t0:.0f} s")
    if not kept:
        raise RuntimeError(f"lineage {lineage} round {k}: no intervention of >= H={cfg.horizon} steps was "
                           f"recorded in {len(episodes)} episodes; nothing to aggregate")
    envs.save_episodes(path, kept)
    run.record_time(f"collect/lineage_{lineage}/round_{k}", time.time() - t0)
    return kept


def stage_calibrate(run, lineage, k, policy, episodes, median_step):
    """Sec. IV-D with the round's HG-DAgger policy on the interventions of rounds 1..k (PAPER_SETUP.md §5)."""
    cfg, path = run.cfg, run.path(f"lineage_{lineage}", f"round_{k}", "calibration.json")
    if os.path.exists(path):
        return calibrate.Calibration.from_dict(read_json(path))
    t0 = time.time()
    ccfg = calibrate.CalibrationConfig(n_samples=cfg.calib_samples, n_act=cfg.n_act,
                                       blend_segments=cfg.calib_blend_episodes,
                                       rollouts_per_beta=cfg.calib_rollouts_per_beta)
    gen = torch.Generator(device=policy.device).manual_seed(stage_seed(cfg, "calibrate", lineage, k))
    cal = calibrate.calibrate(make_run_env(cfg), policy, episodes, median_step, ccfg, gen,
                              log=lambda msg: run.log("  calibration: " + msg))
    run.log(f"lineage {lineage} round {k}: calibration on {len(episodes)} intervention episodes "
            f"({time.time() - t0:.0f} s)\n  " + cal.report().replace("\n", "\n  "))
    write_json(path, cal.to_dict())
    run.record_time(f"calibrate/lineage_{lineage}/round_{k}", time.time() - t0)
    return cal


def noise_model(method, cal, episodes=None, median_step=None, paper_median_step=None):
    """(noise kind, sigma) for relabel.AugmentationSampler. For 'per_step', `episodes` are the indices
    (into the calibrated episode list) of the sampler's episodes, in order.

    'fixed_<s>' is Table I's sigma = s in the paper's median steps (the authors' 0.0176 rad planar, L2 over
    the joints at 30 Hz: envs.paper_median_step), per joint s * paper_median_step rad; the sampler counts
    our median step (median_step, rad), so it gets s * paper_median_step / median_step (fixed_4 planar:
    4 * 0.0176 / 0.0245 = 2.87 of ours = 0.070 rad). Without both units: s of our median steps."""
    if method.startswith("fixed_"):
        sigma = float(method.split("_")[1])  # Table I: sigma in the paper's median steps
        if median_step is None or paper_median_step is None:
            return "isotropic", sigma
        return "isotropic", sigma * paper_median_step / median_step
    if method == "zero_noise":
        return "isotropic", 0.0  # the control: augmented pairs without noise
    if method == "pooled":
        return "pooled", cal.pooled  # Eq. (16)
    if method == "closed_loop":
        return "pooled", cal.closed_loop_pooled if cal.closed_loop_pooled is not None else cal.pooled
    if method == "per_step":  # Eq. (14): each episode's own measured steps
        per_episode = {}
        for j, e in enumerate(episodes if episodes is not None else np.unique(cal.episode_index)):
            rows = cal.episode_index == e
            if rows.any():
                per_episode[j] = (cal.timestep[rows], cal.sigma_alpha[rows])
        return "per_step", per_episode
    raise ValueError(f"method {method!r} adds no noise")


class ChunkSampler:
    """Intervention frames as recorded: (obs, expert chunk) at every valid label start (HG-DAgger's data)."""

    def __init__(self, episodes, H):
        self.obs, self.chunks = diffusion.chunk_dataset(episodes, H)

    def __call__(self, n, rng):
        pick = rng.integers(len(self.obs), size=n)
        return self.obs[pick], self.chunks[pick]


class MixtureSampler:
    """Rows from several rounds' samplers in fixed proportions (the authors: equal). Samplers may return
    (obs, chunks) or (obs, chunks, mask); the mixture returns a mask (all True where a sampler gave none)
    as soon as one of them does."""

    def __init__(self, samplers, weights):
        self.samplers = samplers
        self.p = np.asarray(weights, float) / np.sum(weights)

    def __call__(self, n, rng):
        counts = rng.multinomial(n, self.p)
        parts = [s(c, rng) for s, c in zip(self.samplers, counts) if c > 0]
        obs = np.concatenate([p[0] for p in parts])
        chunks = np.concatenate([p[1] for p in parts])
        if not any(len(p) == 3 for p in parts):
            return obs, chunks
        masks = [p[2] if len(p) == 3 else np.ones(p[1].shape[:2], bool) for p in parts]
        return obs, chunks, np.concatenate(masks)

    def state_dict(self):
        return {str(i): s.state_dict() for i, s in enumerate(self.samplers) if hasattr(s, "state_dict")}

    def load_state_dict(self, state):
        for i, s in enumerate(self.samplers):
            if hasattr(s, "load_state_dict") and str(i) in state:
                s.load_state_dict(state[str(i)])


def intervention_sampler(cfg, method, rounds_data, calibration, stats):
    """The intervention rows of a fine-tuning batch: rounds 1..k in equal shares; HG-DAgger's as recorded, a
    noised method's noised and relabelled (relabel.AugmentationSampler), raw_mix of each round's share as
    recorded."""
    samplers, weights, offset = [], [], 0
    for D in rounds_data:  # equal shares per round; a noised arm takes raw_mix of its round's share as recorded
        if method == "hg_dagger" or cfg.raw_mix > 0:
            samplers.append(ChunkSampler(D, cfg.horizon))
            weights.append(1.0 if method == "hg_dagger" else cfg.raw_mix)
        if method != "hg_dagger":
            kind, sigma = noise_model(method, calibration, range(offset, offset + len(D)), stats.median_step,
                                      stats.paper_median_step)
            samplers.append(relabel.AugmentationSampler(
                D, lambda: make_run_env(cfg), stats, kind, sigma, relabel.RelabelConfig(horizon=cfg.horizon)))
            weights.append(1.0 - cfg.raw_mix)
        offset += len(D)
    return MixtureSampler(samplers, weights)


def stage_train_method(run, lineage, k, method, demos, rounds_data, calibration, stats):
    """Steps 3-4 and 6 (PAPER_SETUP.md §2): fine-tune pi_0 on D0 and, in intervention_fraction of every
    batch, the interventions of rounds 1..k split equally over rounds -- as recorded (HG-DAgger) or every
    drawn frame noised and relabelled with the method's noise (the noised methods); D0 is never noised."""
    cfg = run.cfg
    path = run.path(f"lineage_{lineage}", f"round_{k}", "checkpoints", f"{method}.pt")
    if os.path.exists(path):
        return load_policy(path, device=cfg.device)
    obs, chunks = diffusion.chunk_dataset(demos, cfg.horizon)
    sampler = intervention_sampler(cfg, method, rounds_data, calibration, stats)
    run.log(f"lineage {lineage} round {k}: fine-tune {method} from pi_0, {cfg.finetune_steps} steps, "
            f"{len(obs)} D0 chunks + {cfg.intervention_fraction:.0%} of every batch from the interventions of "
            f"{len(rounds_data)} round(s)" + ("" if method == "hg_dagger" else
                                              f", {1 - cfg.raw_mix:.0%} of them noised and relabelled")
            + (" (continuing pi_0's optimizer and schedule)" if cfg.finetune == "continue" else ""))
    t0 = time.time()
    policy = finetune_from_pi0(run, obs, chunks, stage_seed(cfg, "train", lineage, k, method), path, sampler,
                               cfg.intervention_fraction)
    run.record_time(f"train_{method}/lineage_{lineage}/round_{k}", time.time() - t0)
    return policy


def stage_evaluate(run, path, policy, label):
    """Step 5's numbers: success (scenarios, repeats) bool on the evaluation scenarios (Sec. V; same draws
    for every method), returned; with cfg.eval_unseen the policy is also evaluated on the unseen scenarios,
    never trained on, into unseen_path(path) (not in the paper: under collect_on='eval' HG-DAgger collects on
    the evaluation scenarios, so they are not held out)."""
    ok = evaluate_on(run, path, policy, label, "eval")
    if run.cfg.eval_unseen:
        evaluate_on(run, unseen_path(path), policy, label + ", unseen scenarios", "unseen")
    return ok


def unseen_path(path):
    """The unseen scenarios' file beside an evaluation file: eval/bc.json -> eval/bc_unseen.json."""
    return path[:-len(".json")] + "_unseen.json"


def evaluate_on(run, path, policy, label, scenarios):
    """stage_evaluate on one scenario set, 'eval' (env.eval_seeds) or 'unseen' (env.unseen_seeds): the first
    eval_scenarios of it x eval_repeats, one sampling seed per set shared by every method (paired)."""
    cfg = run.cfg
    if os.path.exists(path):
        return np.asarray(read_json(path)["success"], bool)
    t0 = time.time()
    env = make_run_env(cfg)
    seeds = (env.eval_seeds() if scenarios == "eval" else env.unseen_seeds())[: cfg.eval_scenarios]
    ok = evaluate(policy, cfg.env, seeds, cfg.eval_repeats, cfg.n_act,
                  stage_seed(cfg, "eval" if scenarios == "eval" else "eval_unseen"), env_options(cfg), log=run.log)
    run.log(f"  eval {label}: success {100 * ok.mean():.1f}% "
            f"({ok.size} episodes, {time.time() - t0:.0f} s)")
    write_json(path, {"success": ok.tolist(), "seeds": list(map(int, seeds))})
    run.record_time("evaluate/" + os.path.relpath(path, run.root)[:-len(".json")], time.time() - t0)
    return ok


def run_lineage(run, lineage, demos, stats, workers=1):
    """HG-DAgger rounds of one lineage (PAPER_SETUP.md §4): collect with the lineage's current policy,
    fine-tune HG-DAgger, calibrate with it, fine-tune every noised method, evaluate each (Alg. 2-6).
    workers > 1: the noised methods of a round train side by side in that many processes (run_arms)."""
    cfg = run.cfg
    collector = load_policy(run.path("checkpoints", "bc.pt"), device=cfg.device)
    collector_success = np.asarray(read_json(pi0_eval_path(run))["success"], bool)
    rounds_data = []
    for k in range(1, cfg.rounds + 1):
        rounds_data.append(stage_collect(run, lineage, k, collector, collector_success))
        evals = {}
        hg = stage_train_method(run, lineage, k, "hg_dagger", demos, rounds_data, None, stats)
        evals["hg_dagger"] = stage_evaluate(run, run.path(f"lineage_{lineage}", f"round_{k}", "eval",
                                                          "hg_dagger.json"), hg, f"hg_dagger (lineage {lineage}, K={k})")
        noised = [m for m in cfg.methods if m not in ("bc", "hg_dagger")]
        if noised:
            episodes = [ep for D in rounds_data for ep in D]
            calibration = stage_calibrate(run, lineage, k, hg, episodes, stats.median_step)
        run_arms(run, lineage, k, noised, workers,
                 lambda method: train_and_evaluate(run, lineage, k, method, demos, rounds_data, calibration, stats))
        # the round's HG-DAgger policy collects D_{k+1} (the authors chain their collector's fine-tuning
        # instead: one more policy per round; see benchmarks/README.md)
        collector, collector_success = hg, evals["hg_dagger"]


def train_and_evaluate(run, lineage, k, method, demos, rounds_data, calibration, stats):
    """One arm of round k: fine-tune `method` from pi_0 and evaluate it."""
    policy = stage_train_method(run, lineage, k, method, demos, rounds_data, calibration, stats)
    stage_evaluate(run, run.path(f"lineage_{lineage}", f"round_{k}", "eval", f"{method}.json"),
                   policy, f"{method} (lineage {lineage}, K={k})")


def run_arms(run, lineage, k, methods, workers, arm):
    """arm(method) for every method, in this process, or (workers > 1) in that many worker processes. Every
    stage has its own seed and file, so the numbers do not depend on how many workers ran them."""
    todo = [m for m in methods
            if not os.path.exists(run.path(f"lineage_{lineage}", f"round_{k}", "eval", f"{m}.json"))
            or (run.cfg.eval_unseen and not os.path.exists(
                run.path(f"lineage_{lineage}", f"round_{k}", "eval", f"{m}_unseen.json")))]
    if workers <= 1 or len(todo) <= 1:
        for method in methods:
            arm(method)
        return
    run.log(f"lineage {lineage} round {k}: {len(todo)} arms in {min(workers, len(todo))} worker processes")
    with concurrent.futures.ProcessPoolExecutor(min(workers, len(todo)),
                                                mp_context=multiprocessing.get_context("spawn")) as pool:
        for done in [pool.submit(_arm_in_worker, run.root, asdict(run.cfg), lineage, k, m) for m in todo]:
            done.result()  # re-raises a worker's error here
    for method in methods:  # every file is there now: this only reads them
        arm(method)


def _arm_in_worker(root, cfg_fields, lineage, k, method):
    """run_arms' worker: rebuild what the arm needs from the run folder (one torch thread), then run it."""
    torch.set_num_threads(1)
    cfg = Config(**cfg_fields)
    run = Run(root, cfg)
    demos = load_episodes(run.path("data", "D0.npz"))
    rounds_data = [load_episodes(run.path(f"lineage_{lineage}", f"round_{j}", "D.npz")) for j in range(1, k + 1)]
    calibration = calibrate.Calibration.from_dict(read_json(run.path(f"lineage_{lineage}", f"round_{k}",
                                                                     "calibration.json")))
    train_and_evaluate(run, lineage, k, method, demos, rounds_data, calibration, demo_statistics(cfg, demos))


# ----------------------------------------------------------------------------------------------
# Results: Table I layout, statistics, CSV/JSON, figures
# ----------------------------------------------------------------------------------------------
def collect_results(run, scenarios="eval"):
    """success[method][lineage][k-1] in percent, from every finished evaluation on disk; scenarios 'eval'
    (the evaluation scenarios) or 'unseen' (the unseen ones, files <method>_unseen.json)."""
    cfg = run.cfg
    results = {}
    suffix = "" if scenarios == "eval" else "_unseen"
    bc_path = os.path.join(run.root, "eval", f"bc{suffix}.json")
    if os.path.exists(bc_path):
        results["bc"] = {"all": [100.0 * float(np.mean(read_json(bc_path)["success"]))]}
    for method in cfg.methods:
        if method == "bc":
            continue
        for lineage in range(cfg.lineages):
            row = []
            for k in range(1, cfg.rounds + 1):
                p = os.path.join(run.root, f"lineage_{lineage}", f"round_{k}", "eval", f"{method}{suffix}.json")
                if not os.path.exists(p):
                    break
                row.append(100.0 * float(np.mean(read_json(p)["success"])))
            if row:
                results.setdefault(method, {})[str(lineage)] = row
    return results


def scenario_paired(run, scenarios="eval"):
    """Differences paired over scenarios, in points: per round and lineage, HG-DAgger - BC and every other
    method - HG-DAgger, each the mean over scenarios of the per-scenario success difference (its repeats
    averaged) with the SE over scenarios. What one lineage can say: its scenarios, not its lineages, are the
    repeats. {k: {lineage: {method: {"vs", "diff", "se", "n"}}}}."""
    cfg, suffix = run.cfg, "" if scenarios == "eval" else "_unseen"

    def per_scenario(path):
        return np.asarray(read_json(path)["success"], float).mean(axis=1) if os.path.exists(path) else None

    bc = per_scenario(os.path.join(run.root, "eval", f"bc{suffix}.json"))
    out = {}
    for k in range(1, cfg.rounds + 1):
        for lineage in range(cfg.lineages):
            folder = os.path.join(run.root, f"lineage_{lineage}", f"round_{k}", "eval")
            hg = per_scenario(os.path.join(folder, f"hg_dagger{suffix}.json"))
            if hg is None:
                continue
            pairs = {"hg_dagger": (hg, bc, "bc")} if bc is not None else {}
            for m in cfg.methods:
                if m not in ("bc", "hg_dagger"):
                    mine = per_scenario(os.path.join(folder, f"{m}{suffix}.json"))
                    if mine is not None:
                        pairs[m] = (mine, hg, "hg_dagger")
            for m, (a, b, vs) in pairs.items():
                d = 100.0 * (a - b)
                out.setdefault(str(k), {}).setdefault(str(lineage), {})[m] = {
                    "vs": vs, "diff": float(d.mean()), "se": float(d.std(ddof=1) / math.sqrt(len(d))), "n": len(d)}
    return out


def mean_se(values):
    v = np.asarray(values, float)
    se = v.std(ddof=1) / math.sqrt(v.size) if v.size > 1 else 0.0
    return float(v.mean()), float(se), int(v.size)


def degenerate(a, b):
    """Why a paired test of a vs b has no p-value (the differences have no spread), or None."""
    d = np.asarray(a, float) - np.asarray(b, float)
    if d.size >= 2 and np.all(d == d[0]):
        return (f"every lineage differs by exactly {d[0]:+.1f} points: the paired differences have no spread, "
                "so t and p are undefined")
    return None


def summarize(cfg, results):
    """Per method and round: mean, SE over lineages, count; paired tests averaged over rounds."""
    table = {}
    for method, per_lineage in results.items():
        if method == "bc":
            table[method] = [mean_se(per_lineage["all"])]
            continue
        table[method] = []
        for k in range(cfg.rounds):
            vals = [row[k] for row in per_lineage.values() if len(row) > k]
            table[method].append(mean_se(vals) if vals else None)
    # Paired statistics over lineages that finished every round, each lineage averaged over rounds.
    def round_avg(method):
        rows = results.get(method, {})
        return {l: float(np.mean(r)) for l, r in rows.items() if len(r) == cfg.rounds}

    stats = {"paired_vs_hg_dagger": {}, "tost_vs_best_fixed": {}}
    hg = round_avg("hg_dagger")
    fixed = [m for m in cfg.methods if m.startswith("fixed_") and round_avg(m)]
    best_fixed = max(fixed, key=lambda m: np.mean(list(round_avg(m).values()))) if fixed else None
    stats["best_fixed"] = best_fixed
    for method in cfg.methods:
        if method in ("bc", "hg_dagger"):
            continue
        mine = round_avg(method)
        common = sorted(set(mine) & set(hg))
        if len(common) >= 2:
            t, df, p = paired_ttest([mine[l] for l in common], [hg[l] for l in common])
            stats["paired_vs_hg_dagger"][method] = {
                "diff": float(np.mean([mine[l] - hg[l] for l in common])), "t": t, "df": df, "p": p,
                "degenerate": degenerate([mine[l] for l in common], [hg[l] for l in common])}
        if best_fixed and method in ("pooled", "per_step", "closed_loop"):
            ref = round_avg(best_fixed)
            common = sorted(set(mine) & set(ref))
            if len(common) >= 2:
                p, tl, tu = tost([mine[l] for l in common], [ref[l] for l in common], cfg.tost_margin)
                stats["tost_vs_best_fixed"][method] = {
                    "vs": best_fixed, "diff": float(np.mean([mine[l] - ref[l] for l in common])),
                    "p": p, "margin": cfg.tost_margin,
                    "degenerate": degenerate([mine[l] for l in common], [ref[l] for l in common])}
    # HG-DAgger against BC at every round: one pi_0 for all lineages, so the pairs are (HG_l,k, BC)
    stats["hg_dagger_vs_bc"] = {}
    bc_all = results.get("bc", {}).get("all")
    for k in range(cfg.rounds):
        hg_k = [row[k] for row in results.get("hg_dagger", {}).values() if len(row) > k]
        if bc_all and len(hg_k) >= 2:
            t, df, p = paired_ttest(hg_k, [bc_all[0]] * len(hg_k))
            stats["hg_dagger_vs_bc"][str(k + 1)] = {"diff": float(np.mean(hg_k) - bc_all[0]), "t": t, "df": df,
                                                    "p": p, "n_above": int(sum(v > bc_all[0] for v in hg_k)),
                                                    "n": len(hg_k), "degenerate": degenerate(hg_k, [bc_all[0]] * len(hg_k))}
    # The best fixed sigma of each round in hindsight (beside the calibrated sigma, Sec. V)
    stats["best_fixed_per_round"] = {}
    for k in range(cfg.rounds):
        cells = {m: table[m][k][0] for m in cfg.methods
                 if m.startswith("fixed_") and m in table and table[m][k] is not None}
        if cells:
            stats["best_fixed_per_round"][str(k + 1)] = max(cells, key=cells.get)
    return table, stats


# The paper's calibrated numbers, in its median steps (envs.PAPER_MEDIAN_STEP), set beside ours in that unit: the
# pooled Sigma_bar^alpha's per-joint sigma (paper Sec. VI: "3.9--5.1 median per-step joint displacement in 2D
# planar reacher", "1.3--4.2 median steps in 3D engine lever-reaching") and W (PCD paper/fig_noise_levels/plot.py:
# PLANAR_W = 8.0; LEVER_W 7.94-8.10 over rounds 1-4).
PAPER_CALIBRATION = {"planar": {"sigma": "3.9–5.1", "W": "8.0"}, "engine3d": {"sigma": "1.3–4.2", "W": "7.9–8.1"}}


def calibration_summary(run):
    """Per round: the pooled Sigma_bar^alpha's per-joint sigma and W per lineage, in our median steps
    ('sigma_per_joint', 'W', 'W_ci'), in radians ('..._rad') and in the paper's median steps ('..._paper';
    None where the env has no paper unit)."""
    cfg, out = run.cfg, {}
    paper = envs.paper_median_step(cfg.env)
    in_paper = lambda rad: None if paper is None or rad is None else (np.asarray(rad) / paper).tolist()  # noqa: E731
    for k in range(1, cfg.rounds + 1):
        for lineage in range(cfg.lineages):
            p = os.path.join(run.root, f"lineage_{lineage}", f"round_{k}", "calibration.json")
            if os.path.exists(p):
                c = read_json(p)
                m = c["median_step"]
                ci = c.get("W_ci")
                sigma_rad = np.sqrt(np.diag(np.asarray(c["pooled"], float))).tolist()  # per joint, rad
                out.setdefault(str(k), {})[str(lineage)] = {
                    "sigma_per_joint": [float(v) for v in c["sigma_per_joint"]], "W": c["W"] / m,
                    "W_ci": None if ci is None else [ci[0] / m, ci[1] / m], "fit": c["fit_note"],
                    "kept": int(np.sum(c["blend_kept"])), "rollouts": len(c["blend_kept"]),
                    "median_step": m, "paper_median_step": paper,
                    "sigma_per_joint_rad": sigma_rad, "W_rad": c["W"], "W_ci_rad": ci,
                    "sigma_per_joint_paper": in_paper(sigma_rad), "W_paper": in_paper(c["W"]),
                    "W_ci_paper": in_paper(ci)}
    return out


def stage_times(run):
    """{stage kind: (count, total seconds, mean seconds)} from timings/ (demos, bc, collect, calibrate,
    train_<method>, evaluate)."""
    folder = os.path.join(run.root, "timings")
    kinds = {}
    for name in sorted(os.listdir(folder)) if os.path.isdir(folder) else []:
        t = read_json(os.path.join(folder, name))
        kinds.setdefault(t["stage"].split("/")[0], []).append(t["seconds"])
    return {k: (len(v), float(np.sum(v)), float(np.mean(v))) for k, v in kinds.items()}


def format_cell(cell):
    """'mean ± SE (n)'; a single lineage has no measured spread: 'mean (1)'."""
    if cell is None:
        return "–"
    m, se, n = cell
    return f"{m:.1f} ({n})" if n == 1 else f"{m:.1f} ± {se:.1f} ({n})"


def stat_words(s):
    """t(df) = .., p = .. -- or why there is no p-value."""
    return s["degenerate"] if s.get("degenerate") else f"t({s['df']}) = {s['t']:.2f}, p = {s['p']:.3g}"


def table_rows(cfg, table):
    """The markdown rows of Table I's layout: rows = methods, columns = rounds K, mean +- SE (lineages)."""
    cols = [f"K={k}" for k in range(1, cfg.rounds + 1)]
    lines = ["| Method | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for method in cfg.methods:
        if method not in table:
            continue
        if method == "bc":
            lines.append(f"| {METHOD_LABELS['bc']} | {format_cell(table['bc'][0])}, all K |" + " |" * (len(cols) - 1))
            continue
        cells = [format_cell(c) for c in table[method]]
        lines.append(f"| {METHOD_LABELS[method]} | " + " | ".join(cells) + " |")
    return lines


def scenario_words(cfg, scenarios="eval"):
    """What the table's scenarios are: under collect_on='eval' the evaluation scenarios are the ones HG-DAgger
    collected on (the authors' protocol), not held out; the unseen ones never enter any training data."""
    if scenarios == "unseen":
        return f"{cfg.eval_scenarios} unseen scenarios (never trained on)"
    if cfg.collect_on == "eval":
        return (f"the {cfg.eval_scenarios} evaluation scenarios, on which HG-DAgger collected "
                f"(the authors' protocol)")
    return f"{cfg.eval_scenarios} held-out evaluation scenarios (HG-DAgger collected on fresh training scenarios)"


def format_table(cfg, table, stats, unseen=None):
    """Markdown in Table I's layout: rows = methods, columns = rounds K, mean +- SE (lineages), with the
    paired statistics; unseen: (table, stats) of the same policies on the unseen scenarios, a second table."""
    lines = table_rows(cfg, table)
    lines.append("")
    lines.append(f"Success rate in % on {scenario_words(cfg)} x {cfg.eval_repeats} "
                 f"evaluations; mean ± SE over lineages (count in parentheses; a single lineage has no ±: "
                 f"its spread is not measured). BC is one pi_0 shared by every lineage.")
    lines += paired_lines(cfg, stats)
    if unseen is not None and unseen[0]:
        lines += ["", f"**Unseen scenarios.** The same policies on {scenario_words(cfg, 'unseen')} x "
                      f"{cfg.eval_repeats} evaluations (not in the paper; one sampling seed for every method):", ""]
        lines += table_rows(cfg, unseen[0]) + paired_lines(cfg, unseen[1])
    lines += calibration_lines(cfg, stats)
    if stats.get("stage_times"):
        lines.append("")
        lines.append("Wall time of the stages (s; summed over lineages and rounds; processes ran in parallel):")
        for kind, (n, total, mean) in stats["stage_times"].items():
            lines.append(f"- {kind}: {n} x {mean:.0f} s = {total / 60:.1f} min")
    if not stats["paired_vs_hg_dagger"]:
        lines.append("")
        lines.append("(Paired tests need at least 2 finished lineages.)")
    return "\n".join(lines) + "\n"


def paired_lines(cfg, stats):
    """format_table's paired statistics: each method vs HG-DAgger, TOST vs the best fixed sigma, HG-DAgger vs BC."""
    lines = []
    if stats["paired_vs_hg_dagger"]:
        lines.append("")
        lines.append("Paired t-test vs HG-DAgger (lineages, averaged over rounds):")
        for m, s in stats["paired_vs_hg_dagger"].items():
            lines.append(f"- {METHOD_LABELS[m]}: {s['diff']:+.1f} points, {stat_words(s)}")
    if stats["tost_vs_best_fixed"]:
        lines.append("")
        lines.append(f"TOST equivalence (±{cfg.tost_margin:g} points) vs the best fixed noise in hindsight "
                     f"({stats['best_fixed']}):")
        for m, s in stats["tost_vs_best_fixed"].items():
            lines.append(f"- {METHOD_LABELS[m]}: {s['diff']:+.1f} points, "
                         + (s["degenerate"] if s.get("degenerate") else f"p = {s['p']:.3g}"))
    if stats.get("hg_dagger_vs_bc"):
        lines.append("")
        lines.append("HG-DAgger vs BC at each round (paired over lineages; one pi_0):")
        for k, s in stats["hg_dagger_vs_bc"].items():
            lines.append(f"- K={k}: {s['diff']:+.1f} points, above BC in {s['n_above']} of {s['n']} lineages, "
                         f"{stat_words(s)}")
    lines += scenario_paired_lines(cfg, stats.get("scenario_paired") or {})
    return lines


def scenario_paired_lines(cfg, paired):
    """format_table's differences paired over scenarios (scenario_paired), one line per round: HG-DAgger - BC
    and each arm - HG-DAgger per lineage (mean ± SE over the scenarios); for a single lineage, what it can show."""
    if not paired:
        return []
    lines = ["", f"Paired over the {cfg.eval_scenarios} scenarios (per-scenario success difference, mean ± SE over "
                 f"scenarios; per lineage):"]
    ses = []
    for k, per_lineage in paired.items():
        parts = []
        for m in ["hg_dagger"] + [m for m in cfg.methods if m not in ("bc", "hg_dagger")]:
            cells = [(l, d[m]) for l, d in per_lineage.items() if m in d]
            if not cells:
                continue
            name = "HG-DAgger − BC" if m == "hg_dagger" else f"{m} − HG-DAgger"
            parts.append(name + ": " + ", ".join(f"{s['diff']:+.1f} ± {s['se']:.1f}" for _, s in cells))
            ses += [s["se"] for _, s in cells]
        lines.append(f"- K={k}: " + "; ".join(parts))
    if cfg.lineages == 1 and ses:
        lines.append(f"One lineage shows differences paired over its scenarios only: one beyond about twice its SE "
                     f"(here ±{np.median(ses):.0f} points) is measured, a smaller one is not; the order of the "
                     f"noise arms, a few points apart in the paper, needs lineages (the mid profile).")
    return lines


def calibration_lines(cfg, stats):
    """format_table's calibration: per round the pooled Sigma_bar^alpha's per-joint sigma and W (mean over
    lineages) in our median steps, then in radians and the paper's median steps beside the paper's own
    numbers (PAPER_CALIBRATION: they compare in its unit only), and the best fixed sigma in hindsight."""
    if not stats.get("calibration"):
        return []
    paper = envs.paper_median_step(cfg.env)
    quoted = PAPER_CALIBRATION.get(cfg.env) if paper is not None else None
    lines = ["", "Calibrated pooled Sigma_bar^alpha, per-joint sigma in median steps (mean over lineages), "
                 "beside the best fixed sigma of the round in hindsight"
                 + (" (in the paper's unit)" if paper is not None else "") + "; below each, the "
                 + ("same in radians and in the paper's median steps "
                    f"({paper:.4f} rad, L2 over the joints at 30 Hz), beside the paper's numbers:" if paper is not None
                    else "same in radians (the paper gives no median step for this env):")]
    for k, per in stats["calibration"].items():
        sig = np.mean([v["sigma_per_joint"] for v in per.values()], axis=0)
        W = [v["W"] for v in per.values()]
        best = stats.get("best_fixed_per_round", {}).get(k)
        lines.append(f"- K={k}: sigma = " + ", ".join(f"{x:.2f}" for x in sig)
                     + f" (W = {np.mean(W):.2f} median steps, {len(W)} lineages); best fixed: "
                     + (best.replace("fixed_", "sigma = ") + (" (paper's unit)" if paper is not None else "")
                        if best else "–"))
        sig_rad = np.mean([v["sigma_per_joint_rad"] for v in per.values()], axis=0)  # each lineage's own unit
        W_rad = np.mean([v["W_rad"] for v in per.values()])
        lines.append(f"  - sigma = {calibrate.other_units(sig_rad, paper)}"
                     + (f" (the paper: {quoted['sigma']})" if quoted else "")
                     + f"; W = {calibrate.other_units(W_rad, paper)}"
                     + (f" (the paper: {quoted['W']})" if quoted else ""))
    return lines


def write_report(run):
    """results.json, results.csv, table.md and the success-vs-round figure from what is on disk."""
    cfg = run.cfg
    results = collect_results(run)
    table, stats = summarize(cfg, results)
    stats["calibration"] = calibration_summary(run)
    stats["stage_times"] = stage_times(run)
    stats["scenario_paired"] = scenario_paired(run)
    # the same policies on the unseen scenarios (cfg.eval_unseen), summarized the same way
    results_unseen = collect_results(run, "unseen")
    table_unseen, stats_unseen = summarize(cfg, results_unseen)
    stats_unseen["scenario_paired"] = scenario_paired(run, "unseen")
    write_json(os.path.join(run.root, "results.json"), {"success": results, "stats": stats,
                                                        "success_unseen": results_unseen, "stats_unseen": stats_unseen})
    with open(os.path.join(run.root, "results.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "lineage", "round", "success_pct", "unseen_success_pct"])
        for method, rows in results.items():
            for lineage, row in rows.items():
                unseen = results_unseen.get(method, {}).get(lineage, [])
                for k, v in enumerate(row, start=1):
                    w.writerow([method, lineage, "all" if method == "bc" else k, f"{v:.2f}",
                                f"{unseen[k - 1]:.2f}" if len(unseen) >= k else ""])
    text = format_table(cfg, table, stats, (table_unseen, stats_unseen))
    with open(os.path.join(run.root, "table.md"), "w") as f:
        f.write(text)
    plot_success_vs_round(cfg, table, run.path("figures", "success_vs_round.png"))
    plot_table(cfg, table, run.path("figures", "table_i.png"))
    return text


def plot_policy_view(env, episode, path, n_frames=4):
    """What an image policy sees: the camera image inside the observations of one demonstration, at a few
    steps from start to goal, beside the same camera at full resolution (engine3d with image_obs)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    steps = np.linspace(0, len(episode["obs"]) - 1, n_frames).round().astype(int)
    fig, axes = plt.subplots(1, n_frames + 1, figsize=(2.6 * (n_frames + 1), 2.8))
    axes[0].imshow(env.camera_image(episode["q"][0], 320, 320))
    axes[0].set_title("camera, 320 x 320")
    size = env.image_shape[1]
    for ax, t in zip(axes[1:], steps):
        ax.imshow(env.obs_image(episode["obs"][t]), interpolation="nearest")
        ax.set_title(f"policy input, step {t}\n{size} x {size}")
    for ax in axes:
        ax.axis("off")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_success_vs_round(cfg, table, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.5, 4))
    ks = np.arange(1, cfg.rounds + 1)
    for method in cfg.methods:
        if method not in table:
            continue
        if method == "bc":
            ax.axhline(table["bc"][0][0], color="k", ls=":", label=METHOD_LABELS["bc"])
            continue
        cells = table[method]
        xs = [k for k, c in zip(ks, cells) if c]
        if not xs:
            continue
        m = np.array([c[0] for c in cells if c])
        se = np.array([c[1] for c in cells if c])
        i = list(cfg.methods).index(method)
        xs = np.array(xs, float) + 0.04 * (i - len(cfg.methods) / 2)  # side by side, not on top of each other
        style = "-o" if method in ("pooled", "per_step", "closed_loop") else ("-s" if method == "hg_dagger" else "--.")
        ax.errorbar(xs, m, yerr=se, fmt=style, capsize=3, label=METHOD_LABELS[method])
    ax.set_xlabel("DAgger round K")
    ax.set_ylabel("success rate [%]")
    ax.set_xticks(ks)
    ax.set_xlim(0.6, cfg.rounds + 0.4)
    ax.set_title(f"Success vs round ({cfg.env}, the data of Table I)")
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5), frameon=False)  # outside the data
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)


def plot_table(cfg, table, path):
    """Table I (II for engine3d) as the paper draws it: rows = methods, columns = rounds, each cell shaded
    by its mean success ("darker colors denote higher success") and labelled mean ± SE (n); the best
    cell of each round is boxed and bold."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    rows = [m for m in cfg.methods if m in table]
    R, C = len(rows), cfg.rounds
    means = np.full((R, C), np.nan)
    for i, m in enumerate(rows):
        for k in range(C):
            cell = table[m][0] if m == "bc" else table[m][k]
            if cell is not None:
                means[i, k] = cell[0]
    width, height = 3.7 + 1.9 * C, 1.0 + 0.42 * R  # inches: method labels, one column per round
    fig, ax = plt.subplots(figsize=(width, height))
    lo, hi = np.nanmin(means) if np.isfinite(means).any() else 0, np.nanmax(means) if np.isfinite(means).any() else 1
    shade = lambda v: plt.cm.Blues(0.15 + 0.7 * (v - lo) / max(hi - lo, 1e-9))  # noqa: E731
    best = [int(np.nanargmax(means[:, k])) if np.isfinite(means[:, k]).any() else -1 for k in range(C)]
    for i, m in enumerate(rows):
        for k in range(C):
            v = means[i, k]
            if m == "bc" and k > 0:
                continue  # one pi_0 for every round: one cell across the row
            span = C if m == "bc" else 1
            color = shade(v) if np.isfinite(v) else (1, 1, 1, 1)
            ax.add_patch(Rectangle((k, R - 1 - i), span, 1, facecolor=color, edgecolor="white", lw=2))
            cell = table[m][0] if m == "bc" else table[m][k]
            text = format_cell(cell) + (", all K" if m == "bc" else "")
            dark = np.isfinite(v) and (v - lo) / max(hi - lo, 1e-9) > 0.6
            is_best = m != "bc" and best[k] == i
            ax.text(k + span / 2, R - 0.5 - i, text, ha="center", va="center", fontsize=9,
                    color="white" if dark else "black", fontweight="bold" if is_best else "normal")
            if is_best:
                ax.add_patch(Rectangle((k + 0.03, R - 1 - i + 0.06), 0.94, 0.88, fill=False, edgecolor="#d55e00", lw=2))
    ax.set_xlim(0, C)
    ax.set_ylim(0, R)
    ax.set_xticks(np.arange(C) + 0.5, [f"K = {k}" for k in range(1, C + 1)])
    ax.xaxis.tick_top()
    ax.set_yticks(R - 0.5 - np.arange(R), [METHOD_LABELS[m] for m in rows])
    ax.tick_params(length=0)
    for side in ax.spines.values():
        side.set_visible(False)
    name = "Table II" if cfg.env == "engine3d" else "Table I"
    fig.text(0.5, 1 - 0.1 / height, f"{name} analogue: success rate [%], mean ± SE (n lineages)\n"
             f"darker = higher; boxed = the best of its round", ha="center", va="top", fontsize=9)
    fig.subplots_adjust(left=3.5 / width, right=1 - 0.1 / width, top=1 - 0.85 / height, bottom=0.05 / height)
    fig.savefig(path, dpi=150)
    plt.close(fig)


FIGURE_CAPTIONS = {
    "table_i.png": "Table I as the paper draws it: rows are methods, columns DAgger rounds, cells shaded by "
                   "mean success; the boxed cell is the best of its round.",
    "success_vs_round.png": "The same numbers as lines: does each method improve with more rounds of "
                            "interventions, and where does it sit against BC (dotted)?",
    "fig1_recovery.png": "Fig. 1: the expert path (blue), the calibrated noise Sigma^alpha at a few states "
                         "(ellipses), and recovery chunks from noised states back to the path (orange).",
    "fig2_method_overview.png": "Fig. 2: (a) open-loop Sigma_hat along expert data, (b) blended rollouts, "
                                "(c) per-step Sigma^alpha, (d) pooled Sigma_bar^alpha.",
    "fig3_partial_denoising.png": "Fig. 3: partial denoising at one state: the larger the blend ratio beta, "
                                  "the more the sampled chunks follow the policy instead of the expert.",
    "fig4_blend_fit.png": "Fig. 4: settling error of the blended rollouts against sigma^2_k_sw with the "
                          "fitted equilibrium curve; its value at 1 is W, with a bootstrap interval (left axis: our "
                          "median steps; right axis: the paper's, where its W = 8.0 planar reads).",
    "fig5_environment.png": "Fig. 5: a scenario of the environment with an oracle demonstration.",
    "fig5_policy_view.png": "What the image policy sees: its camera input at a few steps of a demonstration.",
}


def figure_caption(name, cfg):
    """FIGURE_CAPTIONS[name], said for the run's env (Table II and the top view for the UR5)."""
    caption = FIGURE_CAPTIONS[name]
    if cfg.env == "engine3d":
        caption = caption.replace("Table I as", "Table II as")
        if name[:4] in ("fig1", "fig2", "fig3"):
            caption += " The UR5's end effector is drawn in the top view (x, y in m)."
    return caption


def write_markdown_report(run, text, stats):
    """report.md: the run folder readable on its own -- the table, the statistics in words, every figure
    with a one-line caption of what to see."""
    cfg = run.cfg
    lines = [f"# {cfg.name}: Policy-Calibrated DAgger on the {cfg.env} env", "",
             f"Profile settings: {cfg.n_demos} demonstrations, BC {cfg.bc_steps} steps, {cfg.rounds} round(s), "
             f"{cfg.lineages} lineage(s), fine-tuning {cfg.finetune_steps} steps per cell, interventions "
             f"collected on the {'evaluation' if cfg.collect_on == 'eval' else 'fresh training'} scenarios"
             + (" (the paper's protocol: the evaluation scenarios enter the training data)" if cfg.collect_on == "eval"
                else "")
             + (f"; every policy is also evaluated on {scenario_words(cfg, 'unseen')}" if cfg.eval_unseen else "")
             + ".", "", "## Table", "", text.rstrip(), ""]
    words = paired_words(stats)
    if words:
        lines += ["## The paired statistics in words", ""] + words + [""]
    results_path = os.path.join(run.root, "results.json")
    unseen = read_json(results_path).get("stats_unseen") if os.path.exists(results_path) else None
    words = paired_words(unseen or {})
    if words:
        lines += [f"On {scenario_words(cfg, 'unseen')}:", ""] + words + [""]
    figures = [f for f in FIGURE_CAPTIONS if os.path.exists(os.path.join(run.root, "figures", f))]
    if figures:
        lines += ["## Figures", ""]
        for f in figures:
            lines += [f"**{f}** — {figure_caption(f, cfg)}", "", f"![{f}](figures/{f})", ""]
    with open(os.path.join(run.root, "report.md"), "w") as fh:
        fh.write("\n".join(lines))


def paired_words(stats):
    """report.md's sentences for the paired statistics: each method vs HG-DAgger, TOST vs the best fixed sigma."""
    words = []
    for m, s in stats.get("paired_vs_hg_dagger", {}).items():
        words.append(f"- {METHOD_LABELS[m]} − HG-DAgger = {s['diff']:+.1f} points averaged over rounds, "
                     + stat_words(s) + ".")
    for m, s in stats.get("tost_vs_best_fixed", {}).items():
        words.append(f"- {METHOD_LABELS[m]} against the best fixed noise in hindsight ({s['vs']}): "
                     f"{s['diff']:+.1f} points; " + (s["degenerate"] if s.get("degenerate") else
                     f"TOST at ±{s['margin']:g} points, p = {s['p']:.3g} "
                     + ("(equivalent at 5 %)" if s["p"] < 0.05 else "(equivalence not shown)")) + ".")
    return words


def make_figures(run, demos, stats):
    """fig1-fig5 (the paper's analogues) from lineage 0, round 1 (skipped figures are logged)."""
    cfg = run.cfg
    fig = lambda name: run.path("figures", name)  # noqa: E731
    env = make_run_env(cfg)
    rdir = os.path.join(run.root, "lineage_0", "round_1")
    if env.dim == 2:  # fig5: the planar scene drawn with a demonstration; the UR5's scene rendered by pybullet
        oracle_mod.plot_demonstration(env, demos[0], fig("fig5_environment.png"))
    else:
        env.reset(seed=int(demos[0]["seed"]))
        envs.render_scene_image(env, fig("fig5_environment.png"))
        if cfg.image_obs:
            plot_policy_view(env, demos[0], fig("fig5_policy_view.png"))
    if not os.path.exists(os.path.join(rdir, "calibration.json")):
        run.log("figures 1-4 need lineage 0 round 1: not finished yet")
        return
    D1 = load_episodes(os.path.join(rdir, "D.npz"))
    cal = calibrate.Calibration.from_dict(read_json(os.path.join(rdir, "calibration.json")))
    # the policy that was calibrated: the round's HG-DAgger policy (PAPER_SETUP.md §5)
    calibrated = os.path.join(rdir, "checkpoints", "hg_dagger.pt")
    policy = load_policy(calibrated if os.path.exists(calibrated) else run.path("checkpoints", "bc.pt"),
                         device=cfg.device)
    gen = lambda: torch.Generator(device=policy.device).manual_seed(stage_seed(cfg, "figures"))  # noqa: E731
    # the episode with the longest intervention shows the method best
    e = int(np.argmax([ep["expert"].sum() for ep in D1]))
    episode = D1[e]
    calibrate.plot_blend_fit(cal, stats.median_step, fig("fig4_blend_fit.png"))
    # figs 1-3 draw end-effector paths: in the plane of the planar env, in the top view (x, y) of the UR5's
    calibrate.plot_method_overview(env, episode, cal, policy, fig("fig2_method_overview.png"),
                                   generator=gen())
    relabel.plot_recovery(env, episode, cal.pooled, fig("fig1_recovery.png"),
                          np.random.default_rng(stage_seed(cfg, "fig1")), stats)
    t = int(np.flatnonzero(diffusion.label_mask(episode["expert"], cfg.horizon))[0])
    end = min(t + cfg.horizon, len(episode["action"]))
    chunk = episode["action"][t:end]
    chunk = np.concatenate([chunk, np.repeat(chunk[-1:], cfg.horizon - len(chunk), axis=0)])
    env.reset(seed=int(episode["seed"]))
    partial_denoise.plot_partial_denoising(env, policy, episode["obs"][t], chunk, (0.1, 0.3, 0.5, 0.7),
                                           fig("fig3_partial_denoising.png"), gen(),
                                           q=episode["q"][t])


# ==== Beyond the paper (safe to skip) ====================================================
# The run folder: every stage's result on disk before the next starts (atomic writes), so a stopped run
# resumes; a folder remembers its config; a damaged stage file is named. Then the command line.

# ----------------------------------------------------------------------------------------------
# Run folder: stages, atomic writes, log
# ----------------------------------------------------------------------------------------------
class ConfigMismatch(ValueError):
    """A run folder holds a run with another config (stages could not be reused honestly)."""


class RunFolderError(ValueError):
    """The run folder cannot be created (a bad --out), or one of its stage files is damaged."""


# Config fields a run folder lets differ from the config it was made with: they change no stage's result
# (device: where it computes; eval_unseen only adds evaluations; more lineages only add lineage folders, and no
# seed depends on their number). Any other difference is refused (ConfigMismatch).
FOLDER_FREE_FIELDS = ("device", "eval_unseen", "lineages")


class Run:
    """runs/<name>/: config.json, log.txt, data/, checkpoints/, lineage_<l>/round_<k>/, figures/."""

    def __init__(self, root, cfg: Config):
        self.root, self.cfg = root, cfg
        try:
            os.makedirs(root, exist_ok=True)
            open(os.path.join(root, "log.txt"), "a").close()
        except OSError as err:
            raise RunFolderError(f"cannot use {root!r} as the run folder: {err.strerror or err}. Give --out a "
                                 "folder you can create and write (default runs/<profile>).") from None
        path = os.path.join(root, "config.json")
        saved = asdict(cfg)
        if os.path.exists(path):
            old = read_json(path)
            for key in ("methods", "down_dims"):  # JSON keeps tuples as lists
                if key in old:
                    old[key] = tuple(old[key])
                saved[key] = tuple(saved[key])
            # a field added after the run started counts as unchanged if it has its default value
            defaults = {f.name: f.default for f in fields(Config)}
            changed = {k for k in saved if k not in FOLDER_FREE_FIELDS and old.get(k, defaults[k]) != saved[k]}
            if changed:
                raise ConfigMismatch(
                    f"{root} holds a run made with another config: "
                    + ", ".join(f"{k} = {old.get(k, defaults[k])!r} there, {saved[k]!r} now" for k in sorted(changed))
                    + f".\nEither give this run its own folder (--out runs/<new name>), or delete {root} "
                      "to start it afresh (its finished stages are lost).")
            if cfg.lineages > old.get("lineages", 1):  # the folder now holds (or will hold) this many lineages
                write_json(path, {**old, "lineages": cfg.lineages})
        else:
            write_json(path, asdict(cfg))
        self._log = open(os.path.join(root, "log.txt"), "a")

    def path(self, *parts):
        p = os.path.join(self.root, *parts)
        os.makedirs(os.path.dirname(p), exist_ok=True)
        return p

    def record_time(self, stage, seconds):
        """Wall time of a finished stage, one file per stage (parallel lineages never write the same file)."""
        write_json(self.path("timings", stage.replace("/", "__") + ".json"), {"stage": stage, "seconds": seconds})

    def log(self, msg):
        line = f"[{time.strftime('%H:%M:%S')}] {msg}"
        print(line, flush=True)
        self._log.write(line + "\n")
        self._log.flush()


def write_json(path, data):
    tmp = f"{path}.{os.getpid()}.tmp"  # per process: parallel lineages (--lineage i) write the same report
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)  # a stage is finished only when its file is complete


def load_stage_file(path, loader, *args, **kwargs):
    """loader(path) for a finished stage's file; a damaged file (truncated, not what it should be) is an error
    that names it and says how to re-make it, never a raw EOFError or a silently reused stage."""
    try:
        return loader(path, *args, **kwargs)
    except (FileNotFoundError, KeyboardInterrupt):
        raise
    except Exception as err:
        why = ("truncated, or not a checkpoint" if isinstance(err, diffusion.CheckpointDamagedError)  # it says so
               else f"{type(err).__name__}: {err}")
        raise RunFolderError(f"{path} is damaged ({why}). Delete it and run the same "
                             "command again: that stage is made again, the other finished stages are kept.") from None


def _read_json(path):
    with open(path) as f:
        return json.load(f)


def read_json(path):
    return load_stage_file(path, _read_json)


def load_episodes(path):
    return load_stage_file(path, envs.load_episodes)


def load_policy(path, device):
    return load_stage_file(path, diffusion.DiffusionPolicy.load, device=device)


def stage_seed(cfg, *keys):
    """A seed for one stage, derived from the master seed and the stage's name (stable across runs)."""
    return int(np.random.SeedSequence([cfg.seed, *[_key_int(k) for k in keys]]).generate_state(1)[0])


def _key_int(key):
    return key if isinstance(key, int) else int.from_bytes(str(key).encode()[:8].ljust(8, b"\0"), "little")


# ----------------------------------------------------------------------------------------------
# Entry point
# ----------------------------------------------------------------------------------------------
def parse_args(argv):
    p = argparse.ArgumentParser(
        description="Policy-Calibrated DAgger end to end (Wang & Kantor): data, BC, HG-DAgger rounds, "
                    "calibration, augmentation, every method of Table I, evaluation, table and figures.")
    p.add_argument("--profile", default="quick", choices=sorted(PROFILES),
                   help="run size: smoke (CI, ~1 min), quick (default: 9 min 14 s wall measured on a 2-core CPU "
                        "machine with 2 worker processes), mid (Table I's analogue: 500 demos, 5 lineages x 2 "
                        "rounds, hours on 2 cores), table2 (the engine-lever env with Table II's rows), paper "
                        "(Table I protocol at the authors' sizes)")
    p.add_argument("--env", default=None, choices=sorted(envs.ENVIRONMENTS), help="environment (default planar)")
    p.add_argument("--image-obs", action="store_true",
                   help="engine3d: the policy sees a camera image through a small CNN instead of the obstacle list")
    p.add_argument("--start", default=None, choices=sorted(set(envs.ENGINE_STARTS) | set(envs.PLANAR_STARTS)),
                   help="where episodes start: random (the authors', uniform and collision-free), fixed (planar: "
                        "their demonstration config's q) or home (engine3d: near a home pose)")
    p.add_argument("--goal-angle", type=float, default=None, metavar="DEG",
                   help="engine3d: success also needs the tool within DEG degrees of the goal posture's "
                        "orientation (the authors' rule: 10), and the oracle ends at that posture")
    p.add_argument("--methods", default=None,
                   help=f"comma-separated subset of: {','.join(ALL_METHODS)} (BC and HG-DAgger always run)")
    p.add_argument("--collect-on", default=None, choices=("eval", "train"),
                   help="where HG-DAgger collects: eval (default, the paper's protocol: the evaluation scenarios "
                        "the policy does not solve, so they enter the training data) or train (fresh training "
                        "scenarios, the stricter variant)")
    p.add_argument("--rounds", type=int, default=None, help="HG-DAgger rounds K")
    p.add_argument("--lineages", type=int, default=None, help="number of lineages")
    p.add_argument("--lineage", type=int, default=None,
                   help="run only this lineage (0-based), e.g. as one task of a cluster job array")
    p.add_argument("--prepare", action="store_true", help="only the shared stages: D0, BC and its evaluation")
    p.add_argument("--seed", type=int, default=None, help="master seed")
    p.add_argument("--device", default=None, help="torch device: cpu (default) or cuda")
    p.add_argument("--out", default=None, help="run folder (default runs/<profile>[_<env>])")
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default 1: the networks are small, and more threads than free "
                        "cores slow torch down many times on a shared machine)")
    p.add_argument("--workers", type=int, default=None,
                   help="processes for the arms of a round (and the BC row beside the rounds); default: 2 where "
                        "the machine has 2 cores or more, 1 with --lineage (lineages side by side use the cores)")
    p.add_argument("--report", action="store_true", help="merge finished lineages into the table and figures")
    p.add_argument("--no-eval-unseen", action="store_true",
                   help="skip the second evaluation of every policy on the unseen scenarios (never trained on)")
    args = p.parse_args(argv)
    cfg = PROFILES[args.profile]
    over = {}
    if args.env:
        over["env"] = args.env
    if args.methods:
        names = [m.strip() for m in args.methods.split(",")]
        if not all(names):
            p.error(f"--methods {args.methods!r}: an empty item; give comma-separated names, e.g. "
                    f"hg_dagger,fixed_4,pooled (valid: {', '.join(ALL_METHODS)})")
        dup = sorted({m for m in names if names.count(m) > 1})
        if dup:
            p.error(f"--methods {args.methods!r}: {', '.join(dup)} listed twice; name each method once")
        bad = [m for m in names if m not in ALL_METHODS]
        if bad:
            p.error(f"--methods: unknown {bad}; valid choices: {', '.join(ALL_METHODS)}")
        over["methods"] = tuple(names)
    if args.image_obs:
        over["image_obs"] = True
    if args.start:
        over["start"] = args.start
    if args.goal_angle is not None:
        over["goal_angle"] = args.goal_angle
    if args.collect_on:
        over["collect_on"] = args.collect_on
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
    env = over.get("env", cfg.env)
    name = cfg.name + ("" if env == cfg.env else f"_{env}")  # another env than the profile's: own folder
    name += "_images" if args.image_obs else ""
    name += f"_{args.start}_start" if args.start else ""
    name += f"_goal_angle{args.goal_angle:g}" if args.goal_angle is not None else ""
    name += "_collect_train" if over.get("collect_on", cfg.collect_on) == "train" else ""
    if "methods" in over and set(over["methods"]) | {"bc", "hg_dagger"} != set(cfg.methods):
        name += "_" + "-".join(over["methods"])  # another set of methods gets its own folder
    over["name"] = name
    try:
        cfg = replace(cfg, **over)
    except ValueError as err:
        p.error(str(err))
    if args.threads < 1:
        p.error(f"--threads {args.threads}: must be >= 1")
    if args.workers is None:
        args.workers = 1 if args.lineage is not None else min(2, os.cpu_count() or 1)
    if args.workers < 1:
        p.error(f"--workers {args.workers}: must be >= 1")
    if args.lineage is not None and not 0 <= args.lineage < cfg.lineages:
        p.error(f"--lineage {args.lineage}: valid lineages are 0..{cfg.lineages - 1}")
    return args, cfg


def run_experiment(cfg, root, lineage=None, prepare=False, report_only=False, workers=1):
    """The whole method for one config into run folder `root` (resuming whatever is already there).

    lineage: run only this lineage (the shared D0 and BC stages first, if missing);
    prepare: only the shared stages (D0, BC, the BC row and their evaluations); report_only: only the report;
    workers: processes for the arms of a round (and, under finetune='continue', the BC row beside the rounds).
    """
    run = Run(root, cfg)
    t0 = time.time()
    if not report_only:
        run.log(f"Policy-Calibrated DAgger, env {cfg.env}, folder {run.root}, {workers} worker process(es)")
        demos = stage_demos(run)
        bc = stage_bc(run, demos)
        background = None
        if cfg.finetune == "continue":  # pi_0's own evaluation picks round 1's scenarios (the BC row's, else)
            evaluate_on(run, pi0_eval_path(run), bc, "pi_0 (BC)", "eval")
        if cfg.finetune == "continue" and workers > 1 and not prepare:  # the BC row trains beside the rounds
            background = concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
            bc_row_done = background.submit(_bc_row_in_worker, run.root, asdict(cfg))
        else:
            stage_bc_row_evaluated(run, demos, bc)
        if not prepare:
            stats = demo_statistics(cfg, demos)
            for l in ([lineage] if lineage is not None else range(cfg.lineages)):
                run_lineage(run, l, demos, stats, workers)
        if background is not None:
            bc_row_done.result()
            background.shutdown()
    demos = load_episodes(run.path("data", "D0.npz"))
    text = write_report(run)
    make_figures(run, demos, demo_statistics(cfg, demos))
    write_markdown_report(run, text, read_json(os.path.join(run.root, "results.json"))["stats"])
    run.log(f"done in {time.time() - t0:.0f} s; report.md, table, results and figures in {run.root}\n\n{text}")
    return run.root


def demo_statistics(cfg, demos):
    """The base demonstrations' median step (the unit of noise) and speed/acceleration limits, with the env's
    units for what the authors set in theirs (the paper's median step; their 30 Hz frames per env step)."""
    env = make_run_env(cfg)
    return relabel.demo_stats(demos, envs.median_step(demos), env.max_step,
                              paper_median_step=envs.paper_median_step(cfg.env),
                              frames_per_step=env.dt / envs.PAPER_FRAME_DT)


def main(argv=None):
    args, cfg = parse_args(sys.argv[1:] if argv is None else argv)
    torch.set_num_threads(args.threads)
    try:
        return run_experiment(cfg, args.out or os.path.join("runs", cfg.name), lineage=args.lineage,
                              prepare=args.prepare, report_only=args.report, workers=args.workers)
    except KeyboardInterrupt:
        print("\nstopped; the finished stages are saved: run the same command again to resume", file=sys.stderr)
        sys.exit(130)
    except (ConfigMismatch, RunFolderError) as err:
        print(f"dagger.py: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
