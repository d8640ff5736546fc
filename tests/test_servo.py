"""experiment/servo.py: the authors' servo return label, its knobs converted from the authors' units (their median
step per 30 Hz frame, L2 over the joints, per source episode) to ours through radians. The conversion is tested
against the authors' numbers and on oracle demonstrations, where a knob converted with our per-joint median step
(the conversion up to 6192871) caps the label below the demonstrations' own speed."""
from dataclasses import replace

import numpy as np
import pytest

import envs
import relabel
from experiment import servo
from test_relabel import DOF, FakeEnv, intervention_episode, oracle_like_demo, smooth_trajectory

H = 16
FRAMES = 3.0  # 30 Hz frames per 10 Hz env step: envs.PlanarReacher's dt / envs.PAPER_FRAME_DT


@pytest.fixture
def stats():
    demos = [oracle_like_demo(s) for s in range(3)]
    steps = np.abs(np.diff(np.concatenate([d["q"] for d in demos]), axis=0))
    return relabel.demo_stats(demos, median_step=float(np.median(steps[steps > 0])), max_step=FakeEnv.max_step,
                              paper_median_step=0.0176, frames_per_step=FRAMES)


def test_the_knobs_are_the_authors_constants():
    """AUTHORS holds the constants of PCD pcdagger/dart/relabel.py's servo as that file has them (commit 0188fa3),
    each in its own unit: a changed number here is a changed label, not a conversion."""
    got = {name: (k.value, k.unit) for name, k in servo.AUTHORS.items()}
    assert got == {"speed_budget": (1.2, "med_step/frame"), "speed_cap": (1.4, "b/frame"), "speed_cap_v0": (1.05, ""),
                   "launch_cap": (2.5, "b/frame"), "a_clamp_scale": (0.9, ""), "accel_floor": (0.2, "med_step/frame²"),
                   "gain_floor": (4.0, "med_step"), "jerk_slew": (0.5, "a_clamp/frame"),
                   "cursor_advance": (3.0, "med_step/frame")}
    assert all("line" in k.source for k in servo.AUTHORS.values())


def test_servo_knobs_at_the_authors_rate_are_their_expressions():
    """At one frame per step our segment step is their m_f, and each knob is their expression: v_cap's
    1.4 b = 1.68 m_f, the launch cap 2.5 b = 3 m_f, the accel floor 0.2 m_f, the gain floor 4 m_f, the slew 0.5."""
    m_f = 0.0176
    k = servo.servo_knobs(m_f, 1.0)
    assert k.speed_cap == pytest.approx(1.68 * m_f) and k.launch_cap == pytest.approx(3.0 * m_f)
    assert k.accel_floor == pytest.approx(0.2 * m_f) and k.gain_floor == pytest.approx(4.0 * m_f)
    assert (k.jerk_slew, k.speed_cap_v0, k.a_clamp_scale, k.cursor_advance) == (0.5, 1.05, 0.9, 3)


def test_servo_knobs_are_the_same_in_si_units_at_any_rate():
    """One motion seen at their 30 Hz (segment step m_f per frame) and at our 10 Hz (3 m_f per step, three frames):
    every knob is the same physical quantity -- the speed cap in rad/s, the accel floor and the slew's acceleration
    change in rad/s² and rad/s³, the gain floor in rad. Fails on a knob converted with the wrong power of the frames
    per step (a speed scaled as a distance, an acceleration as a speed)."""
    m_f, dt30, dt10 = 0.0176, 1 / 30, 0.1
    at30, at10 = servo.servo_knobs(m_f, 1.0), servo.servo_knobs(FRAMES * m_f, FRAMES)
    assert at10.speed_cap / dt10 == pytest.approx(at30.speed_cap / dt30)  # rad/s
    assert at10.launch_cap / dt10 == pytest.approx(at30.launch_cap / dt30)
    assert at10.accel_floor / dt10 ** 2 == pytest.approx(at30.accel_floor / dt30 ** 2)  # rad/s²
    assert at10.gain_floor == pytest.approx(at30.gain_floor)  # rad
    a30 = 1.0 / dt30 ** 2  # any acceleration clamp, rad/s² -> per step² at each rate
    assert at10.jerk_slew * a30 * dt10 ** 2 / dt10 ** 3 == pytest.approx(at30.jerk_slew * a30 * dt30 ** 2 / dt30 ** 3)
    # the cursor: 3 m_f of arc a frame = 3 of our steps' arc a step: 3 indices at either rate
    assert at10.cursor_advance == at30.cursor_advance == 3
    with pytest.raises(ValueError, match="frames_per_step"):
        servo.servo_knobs(0.05, None)


