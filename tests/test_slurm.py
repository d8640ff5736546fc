"""The cluster recipe of experiment/RUNNING.md on a real Slurm: experiment/slurm_recipe.sh (the shared stages, the
lineages as a job array, the report, each waiting for the one before) submitted to a one-node Slurm started on this
machine in a temporary folder (munged, slurmctld, slurmd, as root), on the smoke profile's two lineages. Its table
must be the one a single process makes, each array task must run its own lineage, and a lineage cancelled in the
middle of a stage must finish, when the recipe is submitted again, with the same numbers.

Slow: the recipe's run and one more lineage, and a single-process smoke run for the reference (shared with the
reading guide's test: tests/conftest.py). On the Intel Xeon (family 6, model 167; 2 cores), nearly idle: the
recipe's run with the cluster's start 73 s, the cancelled and resubmitted lineage 60 s (2026-11-29).
Skipped where Slurm and MUNGE are not installed (.ci/run installs them: apt-get install slurm-wlm munge) or the
test is not root (the daemons run as root: SlurmUser=root).
"""
import glob
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RECIPE = os.path.join(ROOT, "experiment", "slurm_recipe.sh")
PROGRAMS = ("munged", "slurmctld", "slurmd", "sbatch", "scontrol", "squeue", "scancel", "sinfo")
MISSING = [name for name in PROGRAMS if shutil.which(name) is None]

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(bool(MISSING), reason=f"Slurm and MUNGE are not installed here (no {', '.join(MISSING)}): "
                                             "apt-get install slurm-wlm munge"),
    pytest.mark.skipif(os.geteuid() != 0, reason="the one-node Slurm of this test runs its daemons as root "
                                                 "(SlurmUser=root): run it as root"),
]

# The states a job record stays in once it has ended (a job whose dependency failed stays PENDING instead, with
# the reason DependencyNeverSatisfied: Slurm's default keeps it until it is cancelled).
ENDED = {"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "PREEMPTED", "BOOT_FAIL",
         "DEADLINE"}
# s: the recipe's run took 73 s on the Intel Xeon above; an hour leaves room for a busier machine
JOB_TIMEOUT = 3600


