"""W by the run's plain fit (n_iter=1, as calibrate.calibrate fits Eq. (12)) against the robust Huber fit that
exercise 6 grades (fit_equilibrium's default), refitted from the blend points of committed calibrations (no rollout):

    python benchmarks/w_fit_choice.py benchmarks/results/table1

Prints whether every stored W is the plain fit, and the robust - plain difference in the paper's median steps.
"""
from __future__ import annotations

import glob
import gzip
import json
import os
import re
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import calibrate  # noqa: E402


def refits(folder):
    """[(lineage/round, stored W, plain W, robust W)] in the paper's median steps (W at its bounds refitted as is)."""
    cfg, out = calibrate.CalibrationConfig(n_act=10), []  # n_act does not enter the fit
    for path in sorted(glob.glob(os.path.join(folder, "lineage_*.json.gz"))):
        with gzip.open(path, "rt") as fh:
            files = json.load(fh)["files"]
        for name, c in sorted(files.items()):
            if not re.search(r"round_\d+/calibration\.json$", name) or c.get("r") is None:
                continue  # a fallback W was not fitted
            b, s, x, kept = (np.asarray(c[k]) for k in ("blend_beta", "blend_s", "blend_x", "blend_kept"))
            cells = calibrate.ratio_cells(b, s, x, kept.astype(bool), cfg.min_survivors)
            fit = lambda **kw: calibrate.fit_equilibrium(cells.s[cells.fitted], cells.x[cells.fitted],  # noqa: E731
                                                         r_bounds=cfg.r_bounds, **kw).W
            unit = c.get("paper_median_step") or c["median_step"]
            out.append((name.rsplit("/", 1)[0], c["W"] / unit, fit(n_iter=1) / unit, fit() / unit))
    return out


def main(argv=None):
    folder = (argv or sys.argv[1:] or ["benchmarks/results/table1"])[0]
    rows = refits(folder)
    stored, plain, robust = (np.array([r[i] for r in rows]) for i in (1, 2, 3))
    print(f"{folder}: {len(rows)} fitted calibrations; every stored W is the plain fit: "
          f"{bool(np.allclose(stored, plain, rtol=0, atol=1e-7))}")
    d = robust - plain
    print(f"robust - plain W (paper median steps): mean {d.mean():+.3f}, range {d.min():+.3f} .. {d.max():+.3f}, "
          f"largest relative {np.max(np.abs(d / plain)):.1%}")


if __name__ == "__main__":
    main()
