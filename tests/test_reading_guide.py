"""The README's reading guide names what the run executes.

Every function the guide's table names (its "read (file: function)" column) must be called by one run of the whole
loop, from the method itself and not only from a figure — or its row must mark it "(not run: ...)", the paper's
alternative or read-out that the run does not use. A marked function the run does call fails too (a stale mark).
"""
from __future__ import annotations

import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MODULES = ("envs", "diffusion", "partial_denoise", "calibrate", "relabel", "oracle", "dagger", "experiment/report")


def guide_names(readme_text):
    """{(module, name): (step, marked)} for every `name` the guide's 'read' column gives after 'module.py:';
    marked: the name is followed by '(not run' in its row."""
    guide = readme_text.split("## Reading guide", 1)[1].split("\n## ", 1)[0]
    names = {}
    for line in guide.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not line.startswith("| ") or cells[0] == "step" or set(cells[0]) <= set("-"):
            continue
        # the 'read' cell: 'module.py: `a`, `b` (...); other.py: `c`' -- a name belongs to the last module named
        for part in re.split(r"(?=\b(?:%s)\.py:)" % "|".join(MODULES), cells[2]):
            m = re.match(r"(?:experiment/)?(\w+)\.py:(.*)", part.strip(), re.S)
            if not m:
                continue
            for name in re.finditer(r"`([\w.]+)[^`]*`( \(not run)?", m.group(2)):
                names[(m.group(1), name.group(1))] = (cells[0], bool(name.group(2)))
    return names


def runs(called, module, name):
    """A function name, Class, or Class.method of `module` was called (a class: any of its methods)."""
    return any(m == module and (q == name or q.startswith(name + ".") or q.endswith("." + name)) for m, q in called)


def test_the_guide_parser_reads_marks_and_modules():
    """Fails if a name is credited to the wrong module or a '(not run' mark is missed or invented."""
    text = ("## Reading guide\n| step | paper | read (file: function) | checked by |\n|---|---|---|---|\n"
            "| 3a. blend | Eq. 3 | partial_denoise.py: `lerp_blend` (not run: the paper's alternative), `switch_step`; "
            "diffusion.py: `train(sampler=...)`, `DiffusionPolicy.sample` | t |\n"
            "| 7b. stats | Tables | dagger.py: `tost`; experiment/report.py: `summarize` (Table I) | t |\n"
            "## Next\n| x | y | dagger.py: `no` | z |\n")
    assert guide_names(text) == {("partial_denoise", "lerp_blend"): ("3a. blend", True),
                                 ("partial_denoise", "switch_step"): ("3a. blend", False),
                                 ("diffusion", "train"): ("3a. blend", False),
                                 ("diffusion", "DiffusionPolicy.sample"): ("3a. blend", False),
                                 ("dagger", "tost"): ("7b. stats", False), ("report", "summarize"): ("7b. stats", False)}


@pytest.mark.slow
def test_every_function_the_reading_guide_names_runs_or_is_marked(smoke_in_one_process):
    """Fails if the guide names a function that one run of the loop never calls (outside the figures) without
    marking it '(not run: ...)', or marks one the run does call."""
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as fh:
        names = guide_names(fh.read())
    assert len(names) > 40, "the guide's table was not found or not parsed"
    unmarked_not_run = [f"{step}: {mod}.{name}" for (mod, name), (step, marked) in names.items()
                        if not marked and not runs(smoke_in_one_process.called, mod, name)]
    marked_but_run = [f"{step}: {mod}.{name}" for (mod, name), (step, marked) in names.items()
                      if marked and runs(smoke_in_one_process.called, mod, name)]
    assert not unmarked_not_run, f"named in the reading guide, not run and not marked '(not run': {unmarked_not_run}"
    assert not marked_but_run, f"marked '(not run' in the reading guide but run: {marked_but_run}"
