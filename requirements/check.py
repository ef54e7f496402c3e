#!/usr/bin/env python3
"""Fail when a requirement or constraint would not install on another machine.

Usage: python requirements/check.py [FILE ...]   (default: requirements/constraints.txt and the
dependencies of pyproject.toml). Exit 1 listing each offending line with its file and line number.

Refused: direct references (``name @ URL``), ``file:`` URLs, any ``scheme://`` URL, VCS requirements
(``git+``, ``hg+``, ``svn+``, ``bzr+``), editable installs (``-e``), local paths (``./``, ``../``,
``/``, ``~``), and pip options that point pip somewhere else (``--find-links``, ``--index-url``,
``--extra-index-url``, ``-f``, ``-i``). A constraints file holds ``name==version`` lines only.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BAD = [
    (re.compile(r"\s@\s|^[A-Za-z0-9_.\-\[\],]+@"), "a direct reference (name @ URL)"),
    (re.compile(r"file:", re.I), "a file: URL"),
    (re.compile(r"[a-z][a-z0-9+.\-]*://", re.I), "a URL"),
    (re.compile(r"^(git|hg|svn|bzr)\+", re.I), "a VCS requirement"),
    (re.compile(r"^(-e|--editable)\b"), "an editable install"),
    (re.compile(r"^(\.{1,2}/|/|~)"), "a local path"),
    (re.compile(r"^(-f|-i|--find-links|--index-url|--extra-index-url)\b"), "a pip option pointing elsewhere"),
]
PIN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]*(\[[A-Za-z0-9_,.\-]+\])?==[A-Za-z0-9_.+!\-]+(\s*;.*)?$")


def pyproject_requirements(path: Path) -> list[tuple[int, str]]:
    import tomllib

    data = tomllib.loads(path.read_text())
    proj = data.get("project", {})
    reqs = list(proj.get("dependencies", []))
    for extra in proj.get("optional-dependencies", {}).values():
        reqs += extra
    text = path.read_text().splitlines()
    out = []
    for r in reqs:  # line number of the requirement in the file, for the message
        n = next((i + 1 for i, line in enumerate(text) if f'"{r}"' in line), 0)
        out.append((n, r))
    return out


def problems(path: Path) -> list[str]:
    path = Path(path)
    if path.suffix == ".toml":
        lines, pinned = pyproject_requirements(path), False
    else:
        lines = [(i + 1, line.split(" #")[0].strip()) for i, line in enumerate(path.read_text().splitlines())]
        lines = [(n, s) for n, s in lines if s and not s.startswith("#")]
        pinned = True
    out = []
    for n, s in lines:
        why = next((w for rx, w in BAD if rx.search(s)), None)
        if why is None and pinned and not PIN.match(s):
            why = "not a 'name==version' pin"
        if why:
            out.append(f"{path}:{n}: {why}: {s}")
    return out


def main(argv: list[str]) -> int:
    files = [Path(a) for a in argv] or [ROOT / "requirements" / "constraints.txt", ROOT / "pyproject.toml"]
    found = [p for f in files for p in problems(f)]
    for p in found:
        print(p, file=sys.stderr)
    if found:
        print(f"{len(found)} requirement line(s) would not install on another machine", file=sys.stderr)
        return 1
    print(f"ok: {', '.join(str(f) for f in files)} install anywhere (no URLs, no local paths)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
