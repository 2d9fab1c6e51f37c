#!/usr/bin/env python3
"""Every repository path the pages cite resolves.

Scans README.md and docs/**/*.md for
  - markdown links [text](path): resolved against the linking file's
    folder (a leading / against the repository root); http(s), mailto
    and pure #anchor links are left alone, a #fragment is stripped;
  - backticked paths, in `inline code` and in fenced code blocks: tokens
    that start with one of PREFIXES, resolved against the repository
    root. Tokens with a wildcard or shell syntax (* ? { < $) or an
    uppercase placeholder (results/NAME/, ENV, YOUR_ENV) are skipped, as
    are runs/ paths (a run's output, not part of the repository).

Prints FILE:LINE: path for every one that does not exist and exits 1;
otherwise prints one line with the count and exits 0. Standard library
only:

    python3 scripts/check_paths.py
"""

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

PREFIXES = (
    "experiments/", "configs/", "scripts/", "docs/", "results/", "references/",
    "deploy/", "clients/", "src/", "learner/", "sim/", "graph-builder/",
    "actor/", "proto/", "tests/", "fuzz/",
)

# Paths that are cited on purpose although they do not exist now, each
# with the reason. Keyed by (page relative to the root, path as written);
# the path "*" allows every path on that page.
ALLOWED = {
    # A run's own folders, inside runs/RUN/ (the run a service writes has
    # a learner/ folder), not the learner crate.
    ("docs/usage.md", "learner/summary.json"): "a run's learner/summary.json, under runs/<preset>/",
    ("docs/research/2026-11-23-peg-validation-and-seed-ranges.md", "learner/selected/"): "a run's learner/selected/, beside lcrl train's selected/",
}

# Real file names written in capitals, not placeholders.
CAPITAL_NAMES = {"README", "LICENSE", "CHANGELOG", "CONTRIBUTING", "SECURITY", "NOTICE", "AUTHORS", "CITATION"}

# A path inside code: starts with a prefix, not in the middle of a word
# or of another path (docs/research/experiments/ is one docs/ path).
CODE_PATH = re.compile(
    r"(?<![\w.\-/])((?:" + "|".join(re.escape(p) for p in PREFIXES) + r")[^\s`'\"(),;:\[\]|]*)"
)
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
INLINE_CODE = re.compile(r"(`+)(.+?)(?<!`)\1(?!`)", re.S)
FENCE = re.compile(r"^\s{0,3}(```+|~~~+)")
PLACEHOLDER = re.compile(r"(?<![A-Za-z])[A-Z][A-Z0-9_]*(?![a-z])")


def is_placeholder(token):
    if any(c in token for c in "*?{<$"):
        return True
    return any(word not in CAPITAL_NAMES for word in PLACEHOLDER.findall(token))


def code_paths(text):
    """The repository paths in a piece of code, each with its offset."""
    for m in CODE_PATH.finditer(text):
        path = m.group(1).rstrip(".")
        path = path.split("#", 1)[0]
        if path and not is_placeholder(path):
            yield m.start(1), path


def pages():
    yield ROOT / "README.md"
    yield from sorted((ROOT / "docs").rglob("*.md"))


def scan(page):
    """(line, path as written, resolved Path) for every cited path."""
    lines = page.read_text(encoding="utf-8").split("\n")
    found = []
    # Fenced code blocks: every line is code. Outside them, the text is
    # joined so that an inline code span or link may cross a line break.
    prose, starts, fence = [], [], None
    for number, line in enumerate(lines, 1):
        m = FENCE.match(line)
        if fence is not None:
            if m and m.group(1)[0] == fence[0] and len(m.group(1)) >= len(fence):
                fence = None
            else:
                found += [(number, p, ROOT / p) for _, p in code_paths(line)]
            prose.append("")
        elif m:
            fence = m.group(1)
            prose.append("")
        else:
            prose.append(line)
    text = "\n".join(prose)
    for line in prose:
        starts.append(starts[-1] + len(prev) + 1 if starts else 0)
        prev = line

    def line_of(offset):
        lo, hi = 0, len(starts) - 1
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if starts[mid] <= offset:
                lo = mid
            else:
                hi = mid - 1
        return lo + 1

    blanked = list(text)
    for m in INLINE_CODE.finditer(text):
        # A code span does not cross a blank line (a new paragraph).
        if "\n\n" in m.group(2):
            continue
        for offset, p in code_paths(m.group(2)):
            found.append((line_of(m.start(2) + offset), p, ROOT / p))
        for i in range(m.start(2), m.end(2)):
            if blanked[i] != "\n":
                blanked[i] = " "
    for m in LINK.finditer("".join(blanked)):
        target = m.group(1)
        if re.match(r"(?i)(https?:|mailto:|#)", target):
            continue
        target = target.split("#", 1)[0]
        target = re.sub(r"%([0-9A-Fa-f]{2})", lambda h: chr(int(h.group(1), 16)), target)
        resolved = ROOT / target.lstrip("/") if target.startswith("/") else page.parent / target
        try:
            inside = resolved.resolve().relative_to(ROOT)
        except ValueError:
            inside = None
        if inside is not None and inside.parts[:1] == ("runs",):
            continue
        found.append((line_of(m.start(1)), target, resolved))
    return found


def main():
    missing, checked = [], 0
    for page in pages():
        name = page.relative_to(ROOT).as_posix()
        for line, written, resolved in scan(page):
            checked += 1
            if resolved.exists():
                continue
            if (name, written) in ALLOWED or (name, "*") in ALLOWED:
                continue
            missing.append(f"{name}:{line}: {written}")
    for m in missing:
        print(m)
    if missing:
        print(f"{len(missing)} of {checked} cited paths do not exist", file=sys.stderr)
        return 1
    print(f"OK: {checked} cited paths in README.md and docs/ all exist")
    return 0


if __name__ == "__main__":
    sys.exit(main())
