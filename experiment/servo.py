"""The authors' return label, a variant: their clamped servo, its knobs converted from the authors' units to ours.

The paper (Sec. IV-E) labels a noised state with a critically damped PD back to the expert trajectory, its
accelerations clamped to the demonstrations' (relabel.pd_return_chunk, every profile's label). The authors' code
labels it with a clamped servo instead (PCD `pcdagger/dart/relabel.py`, `chunk_labels`, its servo branch; commit
0188fa3; benchmarks/SETUP.md §6): a critically damped servo that tracks the recorded *actions* at its own monotone
cursor, with an acceleration clamp, a jerk slew and a speed cap set from each source episode's own median step.

The authors' unit is not ours. Their med_step m_f (lines 66-69: `seg_len = norm(diff(P), axis=1)`, the median of
the non-zero ones) is, per source episode (one intervention), the median over its 30 Hz frames of the L2 norm over
the joints of a frame's step. Our envs.median_step is the median per-joint |Δq| of D0's 10 Hz steps: on 3 joints
about half the L2 norm of the same steps. So every knob goes through radians, once, in `servo_knobs`: m_f of an
intervention is our expert segment's median L2 step per env step (`segment_geometry`) over the frames a step spans
(`frames_per_step`, env.dt / envs.PAPER_FRAME_DT), and a knob of k m_f per frame^n is k m_f frames_per_step^n rad
per env step^n. AUTHORS lists each knob with its value, unit and source line; tests/test_servo.py holds the
conversion to those numbers.

Rows that use it (experiment/controls.py): zero_noise_servo, fixed_8_servo, pooled_servo, each its default row
(the PD) with the servo's label instead. The sampler is relabel.AugmentationSampler with its return chunks
replaced (`ServoSampler.return_chunks`); everything else (the noised states, their velocity, the redraws) is the
core's. Where the authors' label differs from this one in more than units, and why: benchmarks/SETUP.md §6.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Sequence

import numpy as np

import relabel


@dataclass(frozen=True)
class Knob:
    """One constant of the authors' servo as their code has it: value, unit, and where it is read."""
    value: float
    unit: str  # theirs: 'med_step' a distance in their median steps, '/frame' per 30 Hz frame, '' unit-free
    source: str  # PCD pcdagger/dart/relabel.py at 0188fa3: the line and the expression (m_f: lines 66-69;
    # acc_p95: lines 70-71; the reference, the recorded action at the cursor: lines 268-275)


# The authors' servo, in their units (their med_step m_f: rad per 30 Hz frame, L2 over the joints, per episode)
AUTHORS = {
    "speed_budget": Knob(1.2, "med_step/frame", "line 139, chunk_labels(speed_budget=1.2); line 225, b = 1.2 m_f"),
    "speed_cap": Knob(1.4, "b/frame", "line 241, v_cap = max(1.4 * b, 1.05 * sp0); applied at lines 286-288"),
    "speed_cap_v0": Knob(1.05, "", "line 241, the 1.05 * sp0 of v_cap (sp0 the launch speed)"),
    "launch_cap": Knob(2.5, "b/frame", "lines 226-228, if sp0 > 2.5 * b: v0 scaled to 2.5 * b"),
    "a_clamp_scale": Knob(0.9, "", "line 230, a_clamp = 0.9 * max(2 sqrt(n_arm) acc_p95, 0.2 m_f)"),
    "accel_floor": Knob(0.2, "med_step/frame²", "line 230, the 0.2 m_f of a_clamp (m_f taken as an acceleration)"),
    "gain_floor": Knob(4.0, "med_step", "line 238, kp = a_clamp / max(d0, 4.0 m_f); line 239, kd = 2 sqrt(kp)"),
    "jerk_slew": Knob(0.5, "a_clamp/frame", "line 240, a_slew = 0.5 a_clamp; lines 280-283, |a_k - a_(k-1)| <= a_slew"),
    "cursor_advance": Knob(3.0, "med_step/frame", "line 263, s = min(best_s, s + 3.0 m_f): the cursor's arc a frame"),
}


