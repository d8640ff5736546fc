"""Make a student copy of the project with one exercise blanked out.

    python tests/exercises/make_student_copy.py --list
    python tests/exercises/make_student_copy.py --exercise 3 --out student/

An exercise is one or more regions of the reference modules, each between two marker comments:

    # >>> exercise 3: partial denoising and its index convention (Eq. 4, Sec. IV-B)
    ...reference code...
    # <<< exercise 3

The copy holds every project file (git's tracked and untracked-but-not-ignored files; without git,
the tree minus runs/, student/ and caches) unchanged, except that the lines between the markers of
the chosen exercise become one `raise NotImplementedError("exercise N: ...")` at the marker's
indentation. The markers stay, so the student sees where to write. Every blanked file is parsed
before it is written: a region that is not a complete run of statements is an error here, not in
the student's hands. The texts of the exercises are in tests/exercises/README.md.
"""
from __future__ import annotations

import argparse
import ast
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the project root (tests/exercises/ -> ..)
MODULES = ("envs.py", "diffusion.py", "partial_denoise.py", "calibrate.py", "relabel.py", "oracle.py",
           "dagger.py")  # the only files that hold exercise regions
OPEN = re.compile(r"^(?P<indent>[ ]*)# >>> exercise (?P<n>\d+): (?P<title>\S.*?)\s*$")
CLOSE = re.compile(r"^(?P<indent>[ ]*)# <<< exercise (?P<n>\d+)\s*$")
SKIP_DIRS = {".git", "runs", "student", "__pycache__", ".pytest_cache", ".benchmarks"}  # without git


@dataclass(frozen=True)
class Region:
    exercise: int       # the exercise number
    title: str          # the text after "exercise N:" on the opening marker
    path: str           # module file name, relative to the project root
    start: int          # 0-based line index of the opening marker
    end: int            # 0-based line index of the closing marker
    indent: str         # the markers' indentation (the raise gets the same)


def find_regions(root: Path = ROOT) -> list[Region]:
    """Every marked region of the modules, in file order. ValueError on a malformed marker pair."""
    regions = []
    for name in MODULES:
        path = root / name
        if not path.exists():
            continue
        lines = path.read_text().splitlines()
        open_at = None
        for i, line in enumerate(lines):
            m_open, m_close = OPEN.match(line), CLOSE.match(line)
            if ">>> exercise" in line and not m_open or "<<< exercise" in line and not m_close:
                raise ValueError(f"{name}:{i + 1}: malformed exercise marker {line.strip()!r}; expected "
                                 "'# >>> exercise N: title' or '# <<< exercise N'")
            if m_open:
                if open_at is not None:
                    raise ValueError(f"{name}:{i + 1}: exercise region opened inside the region opened "
                                     f"at line {open_at[0] + 1} (regions do not nest)")
                open_at = (i, m_open)
            elif m_close:
                if open_at is None:
                    raise ValueError(f"{name}:{i + 1}: '# <<< exercise {m_close['n']}' closes no open region")
                j, m = open_at
                if m_close["n"] != m["n"] or m_close["indent"] != m["indent"]:
                    raise ValueError(f"{name}:{i + 1}: closing marker {line.strip()!r} does not match the "
                                     f"opening marker at line {j + 1} (same number and indentation needed)")
                body = [b for b in lines[j + 1:i] if b.strip()]
                if not body:
                    raise ValueError(f"{name}:{j + 1}: exercise {m['n']} region is empty")
                shallow = [b for b in body if len(b) - len(b.lstrip(" ")) < len(m["indent"])]
                if shallow:
                    raise ValueError(f"{name}:{j + 1}: exercise {m['n']} region has a line less indented than "
                                     f"its markers: {shallow[0].strip()!r}")
                regions.append(Region(int(m["n"]), m["title"], name, j, i, m["indent"]))
                open_at = None
        if open_at is not None:
            raise ValueError(f"{name}:{open_at[0] + 1}: exercise {open_at[1]['n']} region is never closed")
    return regions


