"""Every exercise is honest: its test FAILS on a student copy with that exercise blanked, and FAILS on a
copy holding a plausible wrong solution.

(That it passes on the reference code is checked by the normal run of tests/exercises/.)
For each exercise this makes copies of the project in a temporary folder (make_student_copy.py) and
runs only that exercise's test file there, in a subprocess, as a student would:
    python -m pytest -q -x tests/exercises/test_exercise_N_*.py        (cwd = the copy)
- the blanked copy: the failure must come from the hole, the output has to show the exercise's
  NotImplementedError, not an unrelated error;
- the wrong copy: one region of the exercise holds the wrong code of WRONG below, every other line is
  the reference's. The failure must be a test's assertion (AssertionError), with no import, syntax,
  name or NotImplementedError in the output: the test caught the wrong numbers, not a broken copy.
Two copies are tested at a time (most of a run is importing torch).
"""
import ast
import os
import re
import shutil
import subprocess
import sys
import textwrap
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from make_student_copy import ROOT, exercises, find_regions, hole, make_student_copy  # noqa: E402

HERE = Path(__file__).resolve().parent
IN_COPY = "PCD_EXERCISE_COPY"  # set in the subprocesses: a copy never runs the honesty check again
TABLE = exercises()
WORKERS = 2  # the machine has 2 cores

