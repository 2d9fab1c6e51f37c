#!/usr/bin/env python3
"""No function a newcomer must scroll (issue 83 item 6).

Scans every .rs file of the repository (the workspace and fuzz/; never
target/, fuzz/target/, hidden folders, .venv/ or runs/) and lists every
non-test function (free functions, methods and trait methods; closures
are not functions here) that

  - is over MAX_LINES lines, counted from the line of its `fn` to the
    line of its closing brace, or
  - takes more than MAX_ARGS parameters (`self` does not count).

Test code is left out: files named tests.rs or *_tests.rs, files under a
tests/ folder, items marked #[test] or #[cfg(test)] (a module in the file,
or a module file such a declaration names), and everything inside them.

Braces are matched on the code alone: comments (nested block comments
included), strings (raw, byte and C strings included) and character
literals are blanked first, so a brace inside them counts for nothing.

A finding is exempt when the lines directly above its function (its doc
comment, plain comments and attribute lines, with no blank line between)
hold a plain comment `// long: REASON` (for the length) or
`// args: REASON` (for the parameters), for example

    /// Checks a study's file before any run starts.
    // long: one flat table of checks, read top to bottom
    pub fn check(&self) -> Result<(), Error> {

Prints `PATH:LINE fn NAME — N lines` or `— N arguments` for every finding
without its reason and exits 1; otherwise prints one OK line and exits 0.
Standard library only:

    python3 scripts/long_functions.py
"""

import bisect
import os
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

MAX_LINES = 80
MAX_ARGS = 6

# Folders never scanned, wherever they are.
SKIP_DIRS = {"target", "tests", ".venv", "runs", "node_modules"}

IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
FN = re.compile(r"(?<![A-Za-z0-9_$])fn\s+(?:r#)?([A-Za-z_][A-Za-z0-9_]*)")
ATTRIBUTE = re.compile(r"#!?\s*\[")
SELF_PARAM = re.compile(r"^(?:&\s*(?:'[A-Za-z_][A-Za-z0-9_]*\s+)?)?(?:mut\s+)?self\b")
REASON = {"lines": re.compile(r"^\s*//\s*long:\s*\S"), "args": re.compile(r"^\s*//\s*args:\s*\S")}
COMMENT_LINE = re.compile(r"^\s*//")
ATTRIBUTE_LINE = re.compile(r"^\s*#\[")


def mask(text):
    """The text with comments, strings and character literals replaced by
    spaces (newlines kept, so offsets and line numbers stay the same)."""
    out = list(text)
    n = len(text)
    i = 0

    def blank(start, end):
        for k in range(start, min(end, n)):
            if out[k] != "\n":
                out[k] = " "

    def ident_before(k):
        return k > 0 and (text[k - 1].isalnum() or text[k - 1] == "_")

    while i < n:
        c = text[i]
        if c == "/" and text.startswith("//", i):
            end = text.find("\n", i)
            end = n if end < 0 else end
            blank(i, end)
            i = end
        elif c == "/" and text.startswith("/*", i):
            depth, k = 1, i + 2
            while k < n and depth:
                if text.startswith("/*", k):
                    depth, k = depth + 1, k + 2
                elif text.startswith("*/", k):
                    depth, k = depth - 1, k + 2
                else:
                    k += 1
            blank(i, k)
            i = k
        elif c in "brc" and not ident_before(i) and (raw := re.match(r"(?:br|cr|r)(#*)\"", text[i:i + 300])):
            # A raw string: r"..", r#".."#, br".." or cr"..", no escapes.
            close = '"' + raw.group(1)
            end = text.find(close, i + raw.end())
            end = n if end < 0 else end + len(close)
            blank(i, end)
            i = end
        elif c == '"':
            k = i + 1
            while k < n and text[k] != '"':
                k += 2 if text[k] == "\\" else 1
            blank(i, k + 1)
            i = k + 1
        elif c == "'":
            # A character literal ('a', '\n', '\u{7f}', '{') or a lifetime
            # or label ('a, 'static, 'outer:), which is code.
            if i + 1 < n and text[i + 1] == "\\":
                k = i + 3
                while k < n and text[k] != "'":
                    k += 2 if text[k] == "\\" else 1
                blank(i, k + 1)
                i = k + 1
            elif i + 2 < n and text[i + 2] == "'" and text[i + 1] != "\n":
                blank(i, i + 3)
                i += 3
            else:
                i += 1
        else:
            i += 1
    return "".join(out)


