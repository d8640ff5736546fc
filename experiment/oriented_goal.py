"""A research variant: the UR5's success also needs the tool's orientation, the authors' whole rule (the TCP
within 3 cm AND the flange within 10 deg of one fixed pose; benchmarks/HISTORY.md, "The 10° rule": with it BC at
the table2 recipe reaches 88 %, one end posture; without it 49 %, inside the paper's range). Run it with
`python dagger.py --env engine3d_oriented` (any profile).

The harness makes it by name (experiment/environments.py, 'engine3d_oriented'):
    EngineReach3DOriented: EngineReach3D whose goal_reached also asks
                                            tool_angle(q) <= goal_angle_tolerance (theirs: 10 deg), and whose
                                            goal set (goal_configurations, the oracle's goals, goal_is_pose) is
                                            the IK branches of the goal posture goal_q's own pose, tilted by up
                                            to half the tolerance: one goal posture, as the authors' demos have.
The scenes and starts are EngineReach3D's, seed for seed (its reset counts its own, position-only goal set).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from experiment import engine3d


@dataclass
class EngineOrientedConfig(engine3d.EngineConfig):
    # deg: success also needs the flange within this angle of goal_q's orientation (the authors' 10)
    goal_angle_tolerance: float = 10.0


def tool_angle(q, goal_q):
    """Degrees between the flange's orientation at q and at the posture goal_q. (B,) or float."""
    q = np.asarray(q, dtype=np.float64)
    R = engine3d.ur5_frames(q.reshape(-1, 6))[:, 6, :3, :3]
    R_goal = engine3d.ur5_frames(np.asarray(goal_q, dtype=np.float64)[None])[0, 6, :3, :3]
    cos = (np.einsum("bij,ij->b", R, R_goal) - 1) / 2  # (trace(R^T R_goal) - 1) / 2
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return angle.reshape(q.shape[:-1]) if q.ndim > 1 else float(angle[0])


def axis_rotation(axis, angle):
    """The 3 x 3 rotation by `angle` rad about the unit vector `axis` (Rodrigues' formula)."""
    x, y, z = axis
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


class EngineReach3DOriented(engine3d.EngineReach3D):
    """EngineReach3D with the authors' orientation rule (module docstring)."""

    goal_is_pose = True  # goal_configurations is the whole goal set: the oracle takes it (oracle.solve_ik)

    def __init__(self, config: EngineOrientedConfig | None = None):
        cfg = config or EngineOrientedConfig()
        if not 0.0 < cfg.goal_angle_tolerance <= 180.0:
            raise ValueError(f"EngineOrientedConfig.goal_angle_tolerance must be degrees in (0, 180] about the goal "
                             f"posture goal_q (the authors' 10), got {cfg.goal_angle_tolerance!r}")
        super().__init__(cfg)

    def tool_angle(self, q):
        """Degrees between the flange's orientation at q and at the goal posture cfg.goal_q. (B,) or float."""
        return tool_angle(q, self.cfg.goal_q)

    def goal_reached(self, q):
        """True where the TCP is within goal_tolerance of the goal and the flange within goal_angle_tolerance of
        the goal posture's orientation (the authors' 3 cm and 10 deg). (B,) bool."""
        return super().goal_reached(q) & (self.tool_angle(q) <= self.cfg.goal_angle_tolerance)

    def goal_configurations(self):
        """The closed-form IK branches of goal_q's flange pose and of 6 tilts of it by half the angle tolerance
        (about +-x, y, z of the flange), TCP on the goal; within the limits, collision-free and goal_reached.
        (M, 6)."""
        frame = engine3d.ur5_frames(np.asarray(self.cfg.goal_q, dtype=np.float64)[None])[0, 6]  # (4, 4) flange
        tilt = math.radians(self.cfg.goal_angle_tolerance) / 2
        turns = [np.eye(3)] + [axis_rotation(a, tilt) for a in np.vstack([np.eye(3), -np.eye(3)])]
        flange = np.tile(np.eye(4), (len(turns), 1, 1))
        flange[:, :3, :3] = frame[:3, :3] @ np.array(turns)
        flange[:, :3, 3] = self._goal - self.cfg.tool_length * flange[:, :3, 2]  # TCP on the goal
        q = engine3d.ur5_ik(flange).reshape(-1, self.dof)
        q = q[~np.isnan(q).any(axis=1)]
        lo, hi = self.joint_limits
        q = q[np.all((q >= lo) & (q <= hi), axis=1)]
        q = q[~self.in_collision(q)] if len(q) else q
        return q[self.goal_reached(q)] if len(q) else q

