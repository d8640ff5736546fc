"""A research control, not the paper: Sigma_bar measured from unguided closed-loop rollouts (dagger's
'unguided_pooled' method).

The paper's "closed-loop pooled" row is a chain of rounds collected by the calibrated policy
(dagger.closed_loop_chain). This control is an earlier reading of it: from the first state of each
intervention segment the *unguided* policy (beta = 1, plain policy.sample) runs in closed loop for the
segment's length, every executed step contributes d_t d_t^T with d_t = q_t - q*_t (the time-matched expert
state), and the pooled Sigma_bar, their mean (Eq. 15), is scaled to the calibration's W by Eq. (16). A
rollout is cut at its first diverged step (nearest-state distance at the calibration's radius, that step
excluded): a policy that takes another route contributes only while it still follows the expert's.

It uses calibrate's batched simulator (`calibrate.closed_loop_rollouts`) and never dagger.py.
"""
from __future__ import annotations

import numpy as np
import torch

import calibrate
import envs


def unguided_pooled(env, policy, episodes: list[dict], cal: calibrate.Calibration, n_act: int,
                    generator: torch.Generator | None, median_step: float, n_segments: int = 8,
                    log=print) -> np.ndarray | None:
    """Sigma_bar from unguided closed-loop rollouts of the n_segments longest intervention segments, scaled
    by Eq. (16) to the calibration's W -> (dof, dof) rad^2; None (and a logged reason) if every rollout
    diverged on its first step: the open-loop pooled Sigma_bar^alpha (cal.pooled) stands in."""
    threshold = calibrate.diverge_radius(calibrate.CalibrationConfig.diverge_threshold, median_step,
                                         envs.paper_median_step(env))       # radians, as calibrate's
    log("unguided closed-loop rollouts for the unguided_pooled control")
    sigma_bar = unguided_sigma(env, policy, episodes, n_act, generator, threshold, n_segments)
    if sigma_bar is None:
        log("unguided_pooled: every closed-loop rollout diverged at once; the open-loop pooled Sigma_bar^alpha "
            "stands in")
        return None
    pooled = calibrate.calibrated_sigma(sigma_bar, cal.W)                    # Eq. (16)
    per_joint = calibrate.sigma_in_median_steps(pooled, median_step)
    log("unguided closed-loop pooled per-joint sigma [median steps]: "
        + ", ".join(f"{v:.2f}" for v in per_joint)
        + f" = {calibrate.other_units(np.sqrt(np.diag(pooled)), envs.paper_median_step(env))}")
    return pooled


def unguided_sigma(env, policy, episodes: list[dict], n_act: int, generator: torch.Generator | None = None,
                   diverge_rad: float = 0.4, max_segments: int | None = None) -> np.ndarray | None:
    """Sigma_bar (unscaled, Eq. 15) of the unguided policy in closed loop from the first state of each expert
    segment (longest first, at most max_segments), cut at the first step whose nearest-state distance reaches
    diverge_rad (radians). All rollouts batched (one policy.sample call per decision). None if no rollout
    executed a usable step."""
    H = calibrate.policy_horizon(policy)
    segs = calibrate.segments_longest_first(episodes, H)[:max_segments or None]
    if not segs:
        raise ValueError(f"no expert segment of >= {H} steps in {len(episodes)} episodes")

    def chunk_fn(obs, expert, rows):                 # unguided: the expert chunk is ignored
        return policy.sample(obs, generator=generator)

    roll = calibrate.closed_loop_rollouts(env, [(episodes[e], seg) for e, seg in segs], chunk_fn, H, n_act,
                                          diverge_rad, stop_on_divergence=True)
    # executed steps 1..n of each rollout, without the step that diverged
    last = roll.n_recorded - roll.diverged.astype(np.int64)
    steps = np.arange(roll.trajectory.shape[1])[None]
    used = (steps >= 1) & (steps <= last[:, None])                           # (B, L + 1)
    d = (roll.trajectory - roll.reference)[used]                             # (n, dof): q_t - q*_t
    if len(d) == 0:
        return None                              # every rollout diverged on its first step
    return np.einsum("ti,tj->ij", d, d) / len(d)                              # Eq. (15), pooled
