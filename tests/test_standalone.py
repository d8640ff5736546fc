"""The repository stands alone: no tracked file points a reader to a file outside it.

A fresh clone holds only what git tracks. The team's notes that once sat beside the repository (the authors'
setup notes, the design and style notes, the paper's LaTeX source) are not in a clone, so a comment or document
that sends the reader there is a dead end. The authors' setup is benchmarks/SETUP.md; where to get the paper is
in README.md. This test fails on any tracked text file that names the folder beside the repository or one of
those files.
"""
from __future__ import annotations

import os
import re
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Written in pieces so that this file does not match itself.
OUTSIDE_FOLDER = re.compile(r"\.\./" + "shared" + r"\b|/work/" + "shared" + r"\b")
OUTSIDE_FILES = re.compile("PAPER" + "_SETUP" + r"|\bpaper\." + "tex" + r"\b", re.IGNORECASE)
# Notes that may one day be added to the repository: a mention is fine once a tracked file has that name.
MAYBE_OUTSIDE = ("DESIGN" + ".md", "STYLE" + ".md")


def tracked_files():
    """Paths (relative to the root) of every file git tracks; without git, every file under the root but
    the folders git ignores here (a copy of the tree without its .git)."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
        return [p for p in out.decode("utf-8").split("\0") if p]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", "runs", "student", "__pycache__", ".pytest_cache"}
        paths = []
        for folder, dirs, files in os.walk(ROOT):
            dirs[:] = [d for d in dirs if d not in skip and not d.endswith(".egg-info")]
            paths += [os.path.relpath(os.path.join(folder, f), ROOT) for f in files]
        return paths


def outside_references(text, tracked_names=()):
    """[(line number, the matched text)] of every reference in `text` to a path outside the repository;
    tracked_names: the base names of the tracked files (a name among them is inside)."""
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        for pattern in (OUTSIDE_FOLDER, OUTSIDE_FILES):
            found += [(number, m.group(0)) for m in pattern.finditer(line)]
        found += [(number, name) for name in MAYBE_OUTSIDE if name in line and name not in tracked_names]
    return found


def read_text(path):
    """The file's text, or None for a binary file (a checkpoint, an image, a compressed lineage)."""
    with open(os.path.join(ROOT, path), "rb") as fh:
        data = fh.read()
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def test_the_scanner_finds_each_kind_of_outside_reference():
    """Fails if the scanner misses a reference of one of the kinds, or flags the files that replace them."""
    sample = ("see ../" "shared/PAPER" "_SETUP.md §2\n"
              "Paper map (paper." "tex):\n"
              "the design's map (DESIGN" ".md)\n"
              "the authors' setup: benchmarks/SETUP.md §2; the paper: README.md\n")
    found = outside_references(sample)
    assert [n for n, _ in found] == [1, 1, 2, 3], found
    assert outside_references(sample, tracked_names={"DESIGN" ".md"})[-1][0] == 2  # once tracked, a name is inside
    assert outside_references("benchmarks/SETUP.md §5, benchmarks/HISTORY.md, sharedir/x") == []


def test_no_tracked_file_refers_to_a_path_outside_the_repository():
    """Fails, naming file and line, when a tracked text file refers to the folder beside the repository, to the
    authors' setup notes by their old name, to the paper's LaTeX source as a file, or to a design or style note
    that the repository does not hold."""
    paths = tracked_files()
    assert len(paths) > 20, "the tracked files were not found"
    names = {os.path.basename(p) for p in paths}
    me = os.path.relpath(os.path.abspath(__file__), ROOT)
    bad = []
    for path in paths:
        if path == me or not os.path.isfile(os.path.join(ROOT, path)):
            continue
        text = read_text(path)
        if text is None:
            continue
        bad += [f"{path}:{number}: {match}" for number, match in outside_references(text, names)]
    assert not bad, ("references to paths outside the repository (the authors' setup is benchmarks/SETUP.md, "
                     "the paper is named in README.md):\n" + "\n".join(bad))
