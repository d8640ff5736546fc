"""Two processes on one run folder: runs of different lineages both finish (the shared stages made once, the other
waiting), a second run of the same lineage stops at once naming the PID that holds it, and a killed holder
leaves no lock behind."""
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from experiment import run_folder

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Two lineages of the smallest loop that makes every shared stage (D0, pi_0, pi_0's and the BC row's evaluations)
# and a round of HG-DAgger: seconds on an idle core.
CONFIG = ("dagger.Config(name='two', n_demos=4, rounds=1, lineages=2, K=5, down_dims=(8, 16), bc_steps=30, "
          "finetune_steps=12, batch_size=32, methods=('bc', 'hg_dagger'), eval_scenarios=2, eval_repeats=1, "
          "eval_unseen=False)")


def start(root, code):
    """A python process in the repository running `code` (dagger imported, cfg = CONFIG, root given)."""
    script = ("import sys, torch, dagger; from experiment import cli, report, run_folder; torch.set_num_threads(1); "
              f"cfg = {CONFIG}; root = {root!r}\n" + code)
    return subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def run_lineage(root, lineage):
    """`python dagger.py --lineage i` as the command line runs it: a run-folder error is one line, status 2."""
    return start(root, f"cli.run_command(lambda: report.run_experiment(cfg, root, lineage={lineage}))")


def wait_for_lock(root, name, proc, timeout=120):
    """Until process proc holds the lock file `name` of the run folder (its PID written in it)."""
    path = os.path.join(root, run_folder.LOCK_FOLDER, name)
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        if os.path.exists(path) and open(path).read() == str(proc.pid):
            return
        time.sleep(0.05)
    raise AssertionError(f"process {proc.pid} never wrote {path}: {proc.communicate()[1][-3000:]}")


@pytest.mark.slow
def test_two_lineages_into_one_folder_both_finish_and_a_second_run_of_one_stops_naming_its_pid(tmp_path):
    root = str(tmp_path / "run")
    first, second = run_lineage(root, 0), run_lineage(root, 1)  # started together: both make D0 and pi_0 ...
    wait_for_lock(root, "lineage_0.lock", first)
    t0 = time.time()
    again = run_lineage(root, 0)  # ... and lineage 0 a second time while the first runs it
    out, err = again.communicate(timeout=120)
    assert again.returncode == 2, err
    assert f"in use: process {first.pid} runs lineage 0" in err and "Traceback" not in err
    assert "D0:" not in out  # refused before any stage
    assert time.time() - t0 < 60
    for proc in (first, second):
        out, err = proc.communicate(timeout=1200)
        assert proc.returncode == 0, err[-3000:]
    results = json.load(open(os.path.join(root, "results.json")))["success"]
    assert sorted(results["hg_dagger"]) == ["0", "1"]
    log = open(os.path.join(root, "log.txt")).read()
    assert log.count("BC: 30 steps") == 1  # pi_0 was trained once, the other process waited and loaded it
    assert log.count("D0: 4 oracle demonstrations") == 1


@pytest.mark.slow
def test_a_killed_run_leaves_its_lineage_free(tmp_path):
    """The lock is the system's (flock): SIGKILL, which runs no clean-up, still frees the lineage."""
    root = str(tmp_path / "run")
    holder = start(root, "run = run_folder.Run(root, cfg); run.hold_lineages([1]); print('held', flush=True); "
                         "import time; time.sleep(600)")
    assert holder.stdout.readline().strip() == "held"
    cfg = run_folder.read_json(os.path.join(root, "config.json"))
    import dagger
    run = run_folder.Run(root, dagger.Config(**cfg))
    run.hold_lineages([0])  # another lineage is free
    try:
        run.hold_lineages([1])
        raise AssertionError("lineage 1 was taken twice")
    except run_folder.FolderInUse as err:
        assert f"process {holder.pid} runs lineage 1" in str(err)
    holder.send_signal(signal.SIGKILL)
    holder.wait(timeout=60)
    run.hold_lineages([1])
    run.release_lineages()