# One plausible wrong solution per exercise, the mistakes students make: exercise -> (what is wrong,
# the function whose exercise region it fills, the region's code). Only that region differs from the
# reference; the code is written at column 0 and indented to the region's markers in the copy.
WRONG = {
    1: ("q_sample scales a0 by alphabar_k instead of sqrt(alphabar_k)", "q_sample", """
        return (_per_row(schedule.alphas_cumprod, k, a0) * a0              # WRONG: alphabar, not its sqrt
                + _per_row(schedule.sqrt_one_minus_alphas_cumprod, k, a0) * eps)
        """),
    2: ("p_sample forgets to clip the predicted clean chunk to [-1, 1]", "p_sample", """
        a0_hat = (_per_row(schedule.sqrt_recip_alphas_cumprod, k, a_k) * a_k
                  - _per_row(schedule.sqrt_recipm1_alphas_cumprod, k, a_k) * eps_pred)
        # WRONG: no clip (the `clip` argument is ignored)
        mean = (_per_row(schedule.posterior_mean_coef1, k, a_k) * a0_hat
                + _per_row(schedule.posterior_mean_coef2, k, a_k) * a_k)
        if noise is None:
            noise = torch.randn(a_k.shape, generator=generator,
                                device=generator.device if generator is not None else a_k.device)
        return mean + _per_row(schedule.posterior_variance, k, a_k).sqrt() * noise.to(a_k.device)
        """),
    3: ("off by one: the paper's level k_sw used as the code index (one level too noisy, k_sw + 1 steps)",
        "partial_denoise", """
        k_start = torch.as_tensor(np.array(k_sw), device=dev)    # WRONG: paper step k_sw is code level k_sw - 1
        diffused = q_sample(policy.schedule, a_star, k_start.clamp(min=0), noise[:, 0])
        a_start = torch.where((k_start >= 0).view(B, 1, 1), diffused, a_star)
        a_hat = policy.reverse_process(a_start, k_start, obs_norm, noise[:, 1:], use_ema)
        """),
    4: ("the noise fraction taken as q_sample's noise coefficient sqrt(1 - alphabar), not 1 - alphabar",
        "noise_fraction", """
        return np.sqrt(1.0 - _alphabar_with_zero(schedule)[switch_step(beta, schedule.K)])   # WRONG: a std, not a variance
        """),
    5: ("Sigma_hat centered on the policy's own mean instead of the expert chunk", "open_loop_sigma", """
        obs = np.repeat(np.stack(obs_rows).astype(np.float32), n_samples, axis=0)
        samples = _sample_batched(policy, obs, generator, max_batch).astype(np.float64)
        M, dof = len(obs_rows), samples.shape[-1]
        samples = samples.reshape(M, n_samples, H, dof)
        d = (samples - samples.mean(axis=1, keepdims=True))[:, :, :n_act]     # WRONG: around the samples' mean
        sigma = np.einsum("mnhi,mnhj->mij", d, d) / (n_samples * n_act)
        return StepCovariances(sigma, np.asarray(ep_idx, dtype=np.int64), np.asarray(steps, dtype=np.int64))
        """),
    6: ("the gain ratio r = K*/K_theta on the policy's share: x = W s / (r s + 1 - s)", "equilibrium", """
        return np.asarray(W, dtype=np.float64) * s / (r * s + (1.0 - s))     # WRONG: r belongs to the expert's 1 - s
        """),
    7: ("the pooled Sigma_bar^alpha as the mean of the per-step Sigma^alpha_t (scale, then pool)",
        "pooled_sigma", """
        return calibrated_sigma(sigma_hats, W).mean(axis=0)                  # WRONG: Eq. (14) per step, then averaged
        """),
    8: ("off by one in the window: window + 1 candidates t_start .. t_start + window", "monotone_projection", """
        width = int((t_end - t_start).max(initial=1))
        if window is not None:
            width = min(width, int(window) + 1)                             # WRONG: one candidate too many
        idx = np.minimum(t_start[:, None] + np.arange(width)[None, :], t_end[:, None] - 1)
        diff = trajectory[idx] - q[:, None, :]
        best = t_start + np.argmin(np.einsum("bwd,bwd->bw", diff, diff), axis=1)
        return int(best[0]) if single else best
        """),
    9: ("the continuous-time gains Kp = w^2, Kd = 2 w used at dt = 1 step (overshoots)",
        "critically_damped_gains", """
        w = 5.83 / settle_steps                                              # WRONG: no discrete double pole
        return float(w * w), float(2.0 * w)
        """),
    10: ("the path assembled start tree first also when the trees have swapped roles (odd iterations)",
         "rrt_connect", """
        a, b = trees[it % 2], trees[1 - it % 2]
        q_rand = rng.uniform(lo, hi, size=(batch, len(lo)))
        near = a.nearest(q_rand)
        d = q_rand - a.nodes[near]
        dist = np.linalg.norm(d, axis=1)
        q_new = a.nodes[near] + d * np.minimum(1.0, step_size / np.maximum(dist, 1e-12))[:, None]
        free = edge_free_fraction(a.nodes[near], q_new, in_collision, resolution)
        useful = free * np.minimum(dist, step_size) >= 0.1 * step_size
        if not useful.any():
            continue
        new = _grow(a, near[useful], q_new[useful], free[useful], step_size)
        targets = a.nodes[new]
        near_b = b.nearest(targets)
        free_b = edge_free_fraction(b.nodes[near_b], targets, in_collision, resolution)
        last_b = _grow(b, near_b, targets, free_b, step_size)
        reached = np.flatnonzero(free_b == 1.0)
        if len(reached):
            e = reached[0]
            branch_a, branch_b = a.branch(new[e]), b.branch(last_b[e])
            return _drop_duplicates(np.concatenate([branch_a[::-1], branch_b]))   # WRONG: a is not always the start tree
        """),
    11: ("the moving averages' lengths truncated (int) instead of rounded up: ramps too short",
         "filter_kernel", """
        n_acc = int(np.max(v_max / (a_max * dt)))                           # WRONG: floor, not ceil
        n_jerk = int(np.max(a_max / (j_max * dt)))
        return np.convolve(np.ones(n_acc) / n_acc, np.ones(n_jerk) / n_jerk)
        """),
    12: ("the predicted rollout forgets to clip to the joint limits", "rollout_chunk", """
        q = env.q if q is None else np.asarray(q, dtype=np.float64)
        states = [q]
        for action in np.asarray(chunk, dtype=np.float64):
            q = q + np.clip(action - q, -env.max_step, env.max_step)           # WRONG: no clip to (lo, hi)
            states.append(q)
        return np.array(states)
        """),
    13: ("a one-sided p-value where Table I's paired t-test is two-sided", "paired_ttest", """
        mean, sd = d.mean(), d.std(ddof=1)
        if sd == 0:
            return (0.0 if mean == 0 else math.copysign(math.inf, mean)), n - 1, (1.0 if mean == 0 else 0.0)
        t = mean / (sd / math.sqrt(n))
        return t, n - 1, 1.0 - student_t_cdf(abs(t), n - 1)                 # WRONG: one tail only
        """),
}
UNRELATED = re.compile(r"\b(SyntaxError|IndentationError|ImportError|ModuleNotFoundError|NameError|"
                       r"NotImplementedError)\b")


