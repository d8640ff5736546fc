"""experiment/workers.py: the jobs' results in the jobs' order, however the worker processes finish them."""
import os
import time

import pytest

from experiment import workers


def finish(value, wait_for=None, then_write=None):
    """A worker's job (module level: a spawned worker imports it): waits up to 60 s for the file wait_for, writes
    the file then_write, returns value."""
    deadline = time.time() + 60
    while wait_for and not os.path.exists(wait_for) and time.time() < deadline:
        time.sleep(0.01)
    if then_write:
        open(then_write, "w").close()
    return value


@pytest.mark.slow
def test_results_and_progress_come_in_the_jobs_order_when_the_first_job_finishes_last(tmp_path):
    """Job a waits for the file job c writes, so two workers finish b first and a after c. Fails if in_parallel
    hands its results, or each() its calls, in the order the jobs finished (concurrent.futures.as_completed)."""
    marker = str(tmp_path / "c_done")
    seen = []
    jobs = [("a", marker, None), ("b", None, None), ("c", None, marker)]
    assert workers.in_parallel(finish, jobs, 2, each=seen.append) == ["a", "b", "c"]
    assert seen == ["a", "b", "c"]


def total(tensor):
    """A worker's job: the sum of a tensor it received."""
    return float(tensor.sum())


@pytest.mark.parametrize("how", ["worker_map", "in_parallel"])
def test_a_jobs_tensors_stay_where_they_are_in_the_caller(how):
    """The caller keeps computing with what it handed to a worker (pi_0 samples the next collection beside the BC
    row's worker). Fails where the arguments are pickled by the pool's feeder thread with torch's reducers, which
    move the caller's storage to shared memory under its feet (is_shared() turns True: a race with its reads)."""
    import torch
    t = torch.arange(1000, dtype=torch.float32)
    jobs = [(t,), (t[:10],)]
    got = list(workers.worker_map(2)(total, jobs)) if how == "worker_map" else workers.in_parallel(total, jobs, 2)
    assert got == [float(t.sum()), 45.0]
    assert not t.is_shared()