@dataclass(frozen=True)
class ServoKnobs:
    """The servo's knobs for one expert segment, in rad per env step (`servo_knobs`); arrays broadcast per row."""
    speed_cap: np.ndarray  # rad/step, L2: ‖v‖ <= max(speed_cap, speed_cap_v0 ‖v0‖)
    speed_cap_v0: float  # unit-free
    launch_cap: np.ndarray  # rad/step, L2: ‖v0‖ is scaled down to it first
    accel_floor: np.ndarray  # rad/step²: a_clamp = a_clamp_scale · max(2 √dof acc_p95, accel_floor)
    a_clamp_scale: float
    gain_floor: np.ndarray  # rad: Kp = a_clamp / max(d0, gain_floor)
    jerk_slew: float  # a_clamp per step: |a_k - a_{k-1}| <= jerk_slew · a_clamp
    cursor_advance: int  # trajectory indices per step the cursor may advance


def servo_knobs(segment_step, frames_per_step: float) -> ServoKnobs:
    """AUTHORS in rad per env step, for expert segments whose median L2 step per env step is `segment_step` (rad,
    scalar or (B,)). Their m_f (rad per frame) is segment_step / frames_per_step; a knob of k · m_f per frame^n is
    k · m_f · frames_per_step^n per step^n (a distance: n = 0; a speed: 1; an acceleration: 2)."""
    if frames_per_step is None or not frames_per_step > 0:
        raise ValueError(f"frames_per_step: the authors' 30 Hz frames per env step, a number > 0, not "
                         f"{frames_per_step!r} (relabel.demo_stats(frames_per_step=env.dt / envs.PAPER_FRAME_DT))")
    m_f = np.asarray(segment_step, dtype=np.float64) / frames_per_step  # rad per frame: their med_step
    f = frames_per_step
    b = AUTHORS["speed_budget"].value * m_f  # rad per frame: their speed budget
    return ServoKnobs(
        speed_cap=AUTHORS["speed_cap"].value * b * f,  # 1.68 m_f per frame = 1.68 segment_step per step
        speed_cap_v0=AUTHORS["speed_cap_v0"].value,
        launch_cap=AUTHORS["launch_cap"].value * b * f,  # 3 segment_step per step
        accel_floor=AUTHORS["accel_floor"].value * m_f * f ** 2,  # 0.6 segment_step per step²
        a_clamp_scale=AUTHORS["a_clamp_scale"].value,
        gain_floor=AUTHORS["gain_floor"].value * m_f,  # a distance: 4/3 segment_step
        jerk_slew=AUTHORS["jerk_slew"].value * f,  # a change per frame, over a step's frames: 1.5
        # 3 m_f of arc per frame = 3 segment steps per step: 3 trajectory indices at the segment's median speed
        cursor_advance=int(AUTHORS["cursor_advance"].value),
    )


def segment_geometry(q: np.ndarray) -> tuple[float, float]:
    """(median step, acc_p95) of one expert segment's joints q (T, dof), as the authors' demo_geometry does for a
    source episode (lines 66-71), at the env's step: the median L2 norm over the joints of the non-zero steps
    (rad/step) and the 95th percentile of the L2 norm of the second differences (rad/step²)."""
    q = np.asarray(q, dtype=np.float64)
    step = np.linalg.norm(np.diff(q, axis=0), axis=1)
    live = step[step > 1e-9]
    accel = np.linalg.norm(q[2:] - 2 * q[1:-1] + q[:-2], axis=1) if len(q) > 2 else np.zeros(1)
    return (float(np.median(live)) if live.size else 1e-3), float(np.percentile(accel, 95))


def action_reference(states: np.ndarray, actions: np.ndarray, frames_per_step: float) -> np.ndarray:
    """What the servo tracks (T, dof): the recorded action at each step, in the authors' time. Their action leads
    its state by one 30 Hz frame (lines 268-275 track A at the cursor; A[i] governs P[i] -> P[i+1]); ours leads it by
    a whole env step (frames_per_step of their frames), so the action taken literally would lead three times as far
    ahead (a label ~1 median step ahead of the recorded chunk at σ = 0, measured: benchmarks/README.md). The reference
    is the point one frame along, 1/frames_per_step of the way from each state to its action (the action itself at
    frames_per_step = 1)."""
    states, actions = np.asarray(states, dtype=np.float64), np.asarray(actions, dtype=np.float64)
    return states + (actions - states) / frames_per_step