def exercises(root: Path = ROOT) -> dict[int, list[Region]]:
    """Exercise number -> its regions (an exercise may span several functions or files)."""
    out: dict[int, list[Region]] = {}
    for region in find_regions(root):
        out.setdefault(region.exercise, []).append(region)
    return dict(sorted(out.items()))


def hole(region: Region) -> str:
    """The line that replaces a region's body in the student copy."""
    message = f"exercise {region.exercise}: {region.title} -- see tests/exercises/README.md"
    return f"{region.indent}raise NotImplementedError({message!r})"


def blank(text: str, regions: list[Region], path: str) -> str:
    """`text` (one module) with the given regions' bodies replaced by a raise; checked to parse."""
    lines = text.splitlines()
    for region in sorted(regions, key=lambda r: r.start, reverse=True):  # bottom up: indices stay valid
        lines[region.start + 1:region.end] = [hole(region)]
    out = "\n".join(lines) + ("\n" if text.endswith("\n") else "")
    try:
        ast.parse(out, filename=path)
    except SyntaxError as err:
        raise ValueError(f"blanking exercise {regions[0].exercise} leaves {path} unparsable "
                         f"(line {err.lineno}: {err.msg}): its region is not a complete run of statements") from err
    return out


def project_files(root: Path = ROOT) -> list[str]:
    """Paths (relative to root) of the project's files: git's view if available, else a tree walk."""
    try:
        listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
                                cwd=root, capture_output=True, check=True).stdout.decode()
        files = [f for f in listed.split("\0") if f and (root / f).is_file()]
        if files:
            return sorted(files)
    except (OSError, subprocess.CalledProcessError):
        pass
    files = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = [d for d in dirnames if d not in SKIP_DIRS and not d.endswith(".egg-info")]
        files += [os.path.relpath(os.path.join(dirpath, f), root) for f in filenames if not f.endswith(".pyc")]
    return sorted(files)


def make_student_copy(exercise: int, out, root: Path = ROOT) -> list[str]:
    """Copy the project to `out` with exercise `exercise` blanked. Returns the files that were blanked.

    `out` must not exist or be an empty directory (a student's work is never overwritten).
    """
    table = exercises(root)
    if exercise not in table:
        raise ValueError(f"no exercise {exercise}; valid: {sorted(table)} (see --list)")
    out = Path(out).resolve()
    if out == root or out in root.parents or root in out.parents and out.relative_to(root).parts[0] != "student":
        raise ValueError(f"--out {out} would mix the copy with the project; use student/... or a path outside it")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"--out {out} exists and is not an empty directory; choose a new path")
    by_file: dict[str, list[Region]] = {}
    for region in table[exercise]:
        by_file.setdefault(region.path, []).append(region)
    blanked = {name: blank((root / name).read_text(), regs, name) for name, regs in by_file.items()}
    for rel in project_files(root):
        if Path(rel).parts[0] in SKIP_DIRS:
            continue
        dest = out / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        if rel in blanked:
            dest.write_text(blanked[rel])
        else:
            shutil.copy2(root / rel, dest)
    return sorted(blanked)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--list", action="store_true", help="list the exercises and their regions")
    parser.add_argument("--exercise", type=int, help="the exercise to blank")
    parser.add_argument("--out", help="where to write the student copy (a new or empty directory)")
    args = parser.parse_args(argv)
    table = exercises()
    if args.list:
        for n, regions in table.items():
            print(f"exercise {n}: {regions[0].title}")
            for r in regions:
                print(f"    {r.path}:{r.start + 2}-{r.end}")
        return 0
    if args.exercise is None or args.out is None:
        parser.error("give --list, or --exercise N and --out DIR")
    try:
        files = make_student_copy(args.exercise, args.out)
    except ValueError as err:
        parser.error(str(err))
    print(f"wrote {args.out}: exercise {args.exercise} blanked in {', '.join(files)}; "
          f"check it with: cd {args.out} && python -m pytest -q tests/exercises/test_exercise_{args.exercise}_*.py")
    return 0


if __name__ == "__main__":
    sys.exit(main())
