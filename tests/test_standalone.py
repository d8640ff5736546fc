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


# A machine's own folders: a path that starts there is one person's checkout or run folder, not the reader's.
MACHINE_PATH = re.compile(r"(?<![\w.~])/(?:" + "root|home|work" + r")/")


def heading_anchor(heading):
    """The anchor a markdown heading gets on GitHub: its text without links' targets and backticks, lower case,
    every character but letters, digits, '_', '-' and spaces dropped, each space a '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).replace("`", "").strip().lower()
    return "".join(ch for ch in text if ch.isalnum() or ch in "_- ").replace(" ", "-")


def anchors(text):
    """The anchors of a markdown text's headings (outside code fences); a repeated heading's get -1, -2, ..."""
    found, seen, fenced = set(), {}, False
    for line in text.splitlines():
        fenced ^= line.startswith("```")
        m = None if fenced else re.match(r"(#{1,6})\s+(.*?)\s*$", line)
        if m:
            anchor = heading_anchor(m.group(2))
            n = seen[anchor] = seen.get(anchor, -1) + 1
            found.add(anchor if n == 0 else f"{anchor}-{n}")
    return found


def test_the_anchor_rule_matches_githubs():
    """Fails if heading_anchor drops or keeps the wrong characters (then the test below checks the wrong anchors):
    the anchors GitHub gives these headings."""
    assert heading_anchor("Table I (planar reacher), five lineages × five rounds") == \
        "table-i-planar-reacher-five-lineages--five-rounds"
    assert heading_anchor("The default run, `python dagger.py`") == "the-default-run-python-daggerpy"
    assert heading_anchor("The σ = 0 control on the lever: is it the noise?") == \
        "the-σ--0-control-on-the-lever-is-it-the-noise"
    assert heading_anchor("What the env takes from the authors' code (`benchmarks/SETUP.md`)") == \
        "what-the-env-takes-from-the-authors-code-benchmarkssetupmd"
    assert anchors("# A\n```\n# not a heading\n```\n## A\n") == {"a", "a-1"}


def test_every_markdown_link_to_a_section_finds_its_heading():
    """Fails, naming file and line, when a tracked markdown file links to a section (`(#anchor)` or
    `(FILE.md#anchor)`) that no heading of that file has: a renamed heading leaves a dead link."""
    bad = []
    for path in (p for p in tracked_files() if p.endswith(".md")):
        text = read_text(path)
        for m in re.finditer(r"\]\(([^)\s#]*)#([^)\s]+)\)", text):
            target, anchor = m.group(1), m.group(2)
            if re.match(r"\w+://", target):
                continue
            linked = os.path.normpath(os.path.join(os.path.dirname(path), target)) if target else path
            full = os.path.join(ROOT, linked)
            if not os.path.isfile(full) or anchor not in anchors(read_text(linked)):
                bad.append(f"{path}:{text[:m.start()].count(chr(10)) + 1}: {target}#{anchor}")
    assert not bad, "links to sections that no heading has:\n" + "\n".join(bad)


def matches_in_tracked_files(pattern):
    """(path, line number, line, match) of every match of `pattern` in the tracked text files (this file aside: it
    holds the patterns' own examples)."""
    me = os.path.relpath(os.path.abspath(__file__), ROOT)
    for path in tracked_files():
        text = None if path == me or not os.path.isfile(os.path.join(ROOT, path)) else read_text(path)
        for number, line in enumerate((text or "").splitlines(), start=1):
            yield from ((path, number, line, m) for m in pattern.finditer(line))


def test_no_tracked_file_names_a_machine_path():
    """Fails, naming file and line, when a tracked text file names a path under one machine's /root, /home or /work
    (a run folder or script on the machine that wrote it): the reader's clone has it elsewhere or not at all."""
    bad = [f"{path}:{number}: {line.strip()[:100]}" for path, number, line, _ in matches_in_tracked_files(MACHINE_PATH)]
    assert MACHINE_PATH.search("--out /" "root/runs/x") and not MACHINE_PATH.search("runs/x, ~/work/x, a/home/b")
    assert not bad, "machine paths in tracked files (name run folders relative to the repository):\n" + "\n".join(bad)


def test_no_tracked_file_names_an_issue_number():
    """Fails, naming file and line, when a tracked text file cites the project tracker's issues by number ("issue
    42", "issues 60-61", "issue-59"): a reader of a clone has no tracker; a change is named by what it did (and its
    commit)."""
    issue = re.compile(r"\b[Ii]ssues?[ -]#?\d+")
    assert issue.search("as in issue" " 42") and issue.search("the issue-" "59 study") and not issue.search("an issue")
    bad = [f"{path}:{number}: {m.group(0)}" for path, number, _, m in matches_in_tracked_files(issue)]
    assert not bad, "issue numbers in tracked files:\n" + "\n".join(bad)