def test_the_planar_numbers_of_the_authors_unit():
    """The relabel diagnostic's 20 oracle demonstrations have an L2 median step of 0.0565 rad a 10 Hz step (their
    per-joint median 0.0282): the authors' floors there are 0.0753 rad (gain) and 0.0339 rad/step² (accel), their
    speed cap 0.0949 rad/step -- where the per-joint conversion gave 0.0375, 0.0169 and 0.047."""
    k = servo.servo_knobs(0.0565, FRAMES)
    assert k.gain_floor == pytest.approx(0.0753, abs=1e-4) and k.accel_floor == pytest.approx(0.0339, abs=1e-4)
    assert k.speed_cap == pytest.approx(0.0949, abs=1e-4) and k.launch_cap == pytest.approx(0.1695, abs=1e-4)


def test_segment_geometry_is_the_l2_median_of_the_moving_steps():
    """segment_geometry: the median of the L2 norms over the joints of the non-zero steps (their lines 66-69), and
    the 95th percentile of the second differences' L2 norms. Steps (3, 4, 0) / 1000 and (0, 0, 2) / 1000 alternate
    with still ones: the L2 median is 3.5e-3 (zero steps dropped), where the per-joint median of |Δq| would be 0 or
    1e-3 and a max norm 3e-3."""
    steps = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 2.0]] * 4) / 1000
    q = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    median, acc95 = servo.segment_geometry(q)
    assert median == pytest.approx(3.5e-3)
    accel = np.linalg.norm(q[2:] - 2 * q[1:-1] + q[:-2], axis=1)
    assert acc95 == pytest.approx(np.percentile(accel, 95))


@pytest.fixture(scope="module")
def oracle_demos():
    """20 planar oracle demonstrations, every step an intervention (the relabel diagnostic's), and their stats."""
    import oracle
    env = envs.make_env("planar")
    demos, seed = [], 0
    while len(demos) < 20:
        try:
            demos.append(oracle.Oracle().demonstrate(env, env.train_seeds(1, start=seed)[0]))
        except oracle.PlanningFailed:
            pass
        seed += 1
    stats = relabel.demo_stats(demos, envs.median_step(demos), env.max_step, paper_median_step=env.paper_median_step,
                               frames_per_step=env.dt / envs.PAPER_FRAME_DT)
    return demos, stats


def servo_labels_at_sigma_0(demos, stats, seed=0):
    """The servo's label at every labelable step of `demos` at σ = 0 with the run's velocity noise, as the sampler
    makes it: (sampler, kept rows, chunks, mask, recorded chunks)."""
    import diffusion
    sampler = servo.ServoSampler(demos, lambda: envs.make_env("planar"), stats, "isotropic", 0.0, servo.ServoConfig(20))
    rng = np.random.default_rng(seed)
    v = sampler.velocity + relabel.velocity_noise_std(sampler.cfg, stats) * rng.standard_normal(sampler.center.shape)
    t_proj = relabel.monotone_projection(sampler.center, sampler.trajectory, sampler.t_glob, window=32,
                                         t_end=sampler.end_glob)
    rows = np.arange(len(t_proj))
    chunks, mask = sampler.return_chunks(rows, sampler.center, v, t_proj, envs.make_env("planar").joint_limits)
    kept = (t_proj < sampler.end_glob - sampler.cfg.near_end_steps) & mask.any(axis=1)
    _, recorded = diffusion.chunk_dataset(demos, 20)  # the same steps in the same order
    return sampler, kept, chunks, mask, recorded


