"""Test-wide settings. The networks under test are tiny: one torch thread is as fast as two on an idle
machine and many times faster on a loaded one (thread oversubscription), so tests use one."""
import importlib.util
import os

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture
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
