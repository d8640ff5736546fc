"""Policy-Calibrated DAgger end to end: the paper's loop (Sec. IV-A), evaluation and Table I's statistics.

Read `policy_calibrated_dagger` first: Sec. IV-A, steps 1-6, one call per step; below it the config, each step's
function in the loop's order, Table I's tests and the entry point.

Paper map (the paper):
  Sec. IV-A step 1 ......... oracle_demonstrations (D0), behavior_cloning (pi_0)
  Sec. IV-A step 2, Sec. V . collect_interventions / rollout: HG-DAgger collection gated by the RRT oracle
                             (oracle.Gate); interventions shorter than H are discarded (Sec. IV-C)
  Sec. IV-D ................ calibrate_noise -> calibrate.calibrate, once per round with the HG-DAgger policy
  Sec. IV-A steps 3-6, IV-E  fine_tune, intervention_sampler, noise_model -> relabel.AugmentationSampler
  Sec. V, Tables I and II .. evaluate (100 scenarios x 3 evaluations, batched), paired_ttest, tost

Each step is a function of its inputs (config values, data, policies, an optional `log`) that returns what it
makes, and the loop returns everything it made (Made): call it, or one step, in a notebook with your own inputs.
This file imports only the concept modules. The harness in experiment/ (a student may skip it; its __init__.py
lists it) wraps the loop from above: the run folder that keeps each step's result in its file and resumes (the
loop's `memo`), worker processes (its `map`), the command line and profiles, Table I's assembly and report.md,
the CPU kernels it swaps into a policy before training, and the research variants, which hand the loop their own
functions (an env factory, a learning-rate function, a label rule, a sampler, a BC row).

Usage: `python dagger.py` (the quick profile), `--profile smoke` (CI), `--help`; README.md, "Profiles and options".
"""
from __future__ import annotations

import copy
import functools
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

import calibrate
import diffusion
import envs
import oracle as oracle_mod
import relabel


# ---- The loop: Sec. IV-A, steps 1-6 ------------------------------------------------------------------------------
def policy_calibrated_dagger(cfg, lineages=None, memo=None, map=None, log=print, make_env=envs.make_env,
                             lr_schedule=diffusion.warmup_cosine, label_rule=diffusion.expert_runs, sampler=None,
                             bc_row=None):
    """Sec. IV-A's steps 1-6 for the given lineages (default all cfg.lineages; an empty list: the shared step 1
    only); returns what it made (Made). Without memo and map every step is a plain call, one after the other (a
    notebook: no folder). The harness hands in its own: memo(name, step, *args, **kw) keeps a step's result in the
    run folder's file `name` and resumes from it; map(fn, jobs), fn(*job) for each job in order, runs them in
    worker processes (a round's arms, the BC row). The paper's pieces by default; a variant (experiment/) hands in
    its own: make_env(name) an env, lr_schedule(step, train_cfg) the learning rate, label_rule(expert, H) the
    interventions D_k keeps, sampler (as intervention_sampler) a row's intervention rows, bc_row (as bc_row_arm)."""
    memo, map = memo or compute, map or one_after_another
    sampler, bc_row = sampler or intervention_sampler, bc_row or bc_row_arm
    lineages = range(cfg.lineages) if lineages is None else lineages
    # Step 1: D0, oracle demonstrations on training scenarios (Sec. V: a self-written RRT expert) ...
    demos = memo("data/D0.npz", oracle_demonstrations, cfg, map=map, log=log, make_env=make_env)
    stats = demo_statistics(cfg, demos, make_env)  # D0's median step: the unit of every noise level (Sec. V)
    # ... and pi_0 = BC on D0: every method of every round is fine-tuned from this checkpoint (step 6)
    pi0 = memo("checkpoints/bc.pt", behavior_cloning, cfg, demos, log=log, make_env=make_env, lr_schedule=lr_schedule)
    pi0_success = evaluate_policy(memo, cfg, "eval/pi0.json", pi0, "pi_0 (BC)", log, unseen=False, make_env=make_env)
    made = Made(demos, stats, pi0, pi0_success)
    # Table I's BC row: pi_0 trained on D0 alone for the arms' step budget (beside the rounds where map runs it so)
    bc = map(bc_row, [(cfg, demos, pi0, memo, log, make_env, lr_schedule)])
    noised = [m for m in cfg.methods if m not in ("bc", "hg_dagger", "closed_loop")]
    arm = (make_env, lr_schedule, sampler)  # how every row trains and is evaluated (train_and_evaluate's last three)
    for lineage in lineages:  # independent repeats of steps 2-6 from the same pi_0 (Table I: mean ± SE)
        collector, collector_success, rounds_data, calibrations = pi0, pi0_success, [], []
        chain = None  # the closed-loop row's own chain of rounds: its interventions and its latest policy
        for k in range(1, cfg.rounds + 1):  # step 5: repeat steps 2-4 for every round of aggregation
            # Step 2: HG-DAgger -- the lineage's policy drives, the oracle takes over when its gate says so;
            # D_k = the interventions of at least H steps (Sec. IV-C), aggregated with D0 and D_1..D_{k-1}
            rounds_data.append(memo(f"{folder(lineage, k)}/D.npz", collect_interventions, cfg, (lineage, k),
                                    collector, collector_success, log=log, make_env=make_env, label_rule=label_rule))
            made.data[lineage, k] = rounds_data[-1]
            # Steps 4 and 6 without noise, the HG-DAgger row: pi_0 fine-tuned on D0 and D_1..D_k as recorded
            hg, hg_success = train_and_evaluate(cfg, lineage, k, "hg_dagger", demos, pi0, rounds_data, None, stats,
                                                memo, log, *arm)
            made.rows[lineage, k, "hg_dagger"] = hg, hg_success
            if noised or "closed_loop" in cfg.methods:
                # Step 3's noise, measured from the HG-DAgger policy (Sec. IV-D): Sigma_hat along the
                # interventions (Eq. 1), W from blended rollouts (Eqs. 8-12), Sigma^alpha (Eqs. 13-16)
                calibrations.append(memo(f"{folder(lineage, k)}/calibration.json", calibrate_noise, cfg, (lineage, k),
                                         hg, rounds_data, stats, log=log, make_env=make_env))
                made.calibrations[lineage, k] = calibrations[-1]
                # Steps 3, 4 and 6 for every noised row: D_1..D_k noised and relabelled on the fly (Sec. IV-E),
                # co-trained with D0, fine-tuned from pi_0, evaluated (Sec. V)
                rows = list(map(train_and_evaluate, [(cfg, lineage, k, method, demos, pi0, rounds_data,
                                                      calibrations[-1], stats, memo, log, *arm) for method in noised]))
                made.rows.update({(lineage, k, method): row for method, row in zip(noised, rows)})
            # the round's HG-DAgger policy collects D_{k+1} (the authors chain their collector's fine-tuning
            # instead: one more policy per round; see benchmarks/README.md)
            collector, collector_success = hg, hg_success
            if "closed_loop" in cfg.methods:
                # Table I's closed-loop pooled row: steps 2-5 read literally, its own chain from round 1's data
                # and noise; its round k right after the main chain's, so that a finished round has every row
                chain = closed_loop_round(cfg, lineage, k, demos, pi0, stats, chain, rounds_data[0], calibrations[0],
                                          memo, log, *arm, label_rule)
                made.rows[lineage, k, "closed_loop"] = chain[1:]
    made.bc = list(bc)[0]  # the BC row done (where map ran it beside the rounds, this waits for it)
    return made