def test_every_exercise_has_one_test_file_and_a_text():
    readme = (HERE / "README.md").read_text()
    assert len(TABLE) >= 10
    for n in TABLE:
        files = sorted(HERE.glob(f"test_exercise_{n}_*.py"))
        assert len(files) == 1, f"exercise {n}: expected one tests/exercises/test_exercise_{n}_*.py, got {files}"
        assert f"## Exercise {n}:" in readme, f"exercise {n} has no section in tests/exercises/README.md"
    stray = {int(p.name.split("_")[2]) for p in HERE.glob("test_exercise_*_*.py")} - set(TABLE)
    assert not stray, f"test files for exercises without a marked region: {sorted(stray)}"


def test_markers_parse_and_regions_are_disjoint():
    regions = find_regions()
    assert regions and all(r.end > r.start + 1 for r in regions)
    by_file = {}
    for r in regions:
        by_file.setdefault(r.path, []).append((r.start, r.end))
    for spans in by_file.values():
        spans.sort()
        assert all(a[1] < b[0] for a, b in zip(spans, spans[1:]))


def enclosing_function(region):
    """Name of the innermost function whose body holds `region`, or None."""
    tree = ast.parse((ROOT / region.path).read_text(), filename=region.path)
    inside = [node for node in ast.walk(tree) if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
              and node.lineno <= region.start + 1 <= node.end_lineno]
    return max(inside, key=lambda node: node.lineno).name if inside else None


def target_region(n):
    """The one region of exercise n inside WRONG[n]'s function (ValueError if not exactly one)."""
    function = WRONG[n][1]
    found = [r for r in TABLE[n] if enclosing_function(r) == function]
    if len(found) != 1:
        raise ValueError(f"exercise {n}: {len(found)} regions in function {function!r}, expected 1")
    return found[0]


def test_every_exercise_has_a_wrong_solution_for_one_of_its_regions():
    assert set(WRONG) == set(TABLE), "WRONG needs one entry per exercise (make_student_copy.py --list)"
    for n in TABLE:
        region = target_region(n)
        reference = (ROOT / region.path).read_text().splitlines()[region.start + 1:region.end]
        code = textwrap.dedent(WRONG[n][2]).strip("\n").splitlines()
        assert [line.strip() for line in code] != [line.strip() for line in reference if line.strip()], \
            f"exercise {n}: the wrong code is the reference"
        assert any("WRONG" in line for line in code), f"exercise {n}: mark the wrong line with '# WRONG: ...'"


def blank_copy(n, folder):
    """Blank exercise n into folder/; returns (the copy, whether every region became exactly one raise)."""
    copy = folder / f"exercise_{n}"
    make_student_copy(n, copy)
    wanted = Counter((r.path, hole(r)) for r in TABLE[n])
    found = Counter({(path, line): (copy / path).read_text().splitlines().count(line) for path, line in wanted})
    return copy, wanted == found