def test_on_oracle_demonstrations_the_cap_is_the_demos_speed_and_the_label_the_recorded_chunk(oracle_demos):
    """At σ = 0 on oracle demonstrations the authors' cap sits above the speed the expert itself moves at: the
    recorded chunk outruns its row's cap on few of the steps in the loss (86 % with the cap converted with the
    per-joint median step), and the label stays within 0.5 median steps of the recorded chunk on average (1.27
    then). Fails if the knobs are converted with envs.median_step (per joint, over D0) instead of the segment's L2
    median step."""
    demos, stats = oracle_demos
    sampler, kept, chunks, mask, recorded = servo_labels_at_sigma_0(demos, stats)
    speeds = np.linalg.norm(np.diff(np.concatenate([sampler.center[:, None], recorded], axis=1), axis=1), axis=-1)
    over_cap = speeds > sampler.knobs.speed_cap[:, None] * (1 + 1e-9)  # (N, H)
    in_loss = mask & kept[:, None]
    assert over_cap[in_loss].mean() < 0.1
    assert np.median(sampler.knobs.speed_cap) >= np.median(np.linalg.norm(np.diff(np.concatenate(
        [d["q"] for d in demos]), axis=0), axis=1))  # the cap at or above the demonstrations' median L2 speed
    distance = np.linalg.norm(chunks - recorded, axis=-1) / stats.median_step  # (N, H) median steps
    assert kept.mean() > 0.9 and distance[in_loss].mean() < 0.5


# ---- the servo's clamps, gains and masks (FakeEnv's smooth paths, tests/test_relabel.py) -------------------------

def servo_setup(stats, offset, n=64, seed=0, t0=20, velocity=0.3):
    """n states `offset` median steps (per joint, std) off smooth_trajectory at step t0, moving at the path's
    velocity plus `velocity` median steps per step (per joint, std): (traj, q0, v0, their projections)."""
    traj = smooth_trajectory()
    rng = np.random.default_rng(seed)
    t = np.full(n, t0)
    q0 = traj[t] + rng.normal(size=(n, DOF)) * offset * stats.median_step
    v0 = traj[t] - traj[t - 1] + rng.normal(size=(n, DOF)) * velocity * stats.median_step
    return traj, q0, v0, relabel.monotone_projection(q0, traj, t, window=32)


def path_knobs(traj):
    """servo_knobs of the path's own L2 median step, and its acc_p95 (a segment of the whole path)."""
    step, acc = servo.segment_geometry(traj)
    return servo.servo_knobs(step, FRAMES), acc, step


def servo_motion(q0, v0, chunk, max_step):
    """Realized velocities and accelerations of a chunk from (q0, v0): (B, H, dof) each."""
    x = np.concatenate([q0[:, None], chunk], axis=1)
    vel = np.diff(x, axis=1)
    prev = np.concatenate([np.clip(v0, -max_step, max_step)[:, None], vel[:, :-1]], axis=1)
    return vel, vel - prev


def a_clamp_of(knobs, acc):
    return knobs.a_clamp_scale * max(2 * np.sqrt(DOF) * acc, knobs.accel_floor)


