"""Policy checkpoint files: the format, older files' retired fields, damage, and the state a stopped run resumes from.

diffusion.py hands over plain objects -- a policy's config and state_dict, and at train()'s checkpoint steps its
training state {'step', 'optimizer', 'numpy_rng', 'torch_rng'} -- and this module writes and reads them. A file is
{'format', 'config', 'state_dict'} and, for a run that goes on from it, 'train_state': that state (the numpy
stream's state as JSON) with the co-training sampler's own state (SAMPLER_STATE: relabel's pool). Nothing here is
the paper's method.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, replace

import numpy as np
import torch

import diffusion
import relabel
from experiment import cpu_kernels, environments

CHECKPOINT_FORMAT = "diffusion-policy-v2"
# PolicyConfig fields a checkpoint of an earlier version holds: (the one value this code reads, else why not)
RETIRED_POLICY_FIELDS = {
    "schedule": ("squaredcos", "the linear noise schedule was deleted (the squared-cosine one is the only one)"),
    "joint_obs": (True, "absolute chunks (joint_obs False) were deleted: chunks are relative to q_t"),
    "image_shape": ((), "image observations are the research variant experiment/image_obs.py (--env engine3d_image)"),
    "image_features": (64, "image observations are the research variant experiment/image_obs.py"),
}


class CheckpointDamagedError(ValueError):
    """A checkpoint file that cannot be read: truncated (a run killed while copying it), or no checkpoint at all."""


def save_policy(policy, path, train_state=None, sampler=None, train_config=None):
    """The policy's config and weights (with its EMA copy and normalizer) in one file, via a temporary file: never
    half-written. train_state: diffusion.train's state at a checkpoint step, saved with the sampler's state."""
    payload = {"format": CHECKPOINT_FORMAT, "config": asdict(policy.cfg),
               "state_dict": {k: v.detach().cpu() for k, v in policy.state_dict().items()}}
    if train_state is not None:
        payload["train_state"] = {**train_state, "numpy_rng": json.dumps(train_state["numpy_rng"]),
                                  "train_config": json.dumps(train_config_fields(train_config)) if train_config
                                  else None,
                                  "sampler": _as_torch(sampler_state(sampler))}
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.{os.getpid()}.tmp"  # per process: two runs of one folder never write one temporary file
    torch.save(payload, tmp)
    os.replace(tmp, path)


def train_config_fields(train_config):
    """A diffusion.TrainConfig as JSON-able fields: its learning-rate function by name."""
    schedule = train_config.lr_schedule
    name = None if schedule is None else getattr(schedule, "__qualname__", type(schedule).__qualname__)
    return {**asdict(replace(train_config, lr_schedule=None)), "lr_schedule": name}


def load_policy(path, device="cpu"):
    """The policy saved at path (its observation encoder by the name its config records), with its train_state if the
    file keeps one. FileNotFoundError,
    CheckpointDamagedError (a ValueError), or ValueError for a config of a deleted option."""
    payload = read_checkpoint(path)
    config = dict(payload["config"])
    for name, (kept, deleted) in RETIRED_POLICY_FIELDS.items():
        stored = config.pop(name, kept)
        if (tuple(stored) if isinstance(stored, list) else stored) != kept:
            raise ValueError(f"{path!r} holds a policy with {name}={stored!r}: {deleted}; retrain the policy")
    encoder = environments.OBS_ENCODERS[config.get("obs_encoder", "flat")]
    config.setdefault("obs_encoder_sizes", encoder.sizes(**config.get("obs_encoder_args", {})))  # files made before
    config["obs_encoder"] = encoder.__name__
    policy = cpu_kernels.use_kernels(diffusion.DiffusionPolicy(diffusion.PolicyConfig(**config), device=device,
                                                               obs_encoder=encoder))
    policy.load_state_dict(payload["state_dict"])
    if "train_state" in payload:  # pi_0 with its step and AdamW state: what the arms continue (dagger.train_policy)
        policy.train_state = train_state(path, payload, random_streams=False)
    return policy


def read_checkpoint(path):
    """The payload dict of a file written by save_policy. FileNotFoundError if there is no file,
    CheckpointDamagedError if it cannot be read, ValueError if it is another format."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no policy checkpoint at {path!r}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:                                           # EOFError, zip RuntimeError, Unpickling...
        if isinstance(err, OSError):                                   # unreadable (permissions, disk): not damage
            raise
        raise CheckpointDamagedError(f"checkpoint {path} is damaged (truncated or not a checkpoint; torch.load "
                                     f"raised {type(err).__name__}): delete it and run again to re-make it") from None
    if not isinstance(payload, dict):
        raise CheckpointDamagedError(f"checkpoint {path} is damaged (it holds a {type(payload).__name__}, not a "
                                     f"checkpoint): delete it and run again to re-make it")
    if payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path!r} is not a {CHECKPOINT_FORMAT} checkpoint (format {payload.get('format')!r}): "
                         f"retrain the policy")
    return payload