def matching(code, open_at):
    """The offset of the bracket that closes the one at `open_at` (one of
    ( [ {), or len(code) when the file ends first."""
    pairs = {"(": ")", "[": "]", "{": "}"}
    stack = []
    for k in range(open_at, len(code)):
        c = code[k]
        if c in pairs:
            stack.append(pairs[c])
        elif c in ")]}":
            if stack and stack[-1] == c:
                stack.pop()
            if not stack:
                return k
    return len(code)


def item_end(code, start):
    """Where the item that starts at `start` ends: its first `;` outside
    brackets, or the brace that closes its first block."""
    k = start
    while k < len(code):
        c = code[k]
        if c in "([":
            k = matching(code, k) + 1
        elif c == "{":
            return matching(code, k)
        elif c == ";":
            return k
        else:
            k += 1
    return len(code)


def skip_attributes(code, k):
    """The offset after the attributes (and white space) that start at k."""
    while True:
        while k < len(code) and code[k].isspace():
            k += 1
        m = ATTRIBUTE.match(code, k)
        if not m:
            return k
        k = matching(code, m.end() - 1) + 1


def is_test_cfg(attribute):
    """#[test] or a #[cfg(..)] that holds only under test."""
    body = re.sub(r"\s+", "", attribute)
    if body in ("#[test]", "#[tokio::test]") or re.match(r"#\[[\w:]*::test\b", body):
        return True
    if not body.startswith("#[cfg("):
        return False
    return bool(re.search(r"\btest\b", body)) and "not(test" not in body and not body.startswith("#[cfg(any(")


def test_ranges(code):
    """(start, end) offsets of the test items of a file, and the names of
    the module files its #[cfg(test)] declarations (mod name;) bring in."""
    ranges, test_mods = [], []
    if re.search(r"#!\s*\[\s*cfg\s*\(\s*test\s*\)\s*\]", code):
        return [(0, len(code))], test_mods
    for m in ATTRIBUTE.finditer(code):
        if code[m.start() + 1] == "!":
            continue
        close = matching(code, m.end() - 1)
        if not is_test_cfg(code[m.start():close + 1]):
            continue
        start = skip_attributes(code, close + 1)
        end = item_end(code, start)
        ranges.append((m.start(), end))
        decl = re.match(r"(?:pub(?:\([^)]*\))?\s+)?mod\s+([A-Za-z_][A-Za-z0-9_]*)\s*;", code[start:end + 1])
        if decl:
            test_mods.append(decl.group(1))
    return ranges, test_mods


def split_params(params):
    """The parameters in a parameter list's inside, split at the commas
    outside brackets and generics."""
    parts, depth, current = [], 0, []
    k = 0
    while k < len(params):
        c = params[k]
        if c in "([{<":
            depth += 1
        elif c in ")]}":
            depth -= 1
        elif c == ">" and not (k > 0 and params[k - 1] in "-="):
            depth -= 1
        if c == "," and depth == 0:
            parts.append("".join(current))
            current = []
        else:
            current.append(c)
        k += 1
    parts.append("".join(current))
    return [p.strip() for p in parts if p.strip()]