def test_servo_respects_every_clamp(stats):
    traj, q0, v0, proj = servo_setup(stats, offset=8.0)
    knobs, acc, _ = path_knobs(traj)
    knobs = replace(knobs, launch_cap=1.0, speed_cap=0.5 * knobs.speed_cap)  # launch speeds as drawn; a cap in reach
    a_clamp = a_clamp_of(knobs, acc)
    # a loose per-joint max_step, so that the norm speed cap is what binds
    chunk, _ = servo.servo_return_chunk(q0, v0, traj, traj, proj, acc, knobs, H, 1.0)
    vel, accel = servo_motion(q0, v0, chunk, 1.0)
    cap = np.maximum(knobs.speed_cap, 1.05 * np.linalg.norm(v0, axis=1))[:, None]
    assert np.all(np.linalg.norm(accel, axis=-1) <= a_clamp * (1 + 1e-9))
    assert np.all(np.linalg.norm(vel, axis=-1) <= cap * (1 + 1e-9))
    assert np.any(np.linalg.norm(vel, axis=-1) > 0.99 * cap)  # ... and the cap was reached
    # slew: with a tight jerk_slew the accelerations change by at most jerk_slew · a_clamp per step
    chunk, _ = servo.servo_return_chunk(q0, v0, traj, traj, proj, acc, replace(knobs, jerk_slew=0.2), H, 1.0)
    vel, accel = servo_motion(q0, v0, chunk, 1.0)
    free = np.linalg.norm(vel, axis=-1) < 0.999 * cap  # where the speed cap did not alter the command
    jerk = np.linalg.norm(np.diff(accel, axis=1), axis=-1)  # (B, H-1)
    ok = free[:, 1:] & free[:, :-1]
    assert ok.sum() > 100 and np.all(jerk[ok] <= 0.2 * a_clamp * (1 + 1e-9))
    assert np.all(np.linalg.norm(accel[:, 0], axis=-1) <= 0.2 * a_clamp * (1 + 1e-9))  # a_{-1} = 0
    # the env's per-joint speed limit, and joint limits
    chunk, _ = servo.servo_return_chunk(q0, v0, traj, traj, proj, acc, knobs, H, 0.01)
    vel, _ = servo_motion(q0, v0, chunk, 0.01)
    assert np.abs(vel).max() <= 0.01 + 1e-12
    lo, hi = q0.min(0) - 0.01, q0.max(0) + 0.01  # limits that the free servo would leave
    chunk, _ = servo.servo_return_chunk(q0, v0, traj, traj, proj, acc, knobs, H, 1.0, limits=(lo, hi))
    assert np.all((chunk >= lo) & (chunk <= hi))


def test_the_launch_speed_is_capped_first(stats):
    """‖v0‖ is scaled to launch_cap before anything else (their sanity cap, lines 226-228): the speed cap's
    1.05 ‖v0‖ then counts the capped speed. Fails if the launch cap is dropped (the label leaves at ~4 times it)."""
    traj, q0, v0, proj = servo_setup(stats, offset=0.0, velocity=20.0)  # launch speeds far above the cap
    knobs, acc, _ = path_knobs(traj)
    knobs = replace(knobs, speed_cap=0.0)  # the cap is 1.05 ‖v0 after the launch cap‖ alone
    chunk, _ = servo.servo_return_chunk(q0, v0, traj, traj, proj, acc, knobs, H, 10.0)
    vel, _ = servo_motion(q0, v0, chunk, 10.0)
    assert np.all(np.linalg.norm(vel, axis=-1) <= 1.05 * knobs.launch_cap * (1 + 1e-9))
    assert np.linalg.norm(vel, axis=-1).max() > 0.5 * knobs.launch_cap  # it launches near the cap


def test_servo_caps_bind_where_the_unclamped_servo_would_exceed_them(stats):
    """Fails if the acceleration cap (‖a‖ <= a_clamp) or the speed cap (‖v‖ <= max(speed_cap, 1.05 ‖v0‖)) is
    dropped or loosened: states 20 median steps off the path and 2 off its velocity, where the servo's PD commands
    well past both (checked with the speed cap out of reach)."""
    traj, q0, v0, proj = servo_setup(stats, offset=20.0, velocity=2.0)
    knobs, acc, _ = path_knobs(traj)
    knobs = replace(knobs, launch_cap=1.0)
    a_clamp = a_clamp_of(knobs, acc)
    v_cap = np.maximum(knobs.speed_cap, 1.05 * np.linalg.norm(v0, axis=1))[:, None]  # (B, 1)
    chunk, _ = servo.servo_return_chunk(q0, v0, traj, traj, proj, acc, knobs, H, 1.0)
    vel, accel = servo_motion(q0, v0, chunk, 1.0)
    accel, speed = np.linalg.norm(accel, axis=-1), np.linalg.norm(vel, axis=-1)  # (B, H) each
    assert np.all(accel <= a_clamp * (1 + 1e-9)) and accel.max() > 0.999 * a_clamp  # the acceleration cap acts
    assert np.all(speed <= v_cap * (1 + 1e-9)) and (speed / v_cap).max() > 0.999  # the speed cap acts
    loose = replace(knobs, speed_cap=1e3, speed_cap_v0=1e3)
    chunk, _ = servo.servo_return_chunk(q0, v0, traj, traj, proj, acc, loose, H, 1.0)
    vel, accel = servo_motion(q0, v0, chunk, 1.0)
    assert (np.linalg.norm(vel, axis=-1) / v_cap).max() > 1.15
    assert np.all(np.linalg.norm(accel, axis=-1) <= a_clamp * (1 + 1e-9))