@dataclass
class Made:
    """What policy_calibrated_dagger made: D0 and its statistics, pi_0 and its success, the BC row, and by
    (lineage, k): D_k and the calibration, by (lineage, k, method): each row's (policy, success). A success is
    (scenarios, repeats) bool on the evaluation scenarios; table() gives Table I's rows from them."""
    demos: list
    stats: relabel.DemoStats
    pi0: diffusion.DiffusionPolicy
    pi0_success: np.ndarray
    bc: tuple = None                                   # (policy, success): Table I's BC row
    data: dict = field(default_factory=dict)           # (lineage, k) -> D_k, the episodes with kept interventions
    calibrations: dict = field(default_factory=dict)   # (lineage, k) -> calibrate.Calibration
    rows: dict = field(default_factory=dict)           # (lineage, k, method) -> (policy, success)

    def table(self):
        """Table I's cells: {method: {k: [success % of each lineage]}}, BC's under k = 0 (one value for every K)."""
        table = {"bc": {0: [100.0 * float(np.mean(self.bc[1]))]}}
        for (lineage, k, method), (_, success) in sorted(self.rows.items()):
            table.setdefault(method, {}).setdefault(k, []).append(100.0 * float(np.mean(success)))
        return table


def compute(name, step, *args, **kwargs):
    """The loop's memo without a run folder: the step's result, made now (`name` is where the harness keeps it)."""
    return step(*args, **kwargs)


def one_after_another(fn, jobs):
    """The loop's map without worker processes: [fn(*job) for job in jobs], here and now."""
    return [fn(*job) for job in jobs]


def folder(lineage, k, chain=None):
    """Where the harness keeps round k's results of a lineage (and of a chain of its own, e.g. closed_loop)."""
    return f"lineage_{lineage}/round_{k}" + (f"/{chain}" if chain else "")


def round_label(keys):
    """'lineage l round k' (and its chain) of a step's keys (lineage, k[, chain]), for the log."""
    return f"lineage {keys[0]} round {keys[1]}" + (f" ({keys[2]} chain)" if len(keys) > 2 else "")


def stage_seed(cfg, *keys):
    """A step's seed, derived from the master seed and the step's name and keys (stable across runs)."""
    return int(np.random.SeedSequence([cfg.seed, *[_key_int(k) for k in keys]]).generate_state(1)[0])


def _key_int(key):
    return key if isinstance(key, int) else int.from_bytes(str(key).encode()[:8].ljust(8, b"\0"), "little")


# ---- Configuration: one dataclass, the paper's protocol by default; the run sizes in experiment/profiles.py ------
FIXED_SIGMAS = (2, 4, 8, 12, 16)  # Table I's sweep, in the paper's median steps (noise_model converts)
TABLE_I_METHODS = ("bc", "hg_dagger", *[f"fixed_{s}" for s in FIXED_SIGMAS], "pooled", "per_step", "closed_loop")
OBS_NOISE_JOINTS, OBS_NOISE_ENV = 0.01, 0.005  # the authors' training observation noise: rad on q_t, q_{t-1}; m else
TOST_MARGIN = 2.0  # Table I's equivalence margin, success points (paper: +-2)


