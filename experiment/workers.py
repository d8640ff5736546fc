"""Worker processes: D0's plans, the arms of a round side by side, the BC row beside the rounds.

Each job is a module-level function and plain arguments: the run folder's path and the config as a dict (a worker
opens its own handle on the folder to write its stages and log) and the data the loop has in hand (D0, the rounds'
interventions, the calibration), pickled to it. Every stage has its own seed and file, so the numbers do not depend
on how many workers ran them. Workers are spawned (not forked: torch's threads do not survive a
fork) and run one torch thread each, so two workers use two cores. A stage that runs alone may take more threads
(torch_threads), a number fixed by the stage: a thread count changes a training's last bits.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import multiprocessing

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
        for done in [pool.submit(_one_thread, fn, *job) for job in jobs]:
            results.append(done.result())
            each(results[-1])
        return results


class InBackground:
    """fn(*args) in one worker process while this one goes on (enabled), else here and now; wait() for it."""

    def __init__(self, fn, args, enabled=True):
        self._pool = self._done = None
        if enabled:
            self._pool = concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
            self._done = self._pool.submit(_one_thread, fn, *args)
        else:
            fn(*args)

    def wait(self):
        if self._pool is not None:
            self._done.result()  # re-raises the worker's error here
            self._pool.shutdown()
            self._pool = None


def _one_thread(fn, *args):
    torch.set_num_threads(1)
    return fn(*args)


@contextlib.contextmanager
def torch_threads(n):
    """torch's CPU threads set to n inside the block, and back to what they were after it."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
