"""The envs a run names (`--env`), made by name: the env factory the harness hands the loop (dagger's make_env).

    planar             Table I's planar reacher (envs.py)
    engine3d           Table II's UR5 reaching an engine lever (experiment/engine3d.py)
    engine3d_image     the UR5 policy on camera images (experiment/image_obs.py)
    engine3d_oriented  the UR5 whose success also needs the tool's orientation (experiment/oriented_goal.py)

The core makes only 'planar' (envs.make_env); a run of any other env hands this module's make_env to
dagger.policy_calibrated_dagger, which passes it to every step that makes an env. Each env class says which of the
paper's envs it is or derives from (paper_env), which is what its table, unit and sizes follow.
"""
from __future__ import annotations

import diffusion
import envs
from experiment.engine3d import EngineConfig, EngineReach3D
from experiment.image_obs import EngineImageConfig, EngineReach3DImage, ImageEncoder
from experiment.oriented_goal import EngineOrientedConfig, EngineReach3DOriented

ENVIRONMENTS = {"planar": (envs.PlanarReacher, envs.PlanarConfig),
                "engine3d": (EngineReach3D, EngineConfig),
                "engine3d_image": (EngineReach3DImage, EngineImageConfig),
                "engine3d_oriented": (EngineReach3DOriented, EngineOrientedConfig)}

# The observation encoders a policy's config may name (PolicyConfig.obs_encoder; 'flat' and 'image_cnn': the names
# files written before the env handed the class over recorded), for the checkpoint loader
OBS_ENCODERS = {"FlatObservation": diffusion.FlatObservation, "flat": diffusion.FlatObservation,
                "ImageEncoder": ImageEncoder, "image_cnn": ImageEncoder}


def make_env(name="planar", **config):
    """Environment by name, e.g. make_env('engine3d', max_steps=200) (keywords: config fields)."""
    if name not in ENVIRONMENTS:
        raise ValueError(f"unknown env {name!r}; valid: {', '.join(sorted(ENVIRONMENTS))}")
    env_class, config_class = ENVIRONMENTS[name]
    return env_class(config_class(**config))


def paper_env(name):
    """The paper's env ('planar' or 'engine3d') that the env named `name` is or derives from, or None."""
    return ENVIRONMENTS[name][0].paper_env if name in ENVIRONMENTS else None


def paper_median_step(name):
    """The paper's median step (rad) of the env named `name`, or None where the paper gives none."""
    return ENVIRONMENTS[name][0].paper_median_step if name in ENVIRONMENTS else None