@dataclass
class Config:
    # --- the paper's experiment (Sec. V; the authors' values in benchmarks/SETUP.md) ---
    env: str = "planar"  # the env make_env builds: 'planar' (Table I); Table II's 'engine3d' comes from experiment/
    methods: tuple = TABLE_I_METHODS  # Table I's rows (BC and HG-DAgger always run: the others pair with them)
    n_demos: int = 500  # |D0|, oracle demonstrations on training scenarios (paper: 500)
    rounds: int = 5  # HG-DAgger rounds K (paper: 5 planar, 2 UR5)
    lineages: int = 5  # independent repeats of the rounds (paper: 5 planar, 3 UR5)
    horizon: int = 20  # steps: H, actions per chunk (the authors' 64 at 30 Hz; the planar env runs at 10 Hz)
    n_act: int = 10  # steps: actions executed per chunk before the policy is asked again (the authors' 32 at 30 Hz)
    K: int = 100  # diffusion steps (the authors: 100, all of them at inference)
    down_dims: tuple = (64, 128, 256)  # channels of the epsilon U-Net's levels (the authors: 128, 256, 512)
    bc_steps: int = 75_000  # BC training steps (paper: pi_0 = BC's 75k checkpoint)
    finetune_steps: int = 100_000  # fine-tuning steps of every method per round (paper: to 175k)
    batch_size: int = 256  # (state, chunk) pairs per training step
    lr: float = 1e-3  # peak learning rate
    intervention_fraction: float = 0.3  # intervention frames' share of a fine-tuning batch (benchmarks/SETUP.md §2)
    recipe: str = "paper"  # the name of how pi_0 and the arms train ('paper'; a variant's: experiment/lever.py)
    eval_scenarios: int = 100  # the fixed held-out scenarios (Sec. V)
    eval_repeats: int = 3  # evaluations per scenario
    # --- not in the paper ---
    name: str = "quick"  # run folder runs/<name>/ (default: the profile's name)
    seed: int = 0  # master seed; every stage derives its own seed from it
    device: str = "cpu"  # torch device of the policy ('cuda' where a GPU exists)
    oracle_attempts: int = 3  # RRT runs per plan; the shortest end-effector path wins (1 is ~3x faster)
    network: str = "unet"  # the epsilon network, a diffusion.NETWORKS name: 'unet' (the authors') or 'mlp'
    mlp_width: int = 256  # network='mlp': hidden width (~8x the U-Net's training samples per CPU second)
    mlp_blocks: int = 3  # network='mlp': FiLM-conditioned residual blocks
    eval_unseen: bool = True  # also evaluate on envs.unseen_seeds(), scenarios no stage trains on (a second table)


# ---- Step 1: D0 and pi_0 -----------------------------------------------------------------------------------------
def oracle_demonstrations(cfg, map=None, log=print, make_env=envs.make_env):
    """D0: the oracle's demonstrations of the first cfg.n_demos training scenarios it can plan, a batch per tenth of
    D0 (map: in worker processes; every plan has its scenario's own seed: D0 is the same however they run)."""
    map = map or one_after_another
    demos, failures, t0 = [], 0, time.time()
    log(f"D0: {cfg.n_demos} oracle demonstrations on training scenarios")
    while len(demos) < cfg.n_demos:  # the scenarios after those tried, one per missing demonstration
        scenarios = range(len(demos) + failures, cfg.n_demos + failures)
        size = math.ceil(cfg.n_demos / 10)
        jobs = [(cfg, scenarios[i:i + size], make_env) for i in range(0, len(scenarios), size)]
        for batch in map(plan_demonstrations, jobs):
            demos.extend(d for d in batch if d is not None)  # a batch's plans, in scenario order
            failures += sum(d is None for d in batch)
            rate = len(demos) / (time.time() - t0)
            log(f"  demos {len(demos)}/{cfg.n_demos} | {rate * 60:.0f}/min | "
                f"{(cfg.n_demos - len(demos)) / max(rate, 1e-9):.0f} s left | {failures} unplannable")
    return demos


def plan_demonstrations(cfg, scenarios, make_env=envs.make_env):
    """The oracle's demonstrations of training scenarios `scenarios`, None where it found no plan."""
    env, expert, demos = make_env(cfg.env), make_oracle(cfg), []
    for i in scenarios:
        try:
            demos.append(expert.demonstrate(env, env.train_seeds(1, start=i)[0]))
        except oracle_mod.PlanningFailed:
            demos.append(None)
    return demos


def behavior_cloning(cfg, demos, log=print, fit=None, make_env=envs.make_env, lr_schedule=diffusion.warmup_cosine):
    """pi_0 = BC on D0's chunks (Sec. IV-C), with its optimizer state (policy.train_state) for every arm to continue:
    pi_0 is the bc_steps point of one learning-rate schedule of bc_steps + finetune_steps that every arm continues
    (the authors' planar runs, benchmarks/SETUP.md §2). fit: how a policy trains (default train_policy; the
    harness's keeps checkpoints in the run folder)."""
    obs, chunks = diffusion.chunk_dataset(demos, cfg.horizon)
    log(f"BC: {cfg.bc_steps} steps on {len(obs)} chunks from {len(demos)} demonstrations")
    policy = make_policy(cfg, make_env(cfg.env))
    tc = train_config(cfg, policy, cfg.bc_steps, stage_seed(cfg, "bc"), lr_schedule)
    return (fit or train_policy)(policy, obs, chunks, tc, keep_state=True, log=log)


