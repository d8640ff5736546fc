"""The run folder: every stage's result on disk before the next starts, so a stopped run resumes.

runs/<name>/ holds config.json, log.txt, data/D0.npz, checkpoints/, eval/, lineage_<l>/round_<k>/{D.npz,
calibration.json, checkpoints/<method>.pt, eval/<method>.json}, timings/ and figures/. The harness hands
dagger.policy_calibrated_dagger `run.memo`: each step's result is a file of the folder (Run.stage: loaded if the
stage finished, else computed, written atomically, timed), a policy trained by `run.train` (checkpoints, resume).
Two processes may share a folder (.locks/): one lineage runs in one process at a time, and a shared stage is made
by one while the other waits for it. Nothing here is the paper's method.
"""
from __future__ import annotations

import contextlib
import fcntl
import functools
import gzip
import hashlib
import io
import json
import os
import re
import shutil
import time
from dataclasses import asdict, fields, replace

import numpy as np
import torch

import calibrate
import diffusion
import envs
import relabel
from experiment import checkpoints, cpu_kernels
from experiment.workers import torch_threads

PI0_FILE, PI0_THREADS = "checkpoints/bc.pt", 2  # pi_0 trains alone: 2 torch threads (a count changes the last bits)


class ConfigMismatch(ValueError):
    """A run folder holds a run with another config (stages could not be reused honestly)."""


class RunFolderError(ValueError):
    """The run folder cannot be created (a bad --out), or one of its stage files is damaged."""


class FolderInUse(RunFolderError):
    """Another process runs the same lineage in this run folder (its PID is named)."""


# Config fields a run folder lets differ from the config it was made with: they change no stage's result
# (device: where it computes; eval_unseen only adds evaluations; more lineages only add lineage folders, and no
# seed depends on their number). Any other difference is refused (ConfigMismatch).
FOLDER_FREE_FIELDS = ("device", "eval_unseen", "lineages")

# Config fields deleted since run folders and results files were made: options that were measured and not adopted
# (their numbers are in benchmarks/README.md). A stored config (config.json, a lineage.json, a --join file, a
# --copy-from folder) still names them; each must hold a value whose behaviour is the one that remains -- the
# values listed -- and is then dropped before the comparison. Another value ran code that is gone: refused
# (ConfigMismatch), naming the field. ANY_VALUE: a field that only a deleted option read (its value changed nothing).
ANY_VALUE = None
RETIRED_FIELDS = {
    "finetune_lr": (None,),  # the lever recipe runs at lr / 10 (the authors' 1e-6 after BC's 1e-5)
    "raw_mix": (0.0,),  # a noised arm noises every intervention frame it draws (the authors' code)
    "start": (None, "random"),  # the authors' random starts (None: the env's default, 'random')
    "collect_on": ("eval",),  # HG-DAgger collects on the evaluation scenarios (the authors' protocol)
    "episodes_per_round": ANY_VALUE,  # read only by collect_on='train'
    "calib_rollouts_per_beta": (1,),  # one blended rollout per ratio and segment (the authors')
    "calib_blend_segments": (0,),  # every long enough intervention segment starts blended rollouts
    "image_obs": (False,),  # camera images are an env variant now: --env engine3d_image (experiment/image_obs.py)
    "image_size": ANY_VALUE,  # read only by image_obs (the variant's image size is its own)
    "goal_angle": (None,),  # position-only success; the authors' 10 degrees is the env variant engine3d_oriented
    "joint_obs": (True,),  # chunks relative to q_t, the policy sees the velocity (measured, adopted)
    "calib_samples": (4,),  # policy samples per anchor of Sigma_hat: calibrate.CalibrationConfig's (the authors')
    "tost_margin": (2.0,),  # dagger.TOST_MARGIN (the paper's +-2)
    "obs_noise_joints": (0.01,),  # dagger.OBS_NOISE_JOINTS (the authors')
    "obs_noise_env": (0.005,),  # dagger.OBS_NOISE_ENV (the authors')
}
# The return label of a lineage's noised rows (relabel.RelabelConfig.label), recorded in its lineage.json and its
# results file: a lineage's stages continue only under the label they were made with, and a folder's table holds one
# label. A record without it was made before the label was recorded: by the servo of relabel.py up to 6192871, whose
# speed cap and floors were converted with our per-joint median step (half the authors' L2 unit in radians).
LABEL_KEY = "return_label"
RETURN_LABEL = relabel.RelabelConfig.label
OLD_SERVO = "servo up to 6192871"
LABEL_WORDS = {"pd": "the paper's PD (relabel.pd_return_chunk, Sec. IV-E)",
               OLD_SERVO: "the servo as converted up to commit 6192871 (its speed cap half the authors' in radians)"}


def label_of(record):
    """The return label a lineage record (lineage.json, or a results file) was made with."""
    return record.get(LABEL_KEY, OLD_SERVO)


# What to do instead, for a retired field that became a variant rather than being deleted.
RETIRED_ADVICE = {"image_obs": "camera images are the env variant --env engine3d_image now (experiment/image_obs.py)",
                  "goal_angle": "the authors' 10 degrees is the env variant --env engine3d_oriented now "
                                "(experiment/oriented_goal.py)"}
# Four fields that one Config.recipe replaced: their combinations that ran a recipe which remains (dagger.RECIPES).
RECIPE_FIELDS = {"finetune": "continue", "round_shares": "equal", "short_interventions": "drop",
                 "replicates": "lineages"}  # each with its default
RECIPE_OF_FIELDS = {("continue", "equal", "drop", "lineages"): "paper",
                    ("constant", "frames", "pad", "lineages"): "authors_lever",
                    ("constant", "frames", "pad", "seeds"): "authors_lever_seeds"}
