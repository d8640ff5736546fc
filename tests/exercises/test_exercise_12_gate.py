"""Exercise 12: the HG-DAgger gate of the oracle expert: intervene when the policy's chunk would
collide or when the arm has stalled (oracle.rollout_chunk, oracle.stalled, Oracle.should_intervene;
paper Sec. IV-A "Method Design", Sec. V)."""
import numpy as np
import pytest

import envs
from oracle import Oracle, OracleConfig, rollout_chunk, stalled


@pytest.fixture(scope="module")
def env():
    env = envs.make_env("planar")
    env.reset(seed=int(env.eval_seeds()[0]))
    return env


def colliding_and_free_chunks(env, H=16):
    """Straight chunks at full speed from env.q: one whose states run into an obstacle, one that stays
    clear of every obstacle by a margin. Starts from the first evaluation scenario that has both."""
    rng = np.random.default_rng(0)
    steps = np.arange(1, H + 1)[:, None]
    for seed in env.eval_seeds()[:20]:
        env.reset(seed=int(seed))
        found = {}
        for _ in range(200):
            direction = rng.normal(size=env.dof)
            chunk = env.q + steps * env.max_step * direction / np.abs(direction).max()     # (H, dof)
            if np.any(chunk < env.joint_limits[0]) or np.any(chunk > env.joint_limits[1]):
                continue                                                                    # keep it simple
            dense = env.q + np.linspace(0, 1, 400)[:, None] * (chunk[-1] - env.q)
            if env.in_collision(dense).any():
                found.setdefault("hit", chunk)
            elif not env.in_collision(dense, margin=2 * env.link_radius).any():
                found.setdefault("free", chunk)
            if len(found) == 2:
                return found["hit"], found["free"]
    raise AssertionError("no scenario with both a colliding and a free straight chunk")


def test_rollout_chunk_applies_the_contract_step_rule(env):
    lo, hi = env.joint_limits
    chunk = env.q + np.array([[0.01, -0.3, 0.02], [10.0, 10.0, -10.0], [0.0, 0.0, 0.0]])
    states = rollout_chunk(env, chunk)
    assert states.shape == (4, env.dof) and np.array_equal(states[0], env.q)
    q = env.q.copy()
    for k, action in enumerate(chunk):
        q = np.clip(q + np.clip(action - q, -env.max_step, env.max_step), lo, hi)   # the env's motion rule
        assert np.allclose(states[k + 1], q, atol=1e-15)
    other = env.q + 0.1
    assert np.array_equal(rollout_chunk(env, chunk, q=other)[0], other)
    # at the joint limits: joint 0 just below its upper limit, joint 2 just above its lower one, both driven
    # at full speed into them; they stop at the limits (the contract's outer clip), joint 1 does not move
    edge = np.array([hi[0] - 0.02, 0.3, lo[2] + 0.07])
    states = rollout_chunk(env, edge + np.array([[1.0, 0.0, -1.0]] * 3), q=edge)
    assert np.all(states >= lo) and np.all(states <= hi)
    np.testing.assert_allclose(states[1], [hi[0], 0.3, lo[2] + 0.07 - env.max_step])   # 0.05 rad/step
    np.testing.assert_allclose(states[-1], [hi[0], 0.3, lo[2]])


def test_stalled_compares_the_last_window_with_the_best_before():
    assert not stalled([5.0, 4.0, 3.0], window=3, min_progress=0.1)                # history too short
    assert stalled([5.0, 4.0, 3.0, 2.95, 2.95, 2.95], window=3, min_progress=0.1)  # 0.05 < 0.1 progress
    assert not stalled([5.0, 4.0, 3.0, 2.85, 2.95, 2.95], window=3, min_progress=0.1)
    assert stalled([1.0, 2.0, 3.0, 4.0, 5.0, 6.0], window=3, min_progress=0.0)     # moving away
    assert not stalled([5.0, 4.0, 3.0, 2.0], window=3, min_progress=0.5)           # from 5.0 to 2.0


def test_gate_intervenes_on_a_colliding_chunk_then_on_a_stall(env):
    oracle = Oracle(OracleConfig(stall_window=5, stall_progress=0.01, gate_lookahead=None))  # whole chunk
    hit, free = colliding_and_free_chunks(env)
    progress = [1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4]
    flat = [1.0, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9]
    assert oracle.should_intervene(env, hit, progress) == "collision"
    assert oracle.should_intervene(env, hit, flat) == "collision"                   # collision comes first
    assert oracle.should_intervene(env, free, progress) is None
    assert oracle.should_intervene(env, free, flat) == "stall"
    gate = oracle.gate(env)                                                          # the per-episode wrapper
    assert gate.should_intervene(env, free) is None and gate.should_intervene(env, hit) == "collision"