def servo_return_chunk(q0: np.ndarray, v0: np.ndarray, states: np.ndarray, reference: np.ndarray, t_proj,
                       acc_p95, knobs: ServoKnobs, H: int, max_step, t_end=None, limits=None,
                       hold_tol=None) -> tuple[np.ndarray, np.ndarray]:
    """The authors' servo from (q0, v0) (B, dof): a critically damped servo tracking `reference` (`action_reference`:
    the recorded action, as the authors track it) at its own cursor c_k, the monotone projection of x_k onto `states`
    at most `cursor_advance` past c_{k-1} (from t_proj):
        a_k = Kp (A_c - x_k) + Kd (A_{c+1} - A_c - v_k),  Kp = a_clamp / max(d0, gain_floor),  d0 = ‖q0 - S_{t_proj}‖,
    A the reference, S the states; at the segment's end A_{end-1} with zero velocity; ‖a‖ <= a_clamp,
    ‖a_k - a_{k-1}‖ <= jerk_slew · a_clamp, ‖v‖ <= max(speed_cap, speed_cap_v0 ‖v0‖) after ‖v0‖ <= launch_cap.
    Ours beside theirs (benchmarks/SETUP.md §6):
    Kd from the discrete double pole at the env step, |v| <= max_step per joint, x within `limits`, and the held
    tail (cursor at the end, every joint slower than hold_tol per step to the chunk's end) out of the loss.
    states, reference (T, dof): the episodes laid end to end; t_proj, t_end (exclusive): int or (B,); acc_p95 and the
    knobs' arrays: scalar or (B,). Returns (chunk (B, H, dof) joint targets x_1 .. x_H, mask (B, H), True = in the
    loss)."""
    states, reference = np.asarray(states, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    x = np.atleast_2d(np.asarray(q0, dtype=np.float64)).copy()
    B, dof = x.shape
    col = lambda a: np.broadcast_to(np.asarray(a, dtype=np.float64).reshape(-1, 1), (B, 1))  # (B, 1) per row
    v = np.broadcast_to(np.asarray(v0, dtype=np.float64), (B, dof)).copy()
    max_step = np.broadcast_to(np.asarray(max_step, dtype=np.float64), (dof,))
    t_end = np.broadcast_to(np.asarray(len(states) if t_end is None else t_end, dtype=np.int64), (B,))
    cursor = np.broadcast_to(np.asarray(t_proj, dtype=np.int64), (B,)).copy()
    norm = lambda a: np.linalg.norm(a, axis=-1, keepdims=True)  # (B, 1)
    cap = lambda a, limit: a * np.minimum(1.0, limit / np.maximum(norm(a), 1e-300))  # ‖a‖ <= limit
    v = cap(v, col(knobs.launch_cap))  # the authors' sanity cap on the launch speed
    a_clamp = knobs.a_clamp_scale * np.maximum(2 * np.sqrt(dof) * col(acc_p95), col(knobs.accel_floor))  # rad/step²
    d0 = norm(x - states[cursor])  # (B, 1) distance to the projection
    omega = np.sqrt(a_clamp / np.maximum(d0, col(knobs.gain_floor)))  # (B, 1): √Kp per step
    # their Kd = 2 √Kp is the continuous-time double pole -ω; stepped by Euler at our 10 Hz (3 of their frames)
    # it overshoots, so the double pole is placed at e^{-ω} (relabel.critically_damped_gains)
    p = np.exp(-omega)
    kp, kd = (1 - p) ** 2, 1 - p ** 2  # (B, 1) per step², per step
    v_cap = np.maximum(col(knobs.speed_cap), knobs.speed_cap_v0 * norm(v))  # (B, 1) rad/step
    v = np.minimum(np.maximum(v, -max_step), max_step)
    hold = col(0.0 if hold_tol is None else hold_tol)
    a_prev = np.zeros((B, dof))
    chunk = np.empty((B, H, dof))
    held = np.zeros((B, H), dtype=bool)
    for k in range(H):
        # the servo's own monotone cursor: project x_k, never back, at most cursor_advance ahead
        cursor = relabel.monotone_projection(x, states, cursor, window=knobs.cursor_advance + 1, t_end=t_end)
        at_end = cursor >= t_end - 1
        ref = reference[cursor]  # (B, dof) the recorded action at the cursor (the authors' p_ref)
        ref_vel = reference[np.minimum(cursor + 1, t_end - 1)] - ref  # (B, dof), 0 at the end
        a = kp * (ref - x) + kd * (ref_vel - v)  # PD on position and velocity error
        a = cap(a, a_clamp)  # accelerations of the demo envelope
        a = a_prev + cap(a - a_prev, knobs.jerk_slew * a_clamp)  # bounded jerk (slew)
        a_prev = a
        v = cap(v + a, v_cap)  # speed cap
        v = np.minimum(np.maximum(v, -max_step), max_step)  # the env's per-joint speed limit
        x_next = x + v
        if limits is not None:
            x_next = np.minimum(np.maximum(x_next, limits[0]), limits[1])
            v = x_next - x  # a joint stopped by its limit has stopped moving
        held[:, k] = at_end & (np.abs(x_next - x).max(axis=1) < hold[:, 0])
        x = x_next
        chunk[:, k] = x
    # the held tail: steps from which on every step is held; (B, H), True = in the loss
    tail = np.flip(np.logical_and.accumulate(np.flip(held, axis=1), axis=1), axis=1)
    return chunk, ~tail


@dataclass
class ServoConfig(relabel.RelabelConfig):
    """relabel.RelabelConfig with the authors' servo as the return label, and the servo's two knobs of ours."""
    label: ClassVar[str] = "servo"
    hold_tol: float = 0.02  # segment median steps a step: slower steps at the segment's end are held (out of the loss)
    min_moving_steps: int = 3  # steps: a label with fewer in the loss is redrawn (the authors' 8 frames)


class ServoSampler(relabel.AugmentationSampler):
    """relabel.AugmentationSampler whose return chunks are the authors' servo (`servo_return_chunk`), each row
    with the median step and acc_p95 of its own expert segment (the authors': of its source episode)."""

    def __init__(self, episodes: Sequence[dict], make_env, stats: relabel.DemoStats, noise: str, sigma,
                 cfg: ServoConfig, label_steps=None):
        if not isinstance(cfg, ServoConfig):
            raise ValueError(f"ServoSampler: cfg must be a ServoConfig (the servo's knobs), not {type(cfg).__name__}")
        super().__init__(episodes, make_env, stats, noise, sigma, cfg, label_steps)
        first = np.cumsum([0] + [len(ep["q"]) for ep in episodes])
        step, acc = np.empty(len(self.t_glob)), np.empty(len(self.t_glob))
        for e, end in {(int(e), int(end)) for e, end in zip(self.episode_of, self.end_glob)}:
            rows = (self.episode_of == e) & (self.end_glob == end)
            expert = np.asarray(episodes[e]["expert"], dtype=bool)
            t_end = end - first[e]
            start = t_end - int(np.argmin(expert[:t_end][::-1])) if not expert[:t_end].all() else 0  # its run's start
            step[rows], acc[rows] = segment_geometry(self.trajectory[first[e] + start:end])
        self.segment_step, self.segment_acc_p95 = step, acc  # (N,) rad/step, rad/step²
        self.knobs = servo_knobs(step, stats.frames_per_step)
        actions = np.concatenate([np.asarray(ep["action"], dtype=np.float64) for ep in episodes])  # (sum T, dof)
        self.reference = action_reference(self.trajectory, actions, stats.frames_per_step)

    def return_chunks(self, rows, q_tilde, v, t_proj, limits):
        """The servo's labels for table rows `rows`; a label with fewer than min_moving_steps in the loss has none."""
        k = self.knobs
        per_row = ServoKnobs(k.speed_cap[rows], k.speed_cap_v0, k.launch_cap[rows], k.accel_floor[rows],
                             k.a_clamp_scale, k.gain_floor[rows], k.jerk_slew, k.cursor_advance)
        chunks, mask = servo_return_chunk(q_tilde, v, self.trajectory, self.reference, t_proj,
                                          self.segment_acc_p95[rows], per_row, self.cfg.horizon, self.stats.max_step,
                                          t_end=self.end_glob[rows], limits=limits,
                                          hold_tol=self.cfg.hold_tol * self.segment_step[rows])
        mask[mask.sum(axis=1) < self.cfg.min_moving_steps] = False
        return chunks, mask