def bc_row_arm(cfg, demos, pi0, memo=None, log=print, make_env=envs.make_env, lr_schedule=diffusion.warmup_cosine):
    """Table I's BC row, (policy, success): pi_0 continued on D0 alone to bc_steps + finetune_steps, the steps
    every row has trained, and evaluated."""
    memo = memo or compute
    policy = memo("checkpoints/bc_continued.pt", continue_on_d0, cfg, demos, pi0, log=log, lr_schedule=lr_schedule)
    return policy, evaluate_policy(memo, cfg, "eval/bc.json", policy, "bc", log, make_env=make_env)


def continue_on_d0(cfg, demos, pi0, log=print, fit=None, lr_schedule=diffusion.warmup_cosine):
    """pi_0 continued on D0 alone for finetune_steps (the arms' budget): the paper's BC row."""
    obs, chunks = diffusion.chunk_dataset(demos, cfg.horizon)
    log(f"BC row: pi_0 continued on D0 alone, {cfg.finetune_steps} steps (the arms' budget)")
    return finetune_from_pi0(cfg, pi0, obs, chunks, stage_seed(cfg, "train", "bc"), fit=fit, log=log,
                             lr_schedule=lr_schedule)


def train_policy(policy, obs, chunks, train_cfg, sampler=None, start=None, keep_state=False, log=print):
    """diffusion.train from `start` (None, or a policy's train_state: its step and AdamW state, e.g. pi_0's);
    keep_state: the trained policy keeps its own as policy.train_state, for runs that continue from it."""
    final = {}
    if keep_state:
        train_cfg = replace(train_cfg, checkpoint_steps=(train_cfg.steps,))
    diffusion.train(policy, obs, chunks, train_cfg, sampler=sampler, start=start, on_checkpoint=final.update, log=log)
    if keep_state:
        policy.train_state = {"step": final["step"], "optimizer": final["optimizer"]}
    return policy


def demo_statistics(cfg, demos, make_env=envs.make_env):
    """relabel.demo_stats of D0: its median step (the unit of noise), limits, and the paper's median step."""
    env = make_env(cfg.env)
    return relabel.demo_stats(demos, envs.median_step(demos), env.max_step, paper_median_step=env.paper_median_step,
                              frames_per_step=env.dt / envs.PAPER_FRAME_DT)


def make_oracle(cfg, *keys):
    """The RRT expert; keys (e.g. lineage, round) give an intervention run its own planner seed."""
    return oracle_mod.Oracle(oracle_mod.OracleConfig(seed=stage_seed(cfg, "oracle", *keys),
                                                     n_attempts=cfg.oracle_attempts))


def make_policy(cfg, env):
    """A fresh diffusion policy for this run's env and network; the env says how it reads its observation
    (env.obs_encoder: None, as numbers, diffusion.FlatObservation; a variant's env names its own encoder class)."""
    encoder = env.obs_encoder or diffusion.FlatObservation
    pc = diffusion.PolicyConfig(obs_dim=env.obs_dim, dof=env.dof, horizon=cfg.horizon, n_act=cfg.n_act, K=cfg.K,
                                down_dims=cfg.down_dims, network=cfg.network, mlp_width=cfg.mlp_width,
                                mlp_blocks=cfg.mlp_blocks, obs_encoder=encoder.__name__,
                                obs_encoder_args=dict(env.obs_encoder_args),
                                obs_encoder_sizes=encoder.sizes(**env.obs_encoder_args), seed=stage_seed(cfg, "init"))
    return diffusion.DiffusionPolicy(pc, device=cfg.device, obs_encoder=encoder)


# ---- Step 2: HG-DAgger data collection, many episodes in lockstep ------------------------------------------------
def collect_interventions(cfg, keys, policy, policy_success, log=print, make_env=envs.make_env,
                          label_rule=diffusion.expert_runs):
    """D_k: HG-DAgger rollouts of the lineage's policy on the evaluation scenarios its own evaluation
    (policy_success, (scenarios, repeats) bool) did not always solve (benchmarks/SETUP.md §4), the episodes with an
    intervention the label rule keeps (label_rule(expert, H): the runs kept, the paper's >= H steps, Sec. IV-C).
    keys: (lineage, k), and a chain of its own ('closed_loop'): the seeds."""
    label = round_label(keys)
    seeds = make_env(cfg.env).eval_seeds()[: cfg.eval_scenarios]
    solved = np.asarray(policy_success, bool).all(axis=1)
    log(f"{label}: HG-DAgger collection on the evaluation scenarios the policy "
        f"does not always solve: {int((~solved).sum())} of {len(seeds)} ({int(solved.sum())} skipped)")
    t0, env_list = time.time(), reset_envs(cfg.env, np.asarray(seeds)[~solved], make_env)
    gen = torch.Generator(device=policy.device).manual_seed(stage_seed(cfg, "collect", *keys))
    episodes = rollout(env_list, policy, cfg.n_act, gen, oracle=make_oracle(cfg, "collect", *keys),
                       log=log, seed=stage_seed(cfg, "gate", *keys)) if env_list else []
    for ep in episodes:  # D_k: the interventions the label rule keeps (the paper's: >= H steps, Sec. IV-C)
        runs = label_rule(ep["expert"], cfg.horizon)
        ep["expert"] = np.zeros(len(ep["expert"]), bool)
        for start, end in runs:
            ep["expert"][start:end] = True
    kept = [ep for ep in episodes if ep["expert"].any()]
    alone = sum(ep["success"] and ep["interventions"] == 0 for ep in episodes)
    rescued = sum(ep["success"] and ep["interventions"] > 0 for ep in episodes)
    log(f"  {len(episodes)} episodes: {alone} solved by the policy alone, {rescued} solved with the "
        f"expert's help, {len(episodes) - alone - rescued} failed; {len(kept)} kept with interventions, "
        f"{sum(int(ep['expert'].sum()) for ep in kept)} expert steps, {time.time() - t0:.0f} s")
    if not kept:
        raise RuntimeError(f"{label}: no intervention the label rule keeps in {len(episodes)} episodes")
    return kept