def signature(code, name_end):
    """(parameter count without self, offset of the body's `{` or None)
    of the function whose name ends at name_end."""
    k = name_end
    while k < len(code) and code[k].isspace():
        k += 1
    if k < len(code) and code[k] == "<":
        depth = 0
        while k < len(code):
            if code[k] == "<":
                depth += 1
            elif code[k] == ">" and code[k - 1] != "-":
                depth -= 1
                if depth == 0:
                    k += 1
                    break
            k += 1
        while k < len(code) and code[k].isspace():
            k += 1
    if k >= len(code) or code[k] != "(":
        return None
    close = matching(code, k)
    params = [p for p in split_params(code[k + 1:close]) if not SELF_PARAM.match(re.sub(r"#\[[^\]]*\]\s*", "", p))]
    # Then the return type and where clause, up to the body or a `;`.
    j = close + 1
    while j < len(code):
        c = code[j]
        if c in "([":
            j = matching(code, j) + 1
        elif c == "{":
            return len(params), j
        elif c == ";":
            return len(params), None
        else:
            j += 1
    return len(params), None


def has_reason(lines, fn_line, kind):
    """Whether the comment and attribute lines directly above line
    `fn_line` (1-based) hold a `// long:` or `// args:` reason."""
    k = fn_line - 2
    while k >= 0:
        line = lines[k]
        if REASON[kind].match(line):
            return True
        if COMMENT_LINE.match(line) or ATTRIBUTE_LINE.match(line):
            k -= 1
            continue
        if line.rstrip().endswith("]"):
            # The last line of an attribute written over several lines:
            # on from the line that opens it.
            j = k - 1
            while j >= max(0, k - 20) and not ATTRIBUTE_LINE.match(lines[j]):
                j -= 1
            if j >= 0 and ATTRIBUTE_LINE.match(lines[j]):
                k = j - 1
                continue
        return False
    return False


def rust_files():
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = sorted(d for d in dirs if d not in SKIP_DIRS and not d.startswith("."))
        for name in sorted(files):
            if name.endswith(".rs") and name != "tests.rs" and not name.endswith("_tests.rs"):
                yield Path(folder) / name


def module_files(path, names):
    """The files `mod name;` in `path` may name."""
    base = path.parent if path.name in ("mod.rs", "lib.rs", "main.rs") else path.parent / path.stem
    for name in names:
        yield (base / f"{name}.rs").resolve()
        yield (base / name / "mod.rs").resolve()


def scan(path):
    """(findings, functions seen, module files of test modules)."""
    text = path.read_text(encoding="utf-8", errors="replace")
    code = mask(text)
    lines = text.split("\n")
    starts = [0] + [m.end() for m in re.finditer("\n", text)]
    line_of = lambda offset: bisect.bisect_right(starts, offset)
    ranges, test_mods = test_ranges(code)
    findings, seen = [], 0
    for m in FN.finditer(code):
        if any(a <= m.start() <= b for a, b in ranges):
            continue
        sig = signature(code, m.end())
        if sig is None:
            continue
        seen += 1
        params, body = sig
        first = line_of(m.start())
        name = m.group(1)
        if body is not None:
            length = line_of(matching(code, body)) - first + 1
            if length > MAX_LINES and not has_reason(lines, first, "lines"):
                findings.append((first, name, f"{length} lines"))
        if params > MAX_ARGS and not has_reason(lines, first, "args"):
            findings.append((first, name, f"{params} arguments"))
    return findings, seen, list(module_files(path, test_mods))


def main():
    files = list(rust_files())
    test_files = set()
    results = []
    for path in files:
        findings, seen, test_mods = scan(path)
        test_files.update(test_mods)
        results.append((path, findings, seen))
    found, functions, scanned = 0, 0, 0
    for path, findings, seen in results:
        if path.resolve() in test_files:
            continue
        scanned += 1
        functions += seen
        for line, name, what in findings:
            print(f"{path.relative_to(ROOT)}:{line} fn {name} — {what}")
            found += 1
    if found:
        print(f"{found} function(s) over {MAX_LINES} lines or {MAX_ARGS} arguments without a `// long:` or `// args:` reason")
        return 1
    print(f"OK: {functions} functions in {scanned} files, none over {MAX_LINES} lines or {MAX_ARGS} arguments without a reason")
    return 0


if __name__ == "__main__":
    sys.exit(main())
