"""Helpers shared by the tests (and benchmarks/bench_relabel.py): what no run of the method executes."""
import numpy as np


def straight_line_episode(env, seed, peak=0.04, expert_from=5):
    """Stand-in expert data for tests and benchmarks (no oracle needed): in scenario `seed` a straight joint-space
    line from the start toward the nearest goal configuration, stopped at 90 % of the way to the first contact,
    timed with a smoothstep (peak speed `peak` rad/step); steps from `expert_from` on expert."""
    env.reset(seed=int(seed))
    q0 = env.q
    goals = env.goal_configurations()
    target = goals[np.argmin(np.abs(goals - q0).sum(1))]
    f = np.linspace(0, 1, 401)
    hit = env.in_collision(q0 + f[:, None] * (target - q0))
    d = (0.9 * f[np.argmax(hit)] if hit.any() else 1.0) * (target - q0)
    tau = np.linspace(0, 1, int(np.ceil(1.5 * np.abs(d).max() / peak)) + 1)
    q = q0 + (3 * tau ** 2 - 2 * tau ** 3)[:, None] * d  # (T, dof), smoothstep
    prev = np.concatenate([q[:1], q[:-1]])
    return {"obs": env.make_obs(q, prev), "q": q, "action": np.concatenate([q[1:], q[-1:]]),
            "expert": np.arange(len(q)) >= expert_from, "seed": int(seed)}