def reset_envs(env_name, seeds, make_env=envs.make_env):
    """A fresh env of env_name per scenario seed, reset to it: the episodes of one lockstep rollout."""
    env_list = []
    for s in seeds:
        env_list.append(make_env(env_name))
        env_list[-1].reset(seed=int(s))
    return env_list


def rollout(envs_list, policy, n_act, generator, oracle=None, log=None, seed=0):
    """One episode in each (already reset) env, in lockstep, until all end; returns the episode dicts.

    Without an oracle the policy drives (evaluation). With one, HG-DAgger (Sec. IV-A step 2) with the authors'
    gate (benchmarks/SETUP.md §3, oracle.Gate, seeded by `seed`): before every policy step the gate reads the pending
    actions; on a predicted collision the oracle plans from here, on a stall or a time trigger the episode first
    rewinds a few policy steps; the expert then drives (expert=True) a random 20-67 steps and hands back."""
    E = len(envs_list)
    rec = [{"obs": [], "q": [], "action": [], "expert": []} for _ in range(E)]
    q_prev_start = [e.q_prev.copy() for e in envs_list]  # for a rewind to step 0
    obs_now = [e.make_obs(e.q, e.q_prev) for e in envs_list]
    queue = [[] for _ in range(E)]  # pending (action, by_expert) per episode, executed in order
    pending = [np.zeros((0,)) for _ in range(E)]  # the policy's whole remaining chunk (the gate's lookahead)
    done, success = np.zeros(E, bool), np.zeros(E, bool)
    gates = None if oracle is None else [oracle.gate(e, np.random.default_rng([seed, int(e.seed)])) for e in envs_list]
    triggers = {"collision": 0, "stall": 0, "time": 0, "unplanned": 0}

    def follow_policy(i, chunk):  # (H, dof): execute the first n_act, the gate looks at all of them
        queue[i], pending[i] = [(a, False) for a in chunk[:n_act]], np.asarray(chunk)

    def take_over(i, reason):
        """The expert's actions after a trigger (None if no plan was found)."""
        env, gate, r = envs_list[i], gates[i], rec[i]
        gate.interventions += 1  # a failed plan counts too: no re-planning at every step
        if reason in ("stall", "time"):  # rewind, but never into the expert's own data
            policy_tail = len(r["expert"]) - (max(np.flatnonzero(r["expert"]), default=-1) + 1)
            n = gate.rewind_steps(policy_tail)
            if n:
                q, q_prev = r["q"][-n], (r["q"][-n - 1] if len(r["q"]) > n else q_prev_start[i])  # n steps ago
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
                follow_policy(i, chunk)
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
                        follow_policy(i, policy.sample(obs_now[i][None], generator=generator)[0])
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
    episodes = [{"obs": np.asarray(r["obs"], np.float32).reshape(len(r["obs"]), -1),
                 "q": np.asarray(r["q"]).reshape(len(r["q"]), -1),
                 "action": np.asarray(r["action"]).reshape(len(r["action"]), -1),
                 "expert": np.asarray(r["expert"], bool), "seed": int(e.seed), "success": bool(ok),
                 # expert takeovers that drove (a trigger without a plan is not one)
                 "interventions": int(np.sum(np.diff(np.r_[0, np.asarray(r["expert"], int)]) == 1))}
                for e, r, ok in zip(envs_list, rec, success)]
    if log is not None and oracle is not None:
        log(f"  {sum(triggers[k] for k in ('collision', 'stall', 'time'))} interventions in {E} episodes "
            f"(predicted collision {triggers['collision']}, stall {triggers['stall']}, time {triggers['time']}; "
            f"{triggers['unplanned']} triggers found no plan)")
    return episodes