class Cluster:
    """A one-node Slurm of this machine (2 CPUs) with its own MUNGE, every file of it in `folder`."""

    def __init__(self, folder):
        self.folder = folder
        self.conf = os.path.join(folder, "slurm.conf")
        # the jobs inherit the environment of sbatch (its default --export=ALL): `python` is this interpreter
        self.env = dict(os.environ, SLURM_CONF=self.conf,
                        PATH=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))

    def file(self, name):
        return os.path.join(self.folder, name)

    def start(self):
        key = self.file("munge.key")
        with open(os.open(key, os.O_WRONLY | os.O_CREAT, 0o600), "wb") as f:
            f.write(os.urandom(1024))
        # --force: munged refuses a socket in a folder that not everyone may enter (pytest's are 0700; every
        # client of this one runs as root)
        subprocess.run(["munged", "--force", f"--key-file={key}", f"--socket={self.file('munge.socket')}",
                        f"--pid-file={self.file('munged.pid')}", f"--log-file={self.file('munged.log')}",
                        f"--seed-file={self.file('munged.seed')}"], check=True, env=self.env)
        self.write_conf()
        for daemon in ("slurmctld", "slurmd"):
            subprocess.run([daemon, "-f", self.conf], check=True, env=self.env)
        deadline = time.time() + 120
        while self.slurm("sinfo", "-h", "-o", "%t", check=False).strip() != "idle":
            if time.time() > deadline:
                raise AssertionError("the one-node Slurm did not come up within 120 s:\n" + self.logs())
            time.sleep(0.5)

    def write_conf(self):
        node = socket.gethostname().split(".")[0]  # slurmd finds its node by the short host name
        ctld_port, slurmd_port = free_port(), free_port()
        os.makedirs(self.file("state"))
        os.makedirs(self.file("spool"))
        lines = [
            "ClusterName=pcdagger_test",
            f"SlurmctldHost={node}(127.0.0.1)",
            f"SlurmctldPort={ctld_port}",
            f"SlurmdPort={slurmd_port}",
            "SlurmUser=root",
            "SlurmdUser=root",
            "AuthType=auth/munge",
            "CredType=cred/munge",
            f"AuthInfo=socket={self.file('munge.socket')}",
            f"StateSaveLocation={self.file('state')}",
            f"SlurmdSpoolDir={self.file('spool')}",
            f"SlurmctldPidFile={self.file('slurmctld.pid')}",
            f"SlurmdPidFile={self.file('slurmd.pid')}",
            f"SlurmctldLogFile={self.file('slurmctld.log')}",
            f"SlurmdLogFile={self.file('slurmd.log')}",
            # no cgroups: a container or CI runner seldom lets a test mount them; linuxproc finds a job's
            # processes by their parents
            "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none",
            "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none",
            "MpiDefault=none",
            "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_CPU",  # a job's --cpus-per-task counts CPUs of the node's 2
            "ReturnToService=2",
            "MinJobAge=86400",  # ended jobs stay in scontrol's answers for the whole test (no accounting database)
            f"NodeName={node} NodeAddr=127.0.0.1 CPUs=2 State=UNKNOWN",
            "PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP",
        ]
        with open(self.conf, "w") as f:
            f.write("\n".join(lines) + "\n")

    def stop(self):
        """Cancel what is left of the jobs, then stop slurmd, slurmctld and munged by their pid files."""
        try:
            left = self.slurm("squeue", "-h", "-o", "%i", check=False).split()
            if left:
                self.slurm("scancel", *left, check=False)
                deadline = time.time() + 60
                while self.slurm("squeue", "-h", "-o", "%i", check=False).split() and time.time() < deadline:
                    time.sleep(1)
        finally:
            for daemon in ("slurmd", "slurmctld", "munged"):
                stop_by_pid_file(self.file(f"{daemon}.pid"))

    def slurm(self, *command, check=True):
        """A Slurm command's standard output, run against this cluster."""
        done = subprocess.run(command, env=self.env, capture_output=True, text=True, timeout=120)
        if check and done.returncode != 0:
            raise AssertionError(f"{' '.join(command)}: status {done.returncode}: {done.stderr}")
        return done.stdout

    def submit_recipe(self, out):
        """experiment/slurm_recipe.sh smoke OUT, as RUNNING.md has a user run it: the three job IDs."""
        done = subprocess.run(["bash", RECIPE, "smoke", out], env=self.env, capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 0, done.stderr
        prepare, array, report = done.stdout.split()
        return prepare, array, report

    def records(self, job):
        """Each job record of `job` (an array: one per task) as a dict of scontrol's key=value fields."""
        out = self.slurm("scontrol", "-o", "show", "job", job)
        return [dict(field.split("=", 1) for field in line.split() if "=" in field) for line in out.splitlines()]

    def wait(self, *jobs, timeout=JOB_TIMEOUT):
        """{job or 'array_task': (state, reason)} once every record of `jobs` has ended (or waits on a dependency
        that can never be met)."""
        deadline = time.time() + timeout
        while True:
            states = {}
            for job in jobs:
                for record in self.records(job):
                    name = job if record.get("ArrayTaskId") is None else f"{job}_{record['ArrayTaskId']}"
                    states[name] = (record["JobState"], record.get("Reason"))
            if all(s in ENDED or r == "DependencyNeverSatisfied" for s, r in states.values()):
                return states
            if time.time() > deadline:
                raise AssertionError(f"jobs not finished after {timeout} s: {states}\n{self.logs()}")
            time.sleep(2)

    def logs(self):
        text = ""
        for name in ("munged.log", "slurmctld.log", "slurmd.log"):
            if os.path.exists(self.file(name)):
                text += f"--- {name} (end)\n" + open(self.file(name)).read()[-3000:]
        return text


def free_port():
    """A TCP port free now on this machine (the test's daemons never collide with another Slurm's)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop_by_pid_file(path, timeout=30):
    """SIGTERM to the process whose PID the daemon wrote in `path`, SIGKILL if it is still there after timeout."""
    if not os.path.exists(path):
        return
    pid = int(open(path).read().split()[0])
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            return
        deadline = time.time() + timeout
        while time.time() < deadline:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.2)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A one-node Slurm for this file's tests, stopped at the end (also when a test or the start fails)."""
    cluster = Cluster(str(tmp_path_factory.mktemp("slurm")))
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture(scope="module")
def reference(smoke_in_one_process):
    """results.json of the smoke profile run in one process with one worker (the run every split of it must match;
    the reading guide's traced run, shared: tests/conftest.py)."""
    return json.load(open(os.path.join(smoke_in_one_process.root, "results.json")))


@pytest.fixture(scope="module")
def recipe_run(cluster, tmp_path_factory):
    """The recipe submitted once on the smoke profile, waited for: (run folder, job IDs, the dependency Slurm held
    for each job when it was submitted, the jobs' end states)."""
    out = str(tmp_path_factory.mktemp("recipe") / "smoke")
    jobs = cluster.submit_recipe(out)
    held = {job: cluster.records(job)[0]["Dependency"] for job in jobs}  # the prepare job runs for minutes
    return out, jobs, held, cluster.wait(*jobs)


def method_numbers(results):
    """results.json without stats.stage_times (the wall times of the stages: the one part two runs may differ in)."""
    stats = {key: value for key, value in results["stats"].items() if key != "stage_times"}
    return {**results, "stats": stats}


def job_output(out, name):
    """The output file of a job of the recipe (OUT/slurm/<name>), as the job wrote it."""
    return open(os.path.join(out, "slurm", name)).read()


def partial_checkpoints(out, lineage):
    """The checkpoints a training in progress writes at quarters of its steps (<policy>_step<n>.pt; gone once the
    policy's own file is written), under lineage_<lineage>/ of run folder `out`."""
    return sorted(glob.glob(os.path.join(out, f"lineage_{lineage}", "**", "*_step*.pt"), recursive=True))


def test_the_recipe_on_slurm_makes_the_single_process_table_each_task_running_its_own_lineage(
        cluster, recipe_run, reference):
    """experiment/slurm_recipe.sh smoke OUT, as experiment/RUNNING.md has a user submit it, on a real Slurm. Catches
    a job that fails under the scheduler (another interpreter or working directory, the array task's ID read at
    submission instead of in the task), an array over other lineages than the profile's, a lineage that makes the
    shared stages itself (no dependency on the prepare job, or a folder it does not share with it), a report job
    that runs before every lineage has ended, and any number of the joined table that differs from one process's."""
    out, (prepare, array, report), held, states = recipe_run
    assert held == {prepare: "(null)", array: f"afterok:{prepare}(unfulfilled)",
                    report: f"afterok:{array}_*(unfulfilled)"}  # _*: every task of the array
    assert {job: state for job, (state, _) in states.items()} == {
        prepare: "COMPLETED", f"{array}_0": "COMPLETED", f"{array}_1": "COMPLETED", report: "COMPLETED"}
    (shared_job,), tasks, (report_job,) = (cluster.records(job) for job in (prepare, array, report))
    assert all(task["StartTime"] >= shared_job["EndTime"] for task in tasks)  # ISO times: their order is the text's
    assert report_job["StartTime"] >= max(task["EndTime"] for task in tasks)
    shared = job_output(out, f"prepare-{prepare}.out")
    assert "D0: 16 oracle demonstrations" in shared and "BC: 300 steps" in shared
    assert "HG-DAgger collection" not in shared and "fine-tune" not in shared  # no lineage's stage
    for lineage, other in ((0, 1), (1, 0)):
        text = job_output(out, f"lineage_{lineage}-{array}.out")
        assert f"lineage {lineage} round 1: HG-DAgger collection" in text, text[-3000:]
        assert f"lineage {other} round" not in text
        # the shared stages were there when the task started: it neither made them nor waited for their maker (a
        # wait for the other task's report, at the end, is the run folder's order of writing it)
        assert "D0: 16 oracle demonstrations" not in text and "BC: 300 steps" not in text
        waits = [line for line in text.splitlines() if "waiting for process" in line]
        assert all("making report" in line for line in waits), waits
    table = open(os.path.join(out, "table.md")).read().strip()
    assert table in job_output(out, f"report-{report}.out")  # the report job wrote the last table: after both tasks
    assert method_numbers(json.load(open(os.path.join(out, "results.json")))) == method_numbers(reference)


def test_a_lineage_cancelled_mid_stage_finishes_with_the_same_numbers_when_the_recipe_is_submitted_again(
        cluster, recipe_run, reference, tmp_path):
    """A copy of the recipe's run without lineage 1; the recipe submitted on it, and lineage 1's task cancelled
    (scancel) while a policy trains; then, as experiment/RUNNING.md says, the report job left waiting cancelled and
    the recipe submitted again. Catches a report that runs although a task of the array failed, a stage file or a
    lineage lock the kill leaves behind that stops the new task, a resubmission that makes the finished stages again
    instead of resuming, and a resumed training that does not go on exactly where it stopped (other numbers)."""
    out = str(tmp_path / "smoke")
    shutil.copytree(recipe_run[0], out, ignore=shutil.ignore_patterns(
        "lineage_1", "slurm", "results.json", "results.csv", "table.md", "report.md"))
    prepare, array, report = cluster.submit_recipe(out)
    deadline = time.time() + JOB_TIMEOUT
    while not partial_checkpoints(out, 1):
        assert time.time() < deadline, f"lineage 1 wrote no checkpoint within {JOB_TIMEOUT} s"
        task = cluster.records(f"{array}_1")[0]["JobState"]
        assert task not in ENDED, f"lineage 1's task ended ({task}) before it wrote a checkpoint"
        time.sleep(0.5)  # the first checkpoint comes at a quarter of a training: three quarters, seconds, remain
    cluster.slurm("scancel", f"{array}_1")
    states = cluster.wait(prepare, array, report)
    assert {job: state for job, (state, _) in states.items()} == {
        prepare: "COMPLETED", f"{array}_0": "COMPLETED", f"{array}_1": "CANCELLED", report: "PENDING"}
    assert states[report][1] == "DependencyNeverSatisfied"
    assert not os.path.exists(os.path.join(out, "slurm", f"report-{report}.out"))  # it never ran
    left = partial_checkpoints(out, 1)
    assert left, "lineage 1's training ended before the cancel reached it: no stage was stopped in its middle"
    stopped = max(left, key=lambda path: int(path.rsplit("_step", 1)[1][:-3]))  # the one a resumed training reads
    assert not os.path.exists(stopped.rsplit("_step", 1)[0] + ".pt")

    cluster.slurm("scancel", report)
    prepare, array, report = cluster.submit_recipe(out)
    states = cluster.wait(prepare, array, report)
    assert {job: state for job, (state, _) in states.items()} == {
        prepare: "COMPLETED", f"{array}_0": "COMPLETED", f"{array}_1": "COMPLETED", report: "COMPLETED"}
    text = job_output(out, f"lineage_1-{array}.out")
    assert f"resuming from {os.path.relpath(stopped, out)}" in text, text[-3000:]
    assert "lineage 1 round 1: HG-DAgger collection" not in text  # D_1, made before the kill, was loaded
    assert method_numbers(json.load(open(os.path.join(out, "results.json")))) == method_numbers(reference)
