"""Tests of experiment/oriented_goal.py: the UR5 with the authors' orientation rule ('engine3d_oriented')."""
import math

import numpy as np
import pytest

import envs
from experiment import engine3d, environments
from experiment.oriented_goal import EngineReach3DOriented, axis_rotation, tool_angle


def test_tool_angle_is_the_flange_rotation_from_the_goal_posture():
    """Turning joint 1 (about the base's vertical axis) or joint 6 (about the tool axis) by delta rad
    turns the flange by exactly delta; batched and single inputs agree."""
    goal_q = np.array(engine3d.EngineConfig().goal_q)
    assert tool_angle(goal_q, goal_q) == pytest.approx(0.0, abs=1e-5)
    qs = []
    for joint, delta in ((0, 0.2), (5, 0.3), (5, -2.0)):
        q = goal_q.copy()
        q[joint] += delta
        qs.append(q)
        assert tool_angle(q, goal_q) == pytest.approx(math.degrees(abs(delta)), rel=1e-6)
    assert np.allclose(tool_angle(np.array(qs), goal_q), [tool_angle(q, goal_q) for q in qs])


def test_axis_rotation_is_rodrigues():
    R = axis_rotation(np.array([0.0, 0.0, 1.0]), math.pi / 2)  # a quarter turn about z: x -> y
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    axis = np.array([1.0, 2.0, 2.0]) / 3
    R = axis_rotation(axis, 0.7)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R @ axis, axis, atol=1e-12)
    assert math.degrees(math.acos((np.trace(R) - 1) / 2)) == pytest.approx(math.degrees(0.7))


def test_orientation_rule_keeps_the_scenes_and_asks_for_the_goal_posture():
    """The authors' 10 deg: the same scenarios as position-only success; every goal configuration puts the
    TCP on the goal within the angle; a TCP on the goal with the flange turned 0.5 rad about the tool axis is
    reached without the rule and not with it; the oracle's demo ends inside the rule."""
    import oracle
    plain, posed = environments.make_env("engine3d"), environments.make_env("engine3d_oriented")
    assert isinstance(posed, EngineReach3DOriented) and posed.cfg.goal_angle_tolerance == 10.0
    assert posed.goal_is_pose and not plain.goal_is_pose and posed.paper_env == "engine3d"
    for seed in envs.eval_seeds()[:3]:
        plain.reset(seed=seed)
        posed.reset(seed=seed)
        assert np.array_equal(plain.q, posed.q) and np.array_equal(plain.obstacles, posed.obstacles)
        goals = posed.goal_configurations()
        assert len(goals) >= 8
        assert np.all(posed.tool_angle(goals) <= 10.0 + 1e-9)
        assert np.allclose(posed.ee(goals), posed.goal, atol=1e-6) and not posed.in_collision(goals).any()
    turned = np.array(posed.cfg.goal_q)
    turned[5] += 0.5  # about the tool axis: the TCP stays on the goal
    assert plain.goal_reached(turned) and not posed.goal_reached(turned)
    seed = envs.eval_seeds()[0]
    episode = oracle.Oracle().demonstrate(posed, seed)
    posed.reset(seed=seed)
    end = posed.clip_action(episode["q"][-1], episode["action"][-1])
    assert episode["success"] and posed.tool_angle(end) <= 10.0
    plain.close()
    posed.close()
    for bad in (0.0, 200.0):
        with pytest.raises(ValueError, match="goal_angle_tolerance must be degrees"):
            environments.make_env("engine3d_oriented", goal_angle_tolerance=bad)