def test_servo_returns_near_the_expert_path(stats):
    traj, q0, v0, proj = servo_setup(stats, offset=2.0, n=200)
    knobs, acc, _ = path_knobs(traj)
    chunk, mask = servo.servo_return_chunk(q0, v0, traj, traj, proj, acc, knobs, H, stats.max_step)
    start = np.min(np.linalg.norm(q0[:, None] - traj[None], axis=-1), axis=1)
    end = np.min(np.linalg.norm(chunk[:, -1, None] - traj[None], axis=-1), axis=1)  # distance to the path
    assert np.median(end) < 0.5 * stats.median_step and np.median(end) < 0.3 * np.median(start)
    assert mask.all()  # far from the segment's end nothing is held


@pytest.mark.parametrize("acc", [0.002, 0.02])  # a_clamp from the accel floor (0.018 rad/step²), from 2 √3 acc_p95
def test_servo_gains_are_the_discrete_critically_damped_pair(stats, acc):
    """The gains are the discrete critically damped pair of the servo's ω: Kp = (1 - p)², Kd = 1 - p², p = e^{-ω},
    ω² = a_clamp / max(d0, gain_floor), a_clamp = 0.9 max(2 √dof acc_p95, accel_floor). On a path that stands
    still the error from rest is
    e_k = (1 + k (1 - p)) p^k e0, the discrete (1 + ωt) e^{-ωt}: it never crosses the path. Fails on another
    damping (the authors' Kd = 2 √Kp by Euler at 10 Hz overshoots), or another Kp (the floor dropped)."""
    T, t0 = 40, 10
    point = np.array([0.3, -0.2, 0.1])
    traj = np.broadcast_to(point, (T, DOF)).copy()  # the reference and its velocity constant wherever the cursor is
    knobs = replace(servo.servo_knobs(0.03, FRAMES), jerk_slew=1e6, speed_cap=1e6, speed_cap_v0=1e6, launch_cap=1e6)
    a_clamp = 0.9 * max(2 * np.sqrt(3) * acc, 0.6 * 0.03)  # the authors' a_clamp, their 0.2 m_f floor at 10 Hz
    direction = np.array([2.0, -1.0, 2.0]) / 3.0  # unit vector: the error stays on this line
    d0 = np.array([0.3, 3.0, 9.0]) * knobs.gain_floor  # below the floor (ω from the floor), and above it
    q0 = point + d0[:, None] * direction  # (3, DOF) at rest
    chunk, _ = servo.servo_return_chunk(q0, np.zeros_like(q0), traj, traj, t0, acc, knobs, H, 1.0)
    err = (chunk - point) @ direction  # (3, H) signed error along the line
    np.testing.assert_allclose(chunk - point, err[..., None] * direction, atol=1e-12)  # straight back
    k = np.arange(1, H + 1)
    p = np.exp(-np.sqrt(a_clamp / np.maximum(d0, knobs.gain_floor)))[:, None]
    np.testing.assert_allclose(err, (1 + k * (1 - p)) * p ** k * d0[:, None], rtol=1e-9, atol=1e-15)
    assert np.all(err > 0) and np.all(np.diff(err, axis=1) < 0)  # no overshoot, always closing in