def wrong_copy(n, folder):
    """A copy of the project with exercise n's target region holding WRONG[n]'s code and every other line the
    reference's; returns (the copy, whether the module differs from the reference in that region only)."""
    copy = folder / f"wrong_{n}"
    make_student_copy(n, copy)                        # the project with exercise n blanked ...
    for path in {r.path for r in TABLE[n]}:
        shutil.copy2(ROOT / path, copy / path)        # ... its modules back to the reference ...
    region = target_region(n)                         # ... and the wrong code in one region
    lines = (ROOT / region.path).read_text().splitlines(keepends=True)
    body = textwrap.indent(textwrap.dedent(WRONG[n][2]).strip("\n") + "\n", region.indent)
    text = "".join(lines[:region.start + 1]) + body + "".join(lines[region.end:])
    ast.parse(text, filename=region.path)             # indented right: a complete run of statements
    (copy / region.path).write_text(text)
    new = text.splitlines(keepends=True)
    tail = len(lines) - region.end
    only_there = (new[:region.start + 1] == lines[:region.start + 1] and new[len(new) - tail:] == lines[region.end:]
                  and new[region.start + 1:len(new) - tail] != lines[region.start + 1:region.end])
    return copy, only_there


def run_test(n, copy):
    """Run exercise n's test file in a copy; returns (returncode, output)."""
    test_file = next(HERE.glob(f"test_exercise_{n}_*.py")).relative_to(ROOT)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}   # import the copy's modules, not ours
    env[IN_COPY] = "1"
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", str(test_file)],
                            cwd=copy, env=env, capture_output=True, text=True, timeout=600)
    return result.returncode, result.stdout + result.stderr


@pytest.fixture(scope="module")
def copy_runs(request, tmp_path_factory):
    """{(kind, n): (copy check, future of run_test)} for the copies selected in this session, kind 'blanked'
    or 'wrong', WORKERS runs at a time. The copies are made first, in this thread: make_student_copy
    checks each blanked file with ast.parse, and CPython 3.11 can fail ("AST constructor recursion depth
    mismatch") when two threads build ASTs at once -- pytest's assertion rewriting does, in the main
    thread, while other test modules are imported."""
    makers = {"test_blanked_exercise_fails_its_test": ("blanked", blank_copy),
              "test_wrong_solution_fails_its_test": ("wrong", wrong_copy)}
    wanted = sorted({(makers[item.originalname], item.callspec.params["n"]) for item in request.session.items
                     if getattr(item, "originalname", None) in makers}, key=lambda km: (km[1], km[0][0]))
    folder = tmp_path_factory.mktemp("student_copies")
    copies = {(kind, n): make(n, folder) for (kind, make), n in wanted}
    with ThreadPoolExecutor(WORKERS) as pool:
        yield {key: (check, pool.submit(run_test, key[1], copy)) for key, (copy, check) in copies.items()}


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get(IN_COPY) == "1", reason="inside a student copy: no recursion")
@pytest.mark.parametrize("n", sorted(TABLE))
def test_blanked_exercise_fails_its_test(n, copy_runs):
    holes, future = copy_runs["blanked", n]
    returncode, out = future.result()
    assert holes, f"exercise {n}: the copy does not hold one NotImplementedError per region"
    assert returncode == 1, f"exercise {n}: its test did not fail on the blanked copy:\n{out[-3000:]}"
    assert f"NotImplementedError: exercise {n}:" in out, \
        f"exercise {n}: the test failed, but not at the hole:\n{out[-3000:]}"


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get(IN_COPY) == "1", reason="inside a student copy: no recursion")
@pytest.mark.parametrize("n", sorted(WRONG))
def test_wrong_solution_fails_its_test(n, copy_runs):
    """WRONG[n] in exercise n's region: the exercise's test must fail at one of its assertions."""
    only_there, future = copy_runs["wrong", n]
    returncode, out = future.result()
    assert only_there, f"exercise {n}: the wrong copy differs from the reference outside the target region"
    assert returncode == 1, (f"exercise {n}: its test PASSED (or did not run) with a wrong solution "
                             f"({WRONG[n][0]}):\n{out[-3000:]}")
    assert not UNRELATED.search(out), \
        f"exercise {n}: the test failed on an error unrelated to the wrong numbers:\n{out[-3000:]}"
    assert "AssertionError" in out, f"exercise {n}: the test failed, but not at an assertion:\n{out[-3000:]}"
