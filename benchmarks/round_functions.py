"""How many of the project's functions one round of the smoke run calls, and in how many files (the guide set for
the modules' reorganization after 7e18ba9: one round <= ~150 functions). A reader following a round meets these.

The shared stages (D0, pi_0, the BC row) are made first and not counted; then lineage 0's round 1 -- collection,
HG-DAgger, calibration, every noised arm, their evaluations -- runs in this process (workers=1, so that the arms'
functions are seen) under a profiler that records each project function called (tests/ and benchmarks/ aside).

Usage:  python benchmarks/round_functions.py [--out /tmp/round_functions] [--list]
"""
import argparse
import collections
import os
import shutil
import sys
from dataclasses import replace

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import dagger  # noqa: E402
from experiment import profiles, report
from experiment.run_folder import Run  # noqa: E402


def round_functions(out):
    """{file (relative): sorted function names} called by lineage 0's round 1 of the smoke profile."""
    shutil.rmtree(out, ignore_errors=True)
    cfg = replace(profiles.PROFILES["smoke"], lineages=1)
    report.run_experiment(cfg, out, prepare=True)          # the shared stages, not counted
    run, seen = Run(out, cfg), set()
    skip = (os.path.join(ROOT, "tests"), os.path.join(ROOT, "benchmarks"))

    def profile(frame, event, arg):
        path = frame.f_code.co_filename
        name = frame.f_code.co_qualname
        if event == "call" and path.startswith(ROOT) and not path.startswith(skip) and "<" not in name.split(".")[-1]:
            seen.add((os.path.relpath(path, ROOT), name))  # comprehensions and lambdas aside

    sys.setprofile(profile)
    try:
        dagger.policy_calibrated_dagger(cfg, [0], memo=run.memo, log=run.log)
    finally:
        sys.setprofile(None)
    by_file = collections.defaultdict(list)
    for path, name in seen:
        by_file[path].append(name)
    return {path: sorted(names) for path, names in sorted(by_file.items())}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="/tmp/round_functions", help="a scratch run folder (deleted first)")
    parser.add_argument("--list", action="store_true", help="name every function")
    args = parser.parse_args()
    found = round_functions(args.out)
    for path, names in found.items():
        print(f"{path}: {len(names)}" + (": " + ", ".join(names) if args.list else ""))
    total = sum(map(len, found.values()))
    core = sum(len(names) for path, names in found.items() if os.sep not in path)  # top level: the seven modules
    print(f"one round of the smoke run: {total} project functions in {len(found)} files: "
          f"{core} in the seven modules (the method), {total - core} in experiment/ "
          f"(plumbing: run folder, checkpoints, workers, the CPU kernels where they pay on this kind of CPU)")
