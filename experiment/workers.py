"""Worker processes: D0's plans, the arms of a round side by side, the BC row beside the rounds.

Each job is a module-level function of dagger.py and its arguments: the config, the data the loop has in hand (D0,
pi_0, the rounds' interventions, the calibration) and the run folder's memo and log (a Run pickles as its path and
config: a worker opens its own handle on the folder to write its stages and log), pickled to it. Every stage has its own seed and file, so the numbers do not depend
on how many workers ran them. Workers are spawned (not forked: torch's threads do not survive a
fork) and run one torch thread each, so two workers use two cores. A stage that runs alone may take more threads
(torch_threads), a number fixed by the stage: a thread count changes a training's last bits.

A job's arguments are pickled here, when it is submitted, by value (pickle.dumps). Handed to the pool as they are,
a queue's feeder thread would pickle them later with torch's reducers, which move each tensor's storage to shared
memory in place: while the loop samples pi_0 for the next collection, beside the BC row's worker that received it.
Measured with a stand-in (a model sampled here while a pool received it, 25 tries on the Intel Xeon): the output
read during the move differed from the model's in 4, by up to 0.55.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import multiprocessing
import pickle

import torch


def in_parallel(fn, jobs, workers, log=None, each=None):
    """[fn(*job) for job in jobs]: here, one after the other, or (workers > 1 and more than one job) in that many
    worker processes. each(result), if given, is called here on every result in the jobs' order as soon as it and
    those before it are done (progress lines). A worker's error is raised here."""
    each = each or (lambda result: None)
    if workers <= 1 or len(jobs) <= 1:
        results = []
        for job in jobs:
            results.append(fn(*job))
            each(results[-1])
        return results
    if log is not None:
        log(f"{len(jobs)} jobs ({fn.__name__}) in {min(workers, len(jobs))} worker processes")
    with concurrent.futures.ProcessPoolExecutor(min(workers, len(jobs)),
                                                mp_context=multiprocessing.get_context("spawn")) as pool:
        results = []
        for done in [_submit(pool, fn, job) for job in jobs]:
            results.append(done.result())
            each(results[-1])
        return results


def worker_map(workers, log=None):
    """The loop's map (dagger.policy_calibrated_dagger) with `workers` processes: map(fn, jobs) starts every job at
    once in min(workers, len(jobs)) worker processes and yields fn(*job) in the jobs' order as each is done (a job
    not waited for yet runs beside what the loop does next: the BC row beside the rounds); workers <= 1: here, one
    after the other, now. A worker's error is raised where its result is asked for."""
    def map_jobs(fn, jobs):
        jobs = list(jobs)
        if workers <= 1 or not jobs:
            return [fn(*job) for job in jobs]
        if log is not None:
            log(f"{len(jobs)} jobs ({fn.__name__}) in {min(workers, len(jobs))} worker processes")
        pool = concurrent.futures.ProcessPoolExecutor(min(workers, len(jobs)),
                                                      mp_context=multiprocessing.get_context("spawn"))
        done = [_submit(pool, fn, job) for job in jobs]

        def results():
            try:
                for future in done:
                    yield future.result()
            finally:
                pool.shutdown()
        return results()
    return map_jobs


def _submit(pool, fn, job):
    """pool.submit of fn(*job) with the arguments pickled by value now (the module docstring says why)."""
    return pool.submit(_one_thread, pickle.dumps((fn, job), protocol=pickle.HIGHEST_PROTOCOL))


def _one_thread(payload):
    fn, job = pickle.loads(payload)
    torch.set_num_threads(1)
    return fn(*job)


@contextlib.contextmanager
def torch_threads(n):
    """torch's CPU threads set to n inside the block, and back to what they were after it."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
