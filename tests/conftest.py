"""Test-wide settings. The networks under test are tiny: one torch thread is as fast as two on an idle
machine and many times faster on a loaded one (thread oversubscription), so tests use one."""
import gc
import importlib.util
import os
import sys
from collections import namedtuple

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(scope="session")
def load_benchmark():
    """load_benchmark(name) -> the module benchmarks/<name>.py (a script folder, not a package)."""
    def load(name):
        path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", name + ".py")
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    return load


@pytest.fixture
def trained_stages(monkeypatch):
    """The list, in order, of the checkpoint names Run.train is asked for from here on (the stages that trained
    rather than being loaded or copied)."""
    from experiment import run_folder
    trained, real = [], run_folder.Run.train

    def spy(self, name, *args, **kwargs):
        trained.append(name)
        return real(self, name, *args, **kwargs)
    monkeypatch.setattr(run_folder.Run, "train", spy)
    return trained


@pytest.fixture
def augmentation_samplers(monkeypatch):
    """The list, in order, of every relabel.AugmentationSampler built from here on, as dicts: noise (the kind),
    sigma (as the constructor received it), episodes and the built sampler itself."""
    import relabel
    built, real = [], relabel.AugmentationSampler.__init__

    def spy(self, episodes, make_env, stats, noise, sigma, cfg=None, *rest, **kwargs):
        real(self, episodes, make_env, stats, noise, sigma, cfg, *rest, **kwargs)
        built.append(dict(noise=noise, sigma=sigma, episodes=list(episodes), sampler=self))
    monkeypatch.setattr(relabel.AugmentationSampler, "__init__", spy)
    return built


def is_figure(code):
    """A drawing function: what runs inside one is the figure's, not the method's."""
    return code.co_name.startswith(("fig", "plot_", "draw_")) or code.co_name == "figures"


SmokeRun = namedtuple("SmokeRun", "root called")


@pytest.fixture(scope="session")
def smoke_in_one_process(tmp_path_factory):
    """The smoke profile (every stage and Table I row kind, two lineages) run once in this process with one worker,
    traced: SmokeRun(root: its folder, called: {(module, qualified name)} of every function the method called). A
    call made only inside a figure's drawing does not count, except for the drawing functions themselves. Shared by
    the reading guide's test (what the run calls) and the Slurm test (the numbers every split of the run must match):
    one run instead of two.

    The trace is sys.settrace's 'call' event, answered with None (no line events): unlike sys.setprofile it is not
    called for every C function (the traced run took 1.6x the untraced one, once, beside a lineage on the
    Intel Xeon 6/167). A tracer already set (coverage) is put back afterwards."""
    from experiment import profiles, report
    called, seen = set(), set()

    def trace(frame, event, arg):
        code = frame.f_code
        key = (code.co_filename, code.co_qualname)
        if key in seen or code.co_name == "__del__":  # a finalizer of an object an earlier test made is not the run
            return None
        caller = frame.f_back
        while caller is not None and not is_figure(caller.f_code):
            caller = caller.f_back
        if caller is None or is_figure(code):  # from the method, or a drawing function itself
            seen.add(key)
            called.add((os.path.splitext(os.path.basename(code.co_filename))[0], code.co_qualname))
        return None

    root = str(tmp_path_factory.mktemp("one_process") / "smoke")
    gc.collect()  # finalize what earlier tests left behind before the trace starts
    previous = sys.gettrace()
    sys.settrace(trace)
    try:
        report.run_experiment(profiles.PROFILES["smoke"], root, workers=1)
    finally:
        sys.settrace(previous)
    return SmokeRun(root, called)
