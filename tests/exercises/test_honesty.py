"""Every exercise is honest: its test FAILS on a student copy with that exercise blanked.

(That it passes on the reference code is checked by the normal run of tests/exercises/.)
For each exercise this makes a blanked copy in a temporary folder (make_student_copy.py) and runs
only that exercise's test file there, in a subprocess, as a student would:
    python -m pytest -q -x tests/exercises/test_exercise_N_*.py        (cwd = the copy)
The failure must come from the hole: the output has to show the exercise's NotImplementedError,
not an unrelated error. Two copies are tested at a time (most of a run is importing torch).
"""
import os
import subprocess
import sys
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


def blank_copy(n, folder):
    """Blank exercise n into folder/; returns (the copy, whether every region became exactly one raise)."""
    copy = folder / f"exercise_{n}"
    make_student_copy(n, copy)
    wanted = Counter((r.path, hole(r)) for r in TABLE[n])
    found = Counter({(path, line): (copy / path).read_text().splitlines().count(line) for path, line in wanted})
    return copy, wanted == found


def run_test(n, copy, holes):
    """Run exercise n's test in its blanked copy; returns (holes all there, returncode, output)."""
    test_file = next(HERE.glob(f"test_exercise_{n}_*.py")).relative_to(ROOT)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}   # import the copy's modules, not ours
    env[IN_COPY] = "1"
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", str(test_file)],
                            cwd=copy, env=env, capture_output=True, text=True, timeout=600)
    return holes, result.returncode, result.stdout + result.stderr


@pytest.fixture(scope="module")
def blanked_runs(request, tmp_path_factory):
    """Futures of run_test for the exercises selected in this session, WORKERS at a time. The copies are
    made first, in this thread: make_student_copy checks each blanked file with ast.parse, and CPython 3.11
    can fail ("AST constructor recursion depth mismatch") when two threads build ASTs at once -- pytest's
    assertion rewriting does, in the main thread, while other test modules are imported."""
    wanted = sorted({item.callspec.params["n"] for item in request.session.items
                     if getattr(item, "originalname", None) == "test_blanked_exercise_fails_its_test"})
    folder = tmp_path_factory.mktemp("student_copies")
    copies = {n: blank_copy(n, folder) for n in wanted}
    with ThreadPoolExecutor(WORKERS) as pool:
        yield {n: pool.submit(run_test, n, *copies[n]) for n in wanted}


@pytest.mark.skipif(os.environ.get(IN_COPY) == "1", reason="inside a student copy: no recursion")
@pytest.mark.parametrize("n", sorted(TABLE))
def test_blanked_exercise_fails_its_test(n, blanked_runs):
    holes, returncode, out = blanked_runs[n].result()
    assert holes, f"exercise {n}: the copy does not hold one NotImplementedError per region"
    assert returncode == 1, f"exercise {n}: its test did not fail on the blanked copy:\n{out[-3000:]}"
    assert f"NotImplementedError: exercise {n}:" in out, \
        f"exercise {n}: the test failed, but not at the hole:\n{out[-3000:]}"