# ... and the parts of a run folder's name (cli.folder_name) that said those fields, as the recipe's part says it now
RECIPE_NAME_PARTS = {"_constant_frame_shares_pad_short_seed_replicates": "_authors_lever_seeds",
                     "_constant_frame_shares_pad_short": "_authors_lever"}


class Run:
    """One run folder and the config it was made with (any dataclass config: this module never imports it)."""

    def __init__(self, root, cfg):
        self.root, self.cfg = root, cfg
        try:
            os.makedirs(root, exist_ok=True)
            open(os.path.join(root, "log.txt"), "a").close()
        except OSError as err:
            raise RunFolderError(f"cannot use {root!r} as the run folder: {err.strerror or err}. Give --out a "
                                 "folder you can create and write (default runs/<profile>).") from None
        path = os.path.join(root, "config.json")
        if os.path.exists(path):
            old = read_json(path)
            check_same_config(root, old, cfg)
            if cfg.lineages > old.get("lineages", 1):  # the folder now holds (or will hold) this many lineages
                write_json(path, {**old, "lineages": cfg.lineages})
        else:
            write_json(path, asdict(cfg))
        self._log = open(os.path.join(root, "log.txt"), "a")
        self._claimed = set()
        self._held = []  # the file descriptors of the lineage locks this process holds (hold_lineages)

    def __reduce__(self):  # a worker process opens its own handle on the folder (Run.memo and Run.log pickle so)
        return Run, (self.root, self.cfg)

    def memo(self, name, step, *args, **kwargs):
        """dagger's memo: step(*args, **kwargs) kept in the stage file `name` (Run.stage: loaded if it is there). A
        step that trains a policy (`name` a .pt) is handed fit=Run.train into that file: checkpoints, resume; pi_0
        trains with PI0_THREADS torch threads (nothing runs beside it)."""
        if name.endswith(".pt"):
            kwargs["fit"] = functools.partial(self.train, name)
        with torch_threads(PI0_THREADS) if name == PI0_FILE else contextlib.nullcontext():
            return self.stage(name, lambda: step(*args, **kwargs))

    def path(self, *parts):
        """root/parts..., its folder made."""
        p = os.path.join(self.root, *parts)
        os.makedirs(os.path.dirname(p), exist_ok=True)
        return p

    def log(self, msg):
        line = f"[{time.strftime('%H:%M:%S')}] {msg}"
        print(line, flush=True)
        self._log.write(line + "\n")
        self._log.flush()

    def stage(self, name, compute):
        """Load stage `name` (a path under the run folder, '/'-separated) if it finished, else compute() it,
        write it atomically and record its wall time. By the file's kind: .npz a list of episodes
        (save_episodes), calibration.json a calibrate.Calibration, .json a JSON dict, .pt a policy (compute
        writes it: Run.train)."""
        path = self.path(*name.split("/"))
        lineage = re.match(r"lineage_(\d+)/", name)
        if lineage:
            self.claim_lineage(int(lineage.group(1)))
        if os.path.exists(path):
            return self.load(name)
        if lineage:
            self.check_label(int(lineage.group(1)))
        with contextlib.ExitStack() as held:
            if not lineage:  # a shared stage: another run of this folder (another lineage) may be making it now
                held.enter_context(self.stage_lock(name))
                if os.path.exists(path):
                    return self.load(name)
            return self._compute(name, path, compute)

    def _compute(self, name, path, compute):
        t0 = time.time()
        value = compute()
        if name.endswith("calibration.json"):
            write_json(path, calibration_to_json(value))
        elif not name.endswith(".pt"):
            (save_episodes if name.endswith(".npz") else write_json)(path, value)
        self.record_time(timing_name(name), time.time() - t0)  # of this process: a resumed run counts its last part
        return value

    def load(self, name):
        """A finished stage's result (a damaged file, or an evaluation not of this run's scenarios, is named:
        RunFolderError)."""
        path = os.path.join(self.root, *name.split("/"))
        if name.endswith(".pt"):
            return load_policy(path, self.cfg.device)
        if name.endswith(".npz"):
            return load_episodes(path)
        data = read_json(path)
        if name.endswith("calibration.json"):
            return calibration_from_json(data)
        if is_evaluation(name):
            check_evaluation(path, data, self.cfg, EVALUATION_ADVICE)
        return data

    def train(self, name, policy, obs, chunks, train_cfg, sampler=None, start=None, keep_state=False, log=None):
        """dagger.train_policy for a policy `name` (.pt) of the folder: diffusion.train with checkpoints at quarters
        of the run (a stopped run resumes from the last one: weights, AdamW, random streams, the sampler's pool),
        then the final file.

        start: the training state (step, AdamW) of the policy given (pi_0's policy.train_state), which goes on to
        train_cfg.steps; keep_state: the final file keeps the optimizer state, and the policy as
        policy.train_state, for runs that continue from it. log: default the folder's log.
        """
        log = log or self.log
        cpu_kernels.use_kernels(policy)  # eps_theta computed faster on this CPU, the same function (cpu_kernels.py)
        final_path = self.path(*name.split("/"))
        first, steps = (start["step"] if start else 0), train_cfg.steps
        part = final_path.replace(".pt", "_step{step}.pt")
        marks = tuple(sorted({first + max(1, (steps - first) * i // 4) for i in (1, 2, 3)}
                             | ({steps} if keep_state else set())))
        train_cfg = replace(train_cfg, log_every=max(1, (steps - first) // 5), checkpoint_steps=marks)
        resume = next((part.format(step=m) for m in reversed(marks)
                       if m < steps and os.path.exists(part.format(step=m))), None)
        if resume:
            payload = load_stage_file(resume, checkpoints.read_checkpoint)  # a damaged one is named
            policy.load_state_dict(payload["state_dict"])
            start = checkpoints.train_state(resume, payload, sampler)
            log(f"  resuming from {os.path.relpath(resume, self.root)}")
        last = {}

        def save(state):  # train()'s state at a checkpoint step, with the weights and the sampler's pool
            checkpoints.save_policy(policy, part.format(step=state["step"]), state, sampler, train_cfg)
            last.update(state)

        diffusion.train(policy, obs, chunks, train_cfg, sampler=sampler, start=start, on_checkpoint=save,
                        log=lambda m: log("  " + m))
        if keep_state:  # the last checkpoint holds the weights and the optimizer: it is the final file
            os.replace(part.format(step=steps), final_path)
            policy.train_state = {"step": last["step"], "optimizer": last["optimizer"]}
        else:
            checkpoints.save_policy(policy, final_path)
        for m in marks:  # the finished checkpoint supersedes the partial ones
            if os.path.exists(part.format(step=m)):
                os.remove(part.format(step=m))
        return policy

    def inputs_changed(self, stamp, inputs):
        """Whether the files `inputs` (names under the folder) differ -- in size or time -- from when
        record_inputs(stamp, ...) last recorded them, or a file then in stamp's folder is gone."""
        path = os.path.join(self.root, *stamp.split("/"))
        if not os.path.exists(path):
            return True
        record = read_json(path)
        folder = os.path.dirname(path)
        return (record["inputs"] != self._file_states(inputs)
                or not all(os.path.exists(os.path.join(folder, name)) for name in record["outputs"]))

    def record_inputs(self, stamp, inputs):
        """Record the inputs' sizes and times, and the files now in stamp's folder (what was made from them)."""
        path = self.path(*stamp.split("/"))
        outputs = sorted(n for n in os.listdir(os.path.dirname(path)) if n != os.path.basename(path))
        write_json(path, {"inputs": self._file_states(inputs), "outputs": outputs})

    def _file_states(self, names):
        states = {}
        for name in names:
            p = os.path.join(self.root, *name.split("/"))
            states[name] = [os.path.getsize(p), os.stat(p).st_mtime_ns] if os.path.exists(p) else None
        return states

    def hold_lineages(self, lineages):
        """Lock the lineages this process will run (.locks/lineage_<l>.lock, flock: the system drops a lock when
        its process dies, so a killed run never leaves one held). FolderInUse, at once, naming the PID of the
        process that holds one of them; release_lineages() (or the process's end) lets them go."""
        taken = []
        for lineage in lineages:
            fd, holder = try_lock(self.path(LOCK_FOLDER, f"lineage_{lineage}.lock"))
            if fd is None:
                for fd in taken:  # none of the lineages asked for, as before the call
                    os.close(fd)
                raise FolderInUse(
                    f"{self.root} is in use: process {holder or '(its PID not yet written)'} runs lineage {lineage} "
                    "in it. Wait for it to finish (or stop it) and run this command again, or run another lineage "
                    "(--lineage i) or another folder (--out).")
            taken.append(fd)
        self._held += taken

    def release_lineages(self):
        for fd in self._held:
            os.close(fd)  # closing the descriptor drops its flock
        self._held = []

    @contextlib.contextmanager
    def stage_lock(self, name):
        """Hold .locks/<name>.lock while a shared stage is made: a second process of this folder waits for it and
        then loads the stage instead of making it beside the first (their files would cross)."""
        path = self.path(LOCK_FOLDER, name.replace("/", "__") + ".lock")
        fd, holder = try_lock(path)
        if fd is None:
            self.log(f"waiting for process {holder or '(unknown)'}, which is making {name} in this folder")
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            yield
        finally:
            os.close(fd)

    def claim_lineage(self, lineage):
        """lineage_<l>/lineage.json: the config and the pi_0 (the SHA-256 of its weights) the lineage is made
        with, written at its first stage. A lineage folder copied in from another run folder -- run on another
        day or machine, from a copy of this folder's shared stages -- is checked instead: another config
        (FOLDER_FREE_FIELDS aside) or another pi_0 is refused (ConfigMismatch), naming what differs."""
        if lineage in self._claimed:
            return
        pi0_path = os.path.join(self.root, "checkpoints", "bc.pt")
        if not os.path.exists(pi0_path):
            return  # no pi_0 yet: nothing a lineage could have been made from
        path = self.path(f"lineage_{lineage}", "lineage.json")
        pi0 = weights_sha256(pi0_path)
        if os.path.exists(path):
            record = read_json(path)
            where = f"{self.root}/lineage_{lineage}"
            check_same_config(where, record["config"], self.cfg,
                              advice=f"A lineage joins a run folder only if it was made with the folder's config: "
                                     f"delete {where} to run it again here, or report it in a folder of its config.")
            if record["pi0_sha256"] != pi0:
                raise ConfigMismatch(
                    f"{where} was made from another pi_0 (the SHA-256 of its weights {record['pi0_sha256'][:12]}... "
                    f"there, {pi0[:12]}... here). A lineage joins a run folder only with the shared stages it was "
                    "made from: run it from a copy of this folder's data/ and checkpoints/, or run it here.")
        else:
            others = sorted(folder_labels(self.root) - {RETURN_LABEL})
            if others:
                raise ConfigMismatch(f"{self.root} holds lineages made with another return label "
                                     f"({LABEL_WORDS.get(others[0], others[0])}); this code labels with "
                                     f"{LABEL_WORDS[RETURN_LABEL]}, and one table holds one label. Give the new "
                                     "lineage a folder of its own (--out).")
            write_json(path, {"config": asdict(self.cfg), "pi0_sha256": pi0, LABEL_KEY: RETURN_LABEL})
        self._claimed.add(lineage)

    def check_label(self, lineage):
        """ConfigMismatch if lineage `lineage`'s stages were made with another return label than this code's (its
        lineage.json says which): its next stage would be made with another label than its finished ones."""
        path = os.path.join(self.root, f"lineage_{lineage}", "lineage.json")
        label = label_of(read_json(path)) if os.path.exists(path) else RETURN_LABEL
        if label != RETURN_LABEL:
            raise ConfigMismatch(
                f"{self.root}/lineage_{lineage} was made with {LABEL_WORDS.get(label, label)}; this code labels with "
                f"{LABEL_WORDS[RETURN_LABEL]}: a lineage does not continue across a change of label. Run it on in "
                "a folder of its own from its start (--out), or report it as it is (--report).")

    def check_lineages(self):
        """claim_lineage for every lineage folder in the run folder (the report's check before it merges them)."""
        for name in sorted(os.listdir(self.root)):
            match = re.fullmatch(r"lineage_(\d+)", name)
            if match and os.path.isdir(os.path.join(self.root, name)):
                self.claim_lineage(int(match.group(1)))

    def record_time(self, stage, seconds):
        """Wall time of a finished stage, one file per stage (parallel lineages never write the same file)."""
        write_json(self.path("timings", stage.replace("/", "__") + ".json"), {"stage": stage, "seconds": seconds})


# A lineage's results as one small file (gzipped JSON, a few hundred kB; no checkpoints or data): what --export-lineages
# writes and --join reads, so a lineage run on another day or machine -- or committed under benchmarks/results/ --
# joins a run folder's report. It holds every JSON under lineage_<l>/ (evaluations, calibrations, lineage.json),
# the lineage's timings and the shared evaluations under eval/ (pi_0's, the BC row's) it is paired with.
LINEAGE_FILE_FORMAT = "pcdagger-lineage-results-1"


def lineage_results(run, lineage):
    """{relative path: JSON content} of lineage `lineage`'s results in run folder `run` (see LINEAGE_FILE_FORMAT)."""
    where = re.compile(rf"(^|__)lineage_{lineage}(__|\.json$)")
    files = {}
    for top, _, names in os.walk(run.path(f"lineage_{lineage}")):
        for name in names:
            if name.endswith(".json"):
                path = os.path.join(top, name)
                files[os.path.relpath(path, run.root)] = read_json(path)
    for folder, keep in (("timings", where.search), ("eval", lambda name: True)):
        for name in sorted(os.listdir(run.path(folder))) if os.path.isdir(run.path(folder)) else []:
            if name.endswith(".json") and keep(name):
                files[f"{folder}/{name}"] = read_json(run.path(folder, name))
    return files


def export_lineages(run, folder):
    """folder/lineage_<l>.json.gz for every lineage of the run folder that finished a round (every method's
    evaluation); each says how many rounds it finished. Returns the paths written."""
    os.makedirs(folder, exist_ok=True)
    written = []
    for lineage in sorted(int(m.group(1)) for m in map(re.compile(r"lineage_(\d+)$").match, os.listdir(run.root))
                          if m and os.path.exists(run.path(m.group(0), "lineage.json"))):
        record, finished = read_json(run.path(f"lineage_{lineage}", "lineage.json")), rounds_finished(run, lineage)
        if not finished:
            run.log(f"lineage {lineage}: no round finished yet, no results file written")
            continue
        files = lineage_results(run, lineage)
        path = os.path.join(folder, f"lineage_{lineage}.json.gz")
        tmp = f"{path}.{os.getpid()}.tmp"
        # gzip (the calibrations' per-step covariances are most of it) without a time or a name in its header:
        # exporting the same results again writes the same bytes, so a commit shows only what changed
        with open(tmp, "wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as z, \
                io.TextIOWrapper(z, encoding="utf-8") as f:
            json.dump({"format": LINEAGE_FILE_FORMAT, "lineage": lineage, "config": record["config"],
                       "pi0_sha256": record["pi0_sha256"], LABEL_KEY: label_of(record), "rounds_finished": finished,
                       "files": files}, f, separators=(",", ":"))
        os.replace(tmp, path)
        written.append(path)
    return written


def rounds_finished(run, lineage):
    """How many rounds of the lineage have every method's evaluation on disk (the rounds a report can use)."""
    methods = [m for m in getattr(run.cfg, "methods", ()) if m != "bc"]
    k = 0
    while k < run.cfg.rounds and all(os.path.exists(run.path(f"lineage_{lineage}", f"round_{k + 1}", "eval",
                                                                f"{m}.json")) for m in methods):
        k += 1
    return k


STAGE_FOLDERS = ("data", "checkpoints", "eval", "timings")  # a folder's stages, beside its lineage_<l>/ folders

# A profile's shared stages committed once (benchmarks/results/<profile>/start/: config.json, D0, pi_0 with its
# optimizer state, the BC row and their evaluations), so that every lineage -- run on any machine, on any
# day -- continues from the same pi_0 and joins the others (--join): the same seed gives another pi_0 on another
# kind of machine. --prepare / --lineage i / a whole run copy it into a new run folder of the profile's config.
RESULTS_ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "results")


def start_files(root):
    """The shared stages' files of run folder `root` (relative paths): config.json and the files under data/,
    checkpoints/ and eval/ that no lineage owns, without partial checkpoints (*_step<n>.pt) or files being written
    (not timings/: a start is the stages, not the wall times of the machine that made them)."""
    files = ["config.json"]
    for folder in ("data", "checkpoints", "eval"):
        for name in sorted(os.listdir(os.path.join(root, folder))) if os.path.isdir(os.path.join(root, folder)) else []:
            if not re.search(r"lineage_\d+|_step\d+\.pt$|\.tmp", name):
                files.append(f"{folder}/{name}")
    return files


def export_start(root, folder):
    """folder/start/: a copy of run folder `root`'s shared stages (start_files), for a commit that every lineage
    of the profile starts from (committed_start). Refused (RunFolderError) before the shared stages finished
    (run --prepare first). Returns the paths written."""
    needed = ("data/D0.npz", "checkpoints/bc.pt", "eval/pi0.json", "eval/bc.json")
    missing = [rel for rel in needed if not os.path.isfile(os.path.join(root, rel))]
    if missing:
        raise RunFolderError(f"--export-start: {root} has not finished its shared stages ({', '.join(missing)} "
                             "missing): run the same command with --prepare first")
    written = []
    for rel in start_files(root):
        dst = os.path.join(folder, "start", rel)
        try:
            os.makedirs(os.path.dirname(dst), exist_ok=True)
            shutil.copyfile(os.path.join(root, rel), f"{dst}.{os.getpid()}.tmp")
        except OSError as err:
            raise RunFolderError(f"--export-start {folder}: cannot write {dst}: {err.strerror or err}. Give a folder "
                                 "you can create and write.") from None
        os.replace(f"{dst}.{os.getpid()}.tmp", dst)
        written.append(dst)
    return written


def committed_start(profile, cfg, root):
    """RESULTS_ROOT/<profile>/start/ if the repository holds a start of this run's config (methods and rounds aside:
    the shared stages depend on neither) that run folder `root` still lacks; None
    (and a line saying why) where it is another config's, or where `root` already has a pi_0 of its own."""
    start = os.path.join(RESULTS_ROOT, profile, "start")
    if not os.path.isfile(os.path.join(start, "config.json")):
        return None
    stored = without_retired_fields(start, read_json(os.path.join(start, "config.json")))
    try:
        check_same_config(start, {**stored, "methods": cfg.methods, "name": cfg.name, "rounds": cfg.rounds}, cfg,
                          advice="")
    except ConfigMismatch as err:
        print(f"not loading the committed start: {str(err).strip()} (this run computes its own shared stages)")
        return None
    if all(os.path.exists(os.path.join(root, rel)) for rel in start_files(start)):
        return None  # loaded before (or made here): nothing to copy
    pi0 = os.path.join(root, "checkpoints", "bc.pt")
    if os.path.exists(pi0) and weights_sha256(pi0) != weights_sha256(os.path.join(start, "checkpoints", "bc.pt")):
        print(f"not loading the committed start {start}: {root} has a pi_0 of its own (its lineages join only each "
              "other's); give --out a new folder to start from the committed one")
        return None
    return start



def copy_from(run, src):
    """Seed the run folder with the finished stages of folder `src`, made with the same config but fewer methods
    (a row added to a finished run, e.g. the sigma = 0 control beside table2): its data, checkpoints, evaluations,
    timings and lineages are copied in, each lineage.json given this folder's config, so only the new methods'
    stages run. The stage seeds do not depend on the methods list: the copied stages are those this run would
    compute. If src ran the other of the recipes authors_lever / authors_lever_seeds (independent lineages there,
    training seeds on lineage 0's interventions here, or the reverse), only the shared stages and lineage 0 are
    copied: lineage 0 is the same run under both, the others are not. A src of shared stages only (no lineage
    folder: a committed start) may run other methods and rounds, on which those stages do not depend; a src of fewer
    rounds gives this run its first rounds (more rounds: --rounds 2 --copy-from a one-round folder). Refused
    (ConfigMismatch) if src differs in any other field (FOLDER_FREE_FIELDS aside), runs a method this run lacks,
    or has another pi_0 than one already here; files already here are kept. Returns the count."""
    path = os.path.join(src, "config.json")
    if not os.path.isfile(path):
        raise RunFolderError(f"--copy-from {src}: not a run folder (no config.json there)")
    if os.path.realpath(src) == os.path.realpath(run.root):
        raise RunFolderError(f"--copy-from {src}: that is this run's own folder; name the finished run to copy from")
    old, cfg = read_json(path), run.cfg
    # a folder of shared stages only (a start: D0, pi_0, the BC row) serves any methods and rounds; a folder of fewer
    # rounds holds this run's first rounds (no stage's result or seed depends on the round count)
    shared_only = not any(re.fullmatch(r"lineage_\d+", name) for name in os.listdir(src))
    fewer_rounds = shared_only or old.get("rounds", cfg.rounds) <= cfg.rounds
    extra = [m for m in old.get("methods", ()) if m not in cfg.methods]
    if extra and not shared_only:
        raise ConfigMismatch(f"--copy-from {src}: it runs {', '.join(extra)}, which this run does not; copy only from "
                             f"a folder whose methods are among this run's ({', '.join(cfg.methods)})")
    old = without_retired_fields(src, old)
    lever = {"authors_lever", "authors_lever_seeds"}
    lineage_0_only = old.get("recipe", "paper") != cfg.recipe and {old.get("recipe"), cfg.recipe} == lever
    check_same_config(src, {**old, "methods": cfg.methods, "name": cfg.name,
                            **({"recipe": cfg.recipe} if lineage_0_only else {}),
                            **({"rounds": cfg.rounds} if fewer_rounds else {})}, cfg,
                      advice="--copy-from takes the stages of a run that differs only in its methods (or in "
                             "authors_lever / authors_lever_seeds): run the other fields' change from scratch in its "
                             "own folder.")
    pi0_src, pi0_here = (os.path.join(r, "checkpoints", "bc.pt") for r in (src, run.root))
    if os.path.exists(pi0_src) and os.path.exists(pi0_here) and weights_sha256(pi0_src) != weights_sha256(pi0_here):
        raise ConfigMismatch(f"--copy-from {src}: its pi_0 differs from the one already in {run.root} (another "
                             "machine or seed); its lineages pair only with their own pi_0. Copy into a new folder.")
    copied = 0
    for dirpath, _, names in os.walk(src):
        rel_dir = os.path.relpath(dirpath, src)
        top = rel_dir.split(os.sep)[0]
        if top not in STAGE_FOLDERS and not re.fullmatch(r"lineage_\d+", top):
            continue  # the report, the log, the figures: this run writes its own
        for name in sorted(names):
            rel = os.path.join(rel_dir, name)
            if ".tmp" in name or os.path.exists(os.path.join(run.root, rel)):
                continue  # a stage being written there, or one this folder already has
            other = re.search(r"lineage_(\d+)", rel)
            if lineage_0_only and other and other.group(1) != "0":
                continue  # another replicate design: lineages 1, 2, ... are not this run's
            dst = run.path(rel)
            if name == "lineage.json":
                write_json(dst, {**read_json(os.path.join(src, rel)), "config": asdict(cfg)})
            else:
                tmp = f"{dst}.{os.getpid()}.tmp"
                shutil.copyfile(os.path.join(src, rel), tmp)
                os.replace(tmp, dst)  # a stage is finished only when its file is complete
            copied += 1
    run.log(f"copied {copied} stage files from {src} (the same config, methods {', '.join(old.get('methods', ()))}"
            + (f"; recipe {old.get('recipe')} there: lineage 0 only)" if lineage_0_only else ")"))
    return copied


def join_lineage(run, path):
    """Unpack a lineage results file (export_lineages) into the run folder, so --report merges it. Refused
    (ConfigMismatch, naming what differs) if it was made with another config (FOLDER_FREE_FIELDS aside), from
    another pi_0 than the folder's (its checkpoints/bc.pt, else its other lineages' records), or if a file it
    holds is already in the folder with other content. Joining the same file twice changes nothing."""
    if not os.path.isfile(path):
        raise RunFolderError(f"--join {path}: no such file (a lineage results file, written by --export-lineages)")
    data = load_stage_file(path, _read_lineage_file)
    if not isinstance(data, dict) or data.get("format") != LINEAGE_FILE_FORMAT:
        raise RunFolderError(f"{path} is not a lineage results file (format {LINEAGE_FILE_FORMAT!r}, written by "
                             "python dagger.py --profile P --report --export-lineages FOLDER)")
    lineage = data["lineage"]
    check_same_config(f"{path} (lineage {lineage})", data["config"], run.cfg,
                      advice="A lineage joins a run folder only if it was made with the folder's config: join it "
                             "into a folder of its own config (--profile and options as it was run, --out).")
    label, others = label_of(data), sorted(folder_labels(run.root, but=lineage) - {label_of(data)})
    if others:
        raise ConfigMismatch(f"{path} (lineage {lineage}) was made with {LABEL_WORDS.get(label, label)}, "
                             f"{run.root}'s lineages with {LABEL_WORDS.get(others[0], others[0])}: one table holds "
                             "one return label. Join it into a folder of its own (--out).")
    pi0 = folder_pi0(run)
    if pi0 is not None and pi0 != data["pi0_sha256"]:
        raise ConfigMismatch(
            f"{path} (lineage {lineage}) was made from another pi_0 (the SHA-256 of its weights "
            f"{data['pi0_sha256'][:12]}... there, {pi0[:12]}... in {run.root}): its numbers pair only with the "
            "pi_0 they were made from. Join it into a folder of that pi_0.")
    at = lambda rel: os.path.join(run.root, rel)  # noqa: E731 (run.path would make folders of a refused join)
    clash = [rel for rel, content in data["files"].items() if os.path.exists(at(rel)) and read_json(at(rel)) != content]
    if clash:
        raise ConfigMismatch(f"{path} (lineage {lineage}) holds other results than {run.root} already has: "
                             + ", ".join(sorted(clash)[:5]) + (" ..." if len(clash) > 5 else "")
                             + f". Delete lineage_{lineage}/ there to join the file's lineage instead.")
    for rel, content in data["files"].items():
        if is_evaluation(rel):
            check_evaluation(f"{path} (lineage {lineage}): its {rel}", content, run.cfg,
                             "Export the lineage again from its run folder (--report --export-lineages FOLDER).")
    for rel, content in data["files"].items():
        if not os.path.exists(at(rel)):
            write_json(run.path(rel), content)
    run.log(f"joined lineage {lineage} ({data['rounds_finished']} of {run.cfg.rounds} rounds finished) from {path}")
    return lineage


def folder_labels(root, but=None):
    """The return labels of the lineages in run folder `root` (their lineage.json), lineage `but` aside."""
    labels = set()
    for name in os.listdir(root) if os.path.isdir(root) else []:
        record = os.path.join(root, name, "lineage.json")
        if re.fullmatch(r"lineage_\d+", name) and name != f"lineage_{but}" and os.path.exists(record):
            labels.add(label_of(read_json(record)))
    return labels


def _read_lineage_file(path):
    with open(path, "rb") as f:
        gzipped = f.read(2) == b"\x1f\x8b"
    with (gzip.open(path, "rt") if gzipped else open(path)) as f:
        return json.load(f)


def folder_pi0(run):
    """The SHA-256 of the run folder's pi_0: its checkpoints/bc.pt, else the one its lineages record; None if
    neither is there yet."""
    pi0 = os.path.join(run.root, "checkpoints", "bc.pt")
    if os.path.exists(pi0):
        return weights_sha256(pi0)
    for name in sorted(os.listdir(run.root)):
        record = os.path.join(run.root, name, "lineage.json")
        if re.fullmatch(r"lineage_\d+", name) and os.path.exists(record):
            return read_json(record)["pi0_sha256"]
    return None


def without_retired_fields(where, stored):
    """The stored config `stored` (a dict) without its RETIRED_FIELDS, each checked to hold a value of the
    behaviour that remains; ConfigMismatch naming `where` and the field otherwise."""
    if any(key in stored for key in RECIPE_FIELDS):
        combination = tuple(stored.get(key, default) for key, default in RECIPE_FIELDS.items())
        if combination not in RECIPE_OF_FIELDS:
            raise ConfigMismatch(f"{where} was made with " + ", ".join(
                f"{k} = {v!r}" for k, v in zip(RECIPE_FIELDS, combination)) + ", a combination no recipe runs now "
                "(the recipes: paper, authors_lever, authors_lever_seeds). Use the commit that made it to run or "
                "report it.")
        stored = {**{k: v for k, v in stored.items() if k not in RECIPE_FIELDS}, "recipe": RECIPE_OF_FIELDS[combination]}
        for old, new in RECIPE_NAME_PARTS.items():
            if isinstance(stored.get("name"), str) and old in stored["name"]:
                stored["name"] = stored["name"].replace(old, new)
                break
    for key, allowed in RETIRED_FIELDS.items():
        if key in stored and allowed is not ANY_VALUE and stored[key] not in allowed:
            why = (f"a field that left the Config: {RETIRED_ADVICE[key]}" if key in RETIRED_ADVICE else
                   "an option deleted since (measured and not adopted: benchmarks/README.md)")
            raise ConfigMismatch(f"{where} was made with {key} = {stored[key]!r}, {why}; this code runs only {key} = "
                                 + " / ".join(repr(v) for v in allowed) + ". Use the commit that made it to run or "
                                 "report it.")
    return {key: value for key, value in stored.items() if key not in RETIRED_FIELDS}


def check_same_config(root, old, cfg, advice=None):
    """ConfigMismatch naming every field that differs from the folder's config (FOLDER_FREE_FIELDS aside;
    RETIRED_FIELDS checked and dropped: without_retired_fields)."""
    old = without_retired_fields(root, old)
    saved = asdict(cfg)
    for key, value in saved.items():  # JSON keeps tuples as lists
        if isinstance(value, tuple):
            saved[key] = tuple(value)
            if isinstance(old.get(key), list):
                old[key] = tuple(old[key])
    # a field added after the run started counts as unchanged if it has its default value
    defaults = {f.name: f.default for f in fields(cfg)}
    changed = {k for k in saved if k not in FOLDER_FREE_FIELDS and old.get(k, defaults[k]) != saved[k]}
    if changed:
        raise ConfigMismatch(
            f"{root} holds a run made with another config: "
            + ", ".join(f"{k} = {old.get(k, defaults[k])!r} there, {saved[k]!r} now" for k in sorted(changed))
            + ".\n" + (advice or f"Either give this run its own folder (--out runs/<new name>), or delete {root} "
                                    "to start it afresh (its finished stages are lost)."))


# An evaluation file (dagger.evaluation): eval/<name>.json under the folder or a round, <name>_unseen.json on the
# unseen scenarios; {"success": (eval_scenarios, eval_repeats) true/false, "seeds": the scenarios' seeds}.
EVALUATION_ADVICE = ("Delete it and run the same command again to evaluate that policy again (in a folder of joined "
                     "lineage results: --join the lineage's results file again).")


def is_evaluation(name):
    """Whether a '/'-separated stage name is an evaluation file (eval/bc.json, lineage_0/round_1/eval/pooled.json)."""
    return re.search(r"(^|/)eval/[^/]+\.json$", name) is not None


def check_evaluation(where, evaluation, cfg, advice):
    """RunFolderError naming `where` (the file's path, or words ending in it) and saying `advice`, unless
    `evaluation` is one of cfg's: success a (cfg.eval_scenarios, cfg.eval_repeats) table of true/false on the
    first eval_scenarios evaluation scenarios (envs.eval_seeds), or unseen ones (envs.unseen_seeds) for a file
    named *_unseen.json. Its seeds are checked where the file lists them (dagger.evaluation always does).
    Without this a file of another shape is averaged into its table cell as if it were one."""
    unseen = where.endswith("_unseen.json")
    seeds = (envs.unseen_seeds() if unseen else envs.eval_seeds())[:cfg.eval_scenarios]
    shape = (cfg.eval_scenarios, cfg.eval_repeats)
    problem = None
    if not isinstance(evaluation, dict) or "success" not in evaluation:
        problem = "no success table"
    else:
        try:
            success = np.asarray(evaluation["success"])
        except ValueError:  # rows of unequal length
            success = None
        if success is None:
            problem = "success rows of unequal length"
        elif success.shape != shape:
            problem = f"success of shape {success.shape}"
        elif success.dtype.kind not in "biuf" or not np.isin(success, (0, 1)).all():
            problem = "success values other than true/false"
        elif "seeds" in evaluation and evaluation["seeds"] != seeds:
            problem = f"seeds {seed_words(evaluation['seeds'])}"
    if problem:
        raise RunFolderError(
            f"{where} is not an evaluation of this run: {problem}; expected success of shape {shape} "
            f"(eval_scenarios x eval_repeats of the run's config) on the {'unseen' if unseen else 'evaluation'} "
            f"scenarios' seeds {seed_words(seeds)}. {advice}")


def seed_words(seeds):
    """Scenario seeds in a few words: 10000..10099 for a run of consecutive seeds, else the list (its start)."""
    if not isinstance(seeds, list):
        return repr(seeds)
    if seeds and all(isinstance(s, int) for s in seeds) and seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"{seeds[0]}..{seeds[-1]} ({len(seeds)} seeds)"
    return repr(seeds[:5])[:-1] + (", ...]" if len(seeds) > 5 else "]") + f" ({len(seeds)} seeds)"


def timing_name(name):
    """The timings/ name of a stage file: its kind (demos, bc, train_bc, collect, calibrate, train_<method>,
    evaluate), then its lineage and round (and a chain of its own, e.g. closed_loop)."""
    parts = name[:-len(os.path.splitext(name)[1])].split("/")
    where = "/" + "/".join(p for p in parts[:-1] if p != "checkpoints") if parts[0].startswith("lineage_") else ""
    if parts[-2] == "eval":
        return "evaluate/" + "/".join(parts)
    kind = {"D0": "demos", "bc": "bc", "bc_continued": "train_bc", "D": "collect",
            "calibration": "calibrate"}.get(parts[-1], "train_" + parts[-1])
    return kind + where


LOCK_FOLDER = ".locks"  # the run folder's lock files (Run.hold_lineages, Run.stage_lock); nothing else reads them


def try_lock(path):
    """(file descriptor, None) with an exclusive flock on `path` (created), this process's PID written in it; or
    (None, the PID written by the process that holds it) if another open file holds it."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
        os.close(fd)
        return None, holder
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    return fd, None


def weights_sha256(path):
    """The SHA-256 (hex) of a policy checkpoint's weights, name by name: which pi_0 a lineage was made from
    (the same weights give the same digest however the file was written)."""
    state = load_stage_file(path, torch.load, map_location="cpu", weights_only=True)["state_dict"]
    digest = hashlib.sha256()
    for name in sorted(state):
        digest.update(name.encode())
        digest.update(state[name].contiguous().numpy().tobytes())
    return digest.hexdigest()


def write_json(path, data):
    tmp = f"{path}.{os.getpid()}.tmp"  # per process: parallel lineages (--lineage i) write the same report
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)  # a stage is finished only when its file is complete


def save_episodes(path, episodes):
    tmp = f"{path}.{os.getpid()}.tmp.npz"
    write_episodes(tmp, episodes)
    os.replace(tmp, path)


def load_stage_file(path, loader, *args, **kwargs):
    """loader(path) for a finished stage's file; a damaged file (truncated, not what it should be) is an error
    that names it and says how to re-make it, never a raw EOFError or a silently reused stage."""
    try:
        return loader(path, *args, **kwargs)
    except (FileNotFoundError, KeyboardInterrupt):
        raise
    except Exception as err:
        why = ("truncated, or not a checkpoint" if isinstance(err, checkpoints.CheckpointDamagedError)  # it says so
               else f"{type(err).__name__}: {err}")
        raise RunFolderError(f"{path} is damaged ({why}). Delete it and run the same "
                             "command again: that stage is made again, the other finished stages are kept.") from None


def _read_json(path):
    with open(path) as f:
        return json.load(f)


def read_json(path):
    return load_stage_file(path, _read_json)


def load_episodes(path):
    return load_stage_file(path, read_episodes)


def write_episodes(path, episodes):
    """Write a list of episode dicts to one .npz. A key whose first axis is the episode length T in every
    episode ('obs', 'q', 'action', 'expert', ...) is concatenated along time and cut back with 'offsets';
    the others ('seed' always, 'success', a goal vector) must have one shape in all episodes: stacked."""
    if len(episodes) == 0:
        raise ValueError("write_episodes: empty episode list")
    lengths = np.array([len(ep["q"]) for ep in episodes], dtype=np.int64)
    keys = sorted(set().union(*[ep.keys() for ep in episodes]))
    data = {"offsets": np.concatenate([[0], np.cumsum(lengths)])}
    for key in keys:
        if any(key not in ep for ep in episodes):
            raise ValueError(f"write_episodes: key {key!r} is missing from some episodes")
        values = [np.asarray(ep[key]) for ep in episodes]
        if key != "seed" and all(v.ndim >= 1 and len(v) == n for v, n in zip(values, lengths)):
            data["step/" + key] = np.concatenate(values, axis=0)
        elif all(v.shape == values[0].shape for v in values):
            data["episode/" + key] = np.stack(values)
        else:
            raise ValueError(f"write_episodes: key {key!r} is neither per-step (first axis T) nor "
                             f"of one shape in every episode")
    np.savez_compressed(path, **data)


def read_episodes(path):
    """Inverse of write_episodes: a list of episode dicts (FileNotFoundError naming a missing path)."""
    data = np.load(path)
    offsets = data["offsets"]
    episodes = [dict() for _ in range(len(offsets) - 1)]
    for name in data.files:
        kind, _, key = name.partition("/")
        values = data[name]
        for i, ep in enumerate(episodes):
            if kind == "step":
                ep[key] = values[offsets[i]:offsets[i + 1]]
            elif kind == "episode":
                v = values[i]
                if key == "seed":
                    v = int(v)
                elif v.ndim == 0 and v.dtype == bool:
                    v = bool(v)
                ep[key] = v
    return episodes


def load_policy(path, device):
    return load_stage_file(path, checkpoints.load_policy, device=device)


def calibration_to_json(cal):
    """A calibrate.Calibration as plain lists and numbers (calibration.json)."""
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(cal).items()}


def calibration_from_json(data):
    """The inverse of calibration_to_json (older files: without W_ci or paper_median_step, and with the deleted
    unguided control's 'unguided_pooled' / 'closed_loop_pooled', dropped)."""
    dtypes = {"episode_index": np.int64, "timestep": np.int64, "blend_episode": np.int64,
              "blend_start": np.int64, "blend_kept": bool}
    kwargs = {k: v for k, v in data.items() if k not in ("unguided_pooled", "closed_loop_pooled")}
    for k, v in kwargs.items():
        if isinstance(v, list) and k != "W_ci":                        # the arrays
            kwargs[k] = np.asarray(v, dtype=dtypes.get(k, np.float64))
    return calibrate.Calibration(**kwargs)