# ---- Step 3: calibration (Sec. IV-D, calibrate.py) ---------------------------------------------------------------
def calibrate_noise(cfg, keys, policy, rounds_data, stats, log=print, make_env=envs.make_env):
    """calibrate.Calibration of the round's HG-DAgger policy on the interventions of rounds 1..k (benchmarks/SETUP.md
    §5); keys (lineage, k[, chain]): its seed (the closed-loop row's chain: its policy on its chain's data)."""
    episodes = [ep for D in rounds_data for ep in D]
    gen = torch.Generator(device=policy.device).manual_seed(stage_seed(cfg, "calibrate", *keys))
    t0 = time.time()
    cal = calibrate.calibrate(make_env(cfg.env), policy, episodes, stats.median_step, calibration_config(cfg),
                              gen, log=lambda msg: log("  calibration: " + msg))
    unit = cal.paper_median_step or cal.median_step  # the paper's median step where it gives one (Sec. V)
    log(f"{round_label(keys)}: calibration on {len(episodes)} intervention episodes ({time.time() - t0:.0f} s): "
        f"W = {np.linalg.norm(cal.W) / unit:.2f}, pooled Sigma_bar^alpha per-joint sigma "
        f"{np.round(np.sqrt(np.diag(cal.pooled)) / unit, 2).tolist()} {'paper ' if cal.paper_median_step else ''}"
        f"median steps")
    return cal


def calibration_config(cfg):
    """calibrate.CalibrationConfig of this run: the authors' settings but for the sampling counts."""
    return calibrate.CalibrationConfig(n_act=cfg.n_act)


# ---- Steps 3-4: the noise of each method, augmentation on the fly, co-training from pi_0 -------------------------
def noise_model(method, cal, episodes=None, median_step=None, paper_median_step=None):
    """(noise kind, sigma) of `method` for relabel.AugmentationSampler, sigma in our median steps (median_step,
    rad; benchmarks/SETUP.md §1). For 'per_step', `episodes`: the sampler's episodes' indices in the calibration's."""
    if method.startswith("fixed_"):
        sigma = float(method.split("_")[1])  # Table I: sigma in the paper's median steps (envs.paper_median_step)
        if median_step is None or paper_median_step is None:
            return "isotropic", sigma  # without both units: s of our median steps
        return "isotropic", sigma * paper_median_step / median_step
    if method in ("pooled", "closed_loop"):  # Eq. (16); closed_loop's measured on its own chain (closed_loop_round)
        return "pooled", cal.pooled
    if method == "per_step":  # Eq. (14): each episode's own measured steps
        per_episode = {}
        for j, e in enumerate(episodes):
            rows = cal.episode_index == e
            if rows.any():
                per_episode[j] = (cal.timestep[rows], cal.sigma_alpha[rows])
        return "per_step", per_episode
    raise ValueError(f"no noise model for method {method!r}: Table I's are fixed_<sigma>, pooled, per_step and "
                     "closed_loop (a variant's rows bring their own sampler: policy_calibrated_dagger's sampler)")


def intervention_sampler(cfg, method, rounds_data, calibration, stats, make_env=envs.make_env):
    """The intervention rows of a fine-tuning batch, rounds 1..k in equal shares: HG-DAgger's as recorded, a noised
    method's every drawn frame noised and relabelled (the authors' code, benchmarks/SETUP.md §2). A variant's rows
    bring their own function of these arguments (policy_calibrated_dagger's sampler)."""
    samplers, offset = [], 0
    for D in rounds_data:
        if method == "hg_dagger":  # HG-DAgger's rows: the round's chunks as recorded
            samplers.append(relabel.ChunkSampler(D, cfg.horizon))
        else:  # a noised method's rows: every drawn frame noised with the method's noise and relabelled (Sec. IV-E)
            kind, sigma = noise_model(method, calibration, range(offset, offset + len(D)), stats.median_step,
                                      stats.paper_median_step)
            samplers.append(relabel.AugmentationSampler(D, functools.partial(make_env, cfg.env), stats, kind, sigma,
                                                        relabel.RelabelConfig(horizon=cfg.horizon)))
        offset += len(D)
    return relabel.MixtureSampler(samplers, [1.0] * len(samplers))


def fine_tune(cfg, lineage, k, method, demos, pi0, rounds_data, calibration, stats, log=print, fit=None,
              make_env=envs.make_env, lr_schedule=diffusion.warmup_cosine, sampler=None):
    """Steps 3-4 (benchmarks/SETUP.md §2): pi_0 fine-tuned on D0 and, in intervention_fraction of every batch, the
    interventions of rounds 1..k (sampler: default intervention_sampler); D0 is never noised."""
    obs, chunks = diffusion.chunk_dataset(demos, cfg.horizon)
    rows = (sampler or intervention_sampler)(cfg, method, rounds_data, calibration, stats, make_env)
    log(f"lineage {lineage} round {k}: fine-tune {method} from pi_0, {cfg.finetune_steps} steps, "
        f"{len(obs)} D0 chunks + {cfg.intervention_fraction:.0%} of every batch from the interventions of "
        f"{len(rounds_data)} round(s) (continuing pi_0's optimizer)")
    return finetune_from_pi0(cfg, pi0, obs, chunks, stage_seed(cfg, "train", lineage, k, method), rows,
                             cfg.intervention_fraction, fit, log, lr_schedule)


def finetune_from_pi0(cfg, pi0, obs, chunks, seed, sampler=None, aug_fraction=0.0, fit=None, log=print,
                      lr_schedule=diffusion.warmup_cosine):
    """A copy of pi_0 fine-tuned to bc_steps + finetune_steps, continuing its AdamW state and learning-rate schedule."""
    policy = copy_policy(pi0)  # pi_0 itself stays as it is for the next arm
    tc = train_config(cfg, policy, cfg.bc_steps + cfg.finetune_steps, seed, lr_schedule, aug_fraction)
    return (fit or train_policy)(policy, obs, chunks, tc, sampler, start=copy.deepcopy(pi0.train_state), log=log)