def train_state(path, payload, sampler=None, random_streams=True):
    """diffusion.train's `start` from a checkpoint's payload (read from path): its step and AdamW state, and with
    random_streams its two random streams, the sampler then restored to its state at that step (a resumed run);
    without them, fine-tuning goes on from the step with its own streams (continuing pi_0)."""
    if "train_state" not in payload:
        raise ValueError(f"{path!r} holds no training state (the optimizer): it must be a checkpoint of "
                         f"train()'s checkpoint_steps, not a final policy file")
    state = payload["train_state"]
    start = {"step": int(state["step"]), "optimizer": state["optimizer"]}
    if random_streams:
        start.update(numpy_rng=json.loads(state["numpy_rng"]), torch_rng=state["torch_rng"])
        if state.get("sampler") is not None:
            restore_sampler(sampler, _as_numpy(state["sampler"]))
    return start


# A co-training sampler's attributes that a resumed training run restores, by its class: relabel.AugmentationSampler's
# pool and its counters (a sampler of another class keeps no state of its own)
SAMPLER_STATE = {relabel.AugmentationSampler: ("_pool_obs", "_pool_chunks", "_pool_mask", "_filled", "_write",
                                               "_served", "n_drawn", "n_kept")}


def sampler_state(sampler):
    """A co-training sampler's own state (None if it keeps none): its SAMPLER_STATE attributes (relabel's pool),
    a mixture's per part ({'0': ..., '1': ...}), keyed by the attribute's name without its underscore."""
    if hasattr(sampler, "samplers"):                                   # relabel.MixtureSampler: its parts in turn
        parts = {str(i): sampler_state(s) for i, s in enumerate(sampler.samplers)}
        return {i: s for i, s in parts.items() if s is not None}
    names = SAMPLER_STATE.get(type(sampler), ())
    copy = lambda v: v.copy() if isinstance(v, np.ndarray) else v  # noqa: E731 (the pool goes on changing)
    return {name.lstrip("_"): copy(getattr(sampler, name)) for name in names} if names else None


def restore_sampler(sampler, state):
    """The inverse of sampler_state."""
    if hasattr(sampler, "samplers"):
        for i, s in enumerate(sampler.samplers):
            if str(i) in state:
                restore_sampler(s, state[str(i)])
        return
    for name in SAMPLER_STATE.get(type(sampler), ()):
        setattr(sampler, name, state[name.lstrip("_")])


def _nested(x, leaf):
    """leaf(v) for every v inside nested dicts / lists / tuples (a tuple becomes a list)."""
    if isinstance(x, dict):
        return {k: _nested(v, leaf) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_nested(v, leaf) for v in x]
    return leaf(x)


def _as_torch(x):   # numpy arrays -> tensors, numpy scalars -> Python numbers (torch's safe loader takes neither)
    return _nested(x, lambda v: torch.from_numpy(np.ascontiguousarray(v)) if isinstance(v, np.ndarray)
                   else v.item() if isinstance(v, np.generic) else v)


def _as_numpy(x):   # the inverse of _as_torch
    return _nested(x, lambda v: v.numpy() if torch.is_tensor(v) else v)