def test_the_reference_leads_the_state_by_one_frame():
    """action_reference: 1/frames_per_step of the way from each state to its action (the authors' action leads its
    state by one 30 Hz frame; ours by a whole step); the action itself at one frame a step. Fails if the recorded
    action is tracked as it is at 10 Hz (three times their lead) or the state (no lead)."""
    q = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, -0.6]])
    action = np.array([[0.3, 0.0, -0.6], [0.3, 0.0, -0.6]])
    np.testing.assert_allclose(servo.action_reference(q, action, 3.0), [[0.1, 0.0, -0.2], [0.3, 0.0, -0.6]])
    np.testing.assert_allclose(servo.action_reference(q, action, 1.0), action)


def test_servo_masks_the_held_tail_and_the_sampler_redraws_short_labels(stats):
    """Steps held at the segment's end (slower than hold_tol segment steps a step) are out of the loss, a tail to
    the chunk's end; the sampler never serves a label with fewer than min_moving_steps in the loss (the core's rule
    redraws a label with none, the servo empties a short one's mask), nor a state near its segment's end."""
    traj = smooth_trajectory()
    knobs, acc, step = path_knobs(traj)
    t_end = np.array([22, 25, 60])  # segments that end 2, 5, 40 steps after the state
    q0, v0 = traj[[20, 20, 20]], traj[[20, 20, 20]] - traj[[19, 19, 19]]
    chunk, mask = servo.servo_return_chunk(q0, v0, traj, traj, 20, acc, knobs, H, stats.max_step, t_end=t_end,
                                           hold_tol=0.02 * step)
    steps = np.abs(np.diff(np.concatenate([q0[:, None], chunk], axis=1), axis=1)).max(-1)  # (3, H)
    for i in range(2):  # the arm stops on the segment's last point; the rest is masked
        first = np.argmin(mask[i])
        assert not mask[i].all() and mask[i, 0] and not mask[i, first:].any()
        assert np.all(steps[i, first:] < 0.02 * step)
    assert mask[2].all() and mask[0].sum() < mask[1].sum()
    cfg = servo.ServoConfig(H, pool_size=256, refresh_size=64, reuse=2.0, episodes_per_refresh=4, min_moving_steps=8)
    sampler = servo.ServoSampler([intervention_episode()], FakeEnv, stats, "isotropic", 1.0, cfg)
    obs, chunks, mask = sampler(256, np.random.default_rng(0))
    assert np.all(mask.sum(1) >= 8) and (~mask).any()  # short labels redrawn, held tails still masked
    moves = np.abs(np.diff(np.concatenate([obs[:, None, :DOF], chunks], axis=1), axis=1)).max(-1)  # (n, H)
    hold = cfg.hold_tol * sampler.segment_step[0]  # one segment: the sampler's hold tolerance, rad a step
    assert np.all(moves[~mask] < hold * (1 + 1e-3)) and np.any(moves[mask] >= hold)  # held = slower than it
    assert sampler.cfg.label == "servo" and relabel.RelabelConfig(H).label == "pd"
    with pytest.raises(ValueError, match="ServoConfig"):
        servo.ServoSampler([intervention_episode()], FakeEnv, stats, "isotropic", 1.0, relabel.RelabelConfig(H))


def test_the_sampler_gives_each_row_its_own_segments_geometry(stats):
    """Two intervention segments moving at different speeds: each row's knobs come from its own segment's L2 median
    step (the authors' per source episode), not from one number for every row."""
    fast = intervention_episode()
    slow = intervention_episode(seed=1)
    slow["q"] = slow["q"] * 0.25
    slow["action"] = np.concatenate([slow["q"][1:], slow["q"][-1:]])
    sampler = servo.ServoSampler([fast, slow], FakeEnv, stats, "isotropic", 0.0,
                                 servo.ServoConfig(H, pool_size=64, refresh_size=64, episodes_per_refresh=2))
    for e, ep in enumerate((fast, slow)):
        rows = sampler.episode_of == e
        expected = servo.segment_geometry(ep["q"][10:60])[0]  # the intervention: steps 10 .. 59
        np.testing.assert_allclose(sampler.segment_step[rows], expected)
        np.testing.assert_allclose(sampler.knobs.speed_cap[rows], 1.68 * expected)
    assert sampler.segment_step[sampler.episode_of == 1][0] == pytest.approx(
        0.25 * sampler.segment_step[sampler.episode_of == 0][0])