def copy_policy(policy):
    """A policy of its own with `policy`'s config, observation encoder and weights (its EMA copy and normalizer too)."""
    twin = diffusion.DiffusionPolicy(policy.cfg, device=policy.device, obs_encoder=type(policy.net.obs_encoder))
    twin.load_state_dict(policy.state_dict())
    return twin


def train_config(cfg, policy, steps, seed, lr_schedule=diffusion.warmup_cosine, aug_fraction=0.0):
    """diffusion.TrainConfig of a run to step `steps` of the schedule pi_0 and every arm share (bc_steps +
    finetune_steps): AdamW at peak lr, warm-up, lr_schedule (the paper's: a cosine to 0 at the schedule's end), the
    authors' observation noise; aug_fraction of every batch from the sampler."""
    schedule_steps = cfg.bc_steps + cfg.finetune_steps
    return diffusion.TrainConfig(steps=steps, batch_size=cfg.batch_size, lr=cfg.lr, seed=seed,
                                 warmup_steps=min(500, schedule_steps // 10), schedule_steps=schedule_steps,
                                 lr_schedule=lr_schedule, aug_fraction=aug_fraction,
                                 obs_noise=observation_noise(policy.cfg))


def observation_noise(policy_cfg):
    """Per-entry std (obs_dim,) of training observation noise (benchmarks/SETUP.md §2): OBS_NOISE_JOINTS on the joints
    at t and t-1, OBS_NOISE_ENV on the other low-dimensional numbers, none on an encoder's entries (an image)."""
    std = np.zeros(policy_cfg.obs_dim)
    std[:2 * policy_cfg.dof] = OBS_NOISE_JOINTS
    std[2 * policy_cfg.dof:policy_cfg.low_dim] = OBS_NOISE_ENV
    return std


def train_and_evaluate(cfg, lineage, k, method, demos, pi0, rounds_data, calibration, stats, memo=None, log=print,
                       make_env=envs.make_env, lr_schedule=diffusion.warmup_cosine, sampler=None):
    """One row of round k (steps 4 and 6), fine-tuned and evaluated: (policy, success (scenarios, repeats) bool)."""
    memo = memo or compute
    policy = memo(f"{folder(lineage, k)}/checkpoints/{method}.pt", fine_tune, cfg, lineage, k, method, demos, pi0,
                  rounds_data, calibration, stats, log=log, make_env=make_env, lr_schedule=lr_schedule, sampler=sampler)
    return policy, evaluate_policy(memo, cfg, f"{folder(lineage, k)}/eval/{method}.json", policy,
                                   f"{method} (lineage {lineage}, K={k})", log, make_env=make_env)


def closed_loop_round(cfg, lineage, k, demos, pi0, stats, chain, first_round, first_calibration, memo=None, log=print,
                      make_env=envs.make_env, lr_schedule=diffusion.warmup_cosine, sampler=None,
                      label_rule=diffusion.expert_runs):
    """Round k of Table I's closed-loop pooled row, Sec. IV-A's steps 2-5 as written (benchmarks/SETUP.md §5): the
    chain's round k-1 policy, co-trained with pooled Sigma_bar^alpha from pi_0, collects round k, and round k's noise
    is measured on it over the chain's rounds 1..k. Round 1 is the main chain's (the authors copy it too).
    chain: None at k = 1, else round k-1's return: (rounds' data, policy, success)."""
    memo = memo or compute
    if k == 1:
        rounds_data, calibration = [first_round], first_calibration
    else:  # the previous round's calibrated policy drives, the oracle intervenes (step 2) ...
        rounds_data, policy, success = chain
        keys, where = (lineage, k, "closed_loop"), folder(lineage, k, "closed_loop")
        rounds_data = rounds_data + [memo(f"{where}/D.npz", collect_interventions, cfg, keys, policy, success,
                                          log=log, make_env=make_env, label_rule=label_rule)]
        # ... and its own noise is measured on the chain's interventions of rounds 1..k (step 3)
        calibration = memo(f"{where}/calibration.json", calibrate_noise, cfg, keys, policy, rounds_data, stats,
                           log=log, make_env=make_env)
    return rounds_data, *train_and_evaluate(cfg, lineage, k, "closed_loop", demos, pi0, rounds_data, calibration,
                                            stats, memo, log, make_env, lr_schedule, sampler)


# ---- Step 5: evaluation (Sec. V: 100 scenarios x 3 evaluations; success = goal reached without collision) --------
def evaluate_policy(memo, cfg, name, policy, label, log=print, unseen=None, make_env=envs.make_env):
    """Success (scenarios, repeats) bool of `policy` on the evaluation scenarios, kept as `name`. With unseen (default
    cfg.eval_unseen) also on the unseen scenarios, never trained on (not in the paper), as <name>_unseen.json."""
    ok = memo(name, evaluation, cfg, policy, label, "eval", log=log, make_env=make_env)
    if cfg.eval_unseen if unseen is None else unseen:  # eval/bc.json -> eval/bc_unseen.json
        memo(name[:-len(".json")] + "_unseen.json", evaluation, cfg, policy, label + ", unseen scenarios", "unseen",
             log=log, make_env=make_env)
    return np.asarray(ok["success"], bool)


def evaluation(cfg, policy, label, scenarios, log=print, make_env=envs.make_env):
    """evaluate on the first eval_scenarios of 'eval' or 'unseen', one sampling seed per set for every method."""
    t0 = time.time()
    env = make_env(cfg.env)
    seeds = (env.eval_seeds() if scenarios == "eval" else env.unseen_seeds())[: cfg.eval_scenarios]
    ok = evaluate(policy, cfg.env, seeds, cfg.eval_repeats, cfg.n_act,
                  stage_seed(cfg, "eval" if scenarios == "eval" else "eval_unseen"), log=log, make_env=make_env)
    log(f"  eval {label}: success {100 * ok.mean():.1f}% ({ok.size} episodes, {time.time() - t0:.0f} s)")
    return {"success": ok.tolist(), "seeds": list(map(int, seeds))}


def evaluate(policy, env_name, seeds, repeats, n_act, seed, max_parallel="env default", log=None,
             make_env=envs.make_env):
    """Success (len(seeds), repeats) bool: goal reached without collision within the step limit. `seed` seeds the
    sampling identically for every method: methods face the same draws where their policies agree (paired)."""
    jobs = [int(s) for _ in range(repeats) for s in seeds]
    gen = torch.Generator(device=policy.device).manual_seed(seed)
    ok = np.array([ep["success"] for _, ep in rollouts_in_groups(policy, env_name, jobs, n_act, gen, max_parallel,
                                                                 log, make_env)], bool)
    return ok.reshape(repeats, len(seeds)).T


def rollouts_in_groups(policy, env_name, jobs, n_act, generator, max_parallel="env default", log=None,
                       make_env=envs.make_env):
    """(env, episode) for each scenario seed in `jobs`, in order: lockstep rollouts in groups of at most
    max_parallel (default the env's own max_parallel; None: all at once), a group's envs closed after it."""
    if not jobs:
        return
    first = reset_envs(env_name, jobs[:1], make_env)  # the first episode's env says how many may run at once
    group = (first[0].max_parallel if max_parallel == "env default" else max_parallel) or len(jobs)
    for start in range(0, len(jobs), group):
        env_list = (reset_envs(env_name, jobs[start:start + group], make_env) if start else
                    first + reset_envs(env_name, jobs[1:group], make_env))
        yield from zip(env_list, rollout(env_list, policy, n_act, generator, log=log))
        for e in env_list:
            if hasattr(e, "close"):
                e.close()  # free the simulator (a pybullet client) before the next group


# ---- Table I's statistics (Sec. V): paired t-test vs HG-DAgger, TOST vs the best fixed sigma ---------------------
def paired_differences(a, b):
    """a - b per pair, to 1e-9 points: success rates are counts of episodes, so equal gains (47.0 - 46.0 and
    47.33 - 46.33) are equal, not 1e-14 apart (a spread of float rounding would give t ~ 1e14)."""
    return np.round(np.asarray(a, float) - np.asarray(b, float), 9)


def paired_ttest(a, b):
    """Two-sided paired t-test of mean(a - b) = 0. Returns (t, df, p). Needs >= 2 pairs."""
    d = paired_differences(a, b)
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
    """Two one-sided tests: is mean(a - b) within (-margin, +margin)? Returns (p, t_lower, t_upper). H0: the
    difference is <= -margin or >= +margin; a small p (the larger one-sided p) shows equivalence. Needs >= 2 pairs."""
    d = paired_differences(a, b)
    n = d.size
    if n < 2 or margin <= 0:
        raise ValueError(f"TOST needs at least 2 pairs (lineages) and a margin > 0, got {n} pairs, margin {margin}")
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




# Student's t distribution without scipy: the p-values of paired_ttest and tost (a special function, not the paper's)
def student_t_cdf(t, df):
    """P(T <= t) for Student's t with df > 0 degrees of freedom: 1 - I_{df/(df+t^2)}(df/2, 1/2) / 2."""
    assert df > 0, df
    if math.isinf(t):
        return 1.0 if t > 0 else 0.0
    tail = 0.5 * incomplete_beta(df / 2.0, 0.5, df / (df + t * t))
    return 1.0 - tail if t > 0 else tail


def incomplete_beta(a, b, x):
    """Regularized incomplete beta I_x(a, b) for a, b > 0 and 0 <= x <= 1."""
    assert 0.0 <= x <= 1.0, x
    if x in (0.0, 1.0):
        return x
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):  # the continued fraction converges fast here
        return front * _beta_fraction(a, b, x) / a
    return 1.0 - front * _beta_fraction(b, a, 1.0 - x) / b  # symmetry I_x(a,b) = 1 - I_{1-x}(b,a)


def _beta_fraction(a, b, x):
    """The continued fraction of I_x(a, b) (modified Lentz; 300 terms at most)."""
    tiny = 1e-300  # keeps every denominator off zero
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 301):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),  # the even term d_{2m}, then the odd d_{2m+1}
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


# ---- The entry point: `python dagger.py [options]` hands the process to the harness's command line ---------------
if __name__ == "__main__":  # experiment/cli.py: profiles, the run folder, this file's loop, the report (--help)
    import runpy
    runpy.run_module("experiment.cli", run_name="__main__", alter_sys=True)
