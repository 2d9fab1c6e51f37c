#!/usr/bin/env python3
"""Every shell and Python block of README.md and docs/usage.md, run as printed.

Each ```sh or ```python block in those files carries a mark on the line just
above its fence, so that no block is left untested by accident:

  <!-- readme-test: quick -->                 the suite runs it (tests/e2e/readme.rs)
  <!-- readme-test: quick, beside lti-run -->  ... while `lcrl run --config configs/lti-paper.toml` trains
  <!-- readme-test: quick, beside learner -->  ... beside a standalone lcrl-learner (no token) on 127.0.0.1:50052
  <!-- readme-test: quick, after peg-run -->   ... after a short peg-group1 run (what scripts/run.sh runs, 20 episodes)
  <!-- readme-test: apart, slow -->           too slow for the suite: `bash scripts/readme-apart.sh` runs it
  <!-- readme-test: apart, needs TOOL -->     needs a tool set-up does not install (grpcurl, kubectl):
                                              scripts/readme-apart.sh runs it where TOOL is on PATH
  <!-- readme-test: apart, service -->        a service that runs until stopped (docker compose up): by
                                              hand; tests/e2e/deploy.rs runs the compose stack
  <!-- readme-test: suite -->                 the test command itself (.ci/run runs it)

A quick block runs in a scratch directory that links the repository's folders
(so `runs/`, `policy.pt` and the like land there, never in the checkout); an
apart block runs in the checkout, as a user runs it. Either runs as
one bash script with `set -euo pipefail` (Python blocks with .venv/bin/python).
What is substituted, and nothing else:
  - a line's leading `lcrl ` becomes `target/debug/lcrl ` (README: "below,
    `lcrl` is `target/debug/lcrl`");
  - `PORT` becomes the port of the run the block is beside;
  - the fixed ports 50051 and 50052 become free ones (the same one for the
    whole block and what it is beside), so a busy port on this machine does
    not fail the test;
  - after a line that starts a server in the background (`... --listen
    HOST:PORT &`), the block waits until that port accepts connections, as a
    person would before the next command.
Beside lti-run, the query commands `lcrl run` itself prints ("query it") are
run as well.

Usage: readme_blocks.py list | quick | apart [--dry-run]   [--file MD ...] [--only FILE:LINE ...]
Exits non-zero if a block has no mark, a quick block fails, or (apart) a block
that can run here fails.
"""
import argparse
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FILES = ["README.md", "docs/usage.md"]
MARK = re.compile(r"<!--\s*readme-test:\s*(.*?)\s*-->")
FENCE = re.compile(r"^```(\w*)\s*$")
APART_SCRIPT = "scripts/readme-apart.sh"
BLOCK_TIMEOUT_S = 600
# What the scratch directory links from the checkout (everything a block may
# read); outputs (runs/, policy.pt, ...) stay in the scratch directory.
LINKED = ["target", ".venv", "configs", "clients", "experiments", "references", "scripts", "proto", "deploy", "docs", "Cargo.toml", "Cargo.lock"]


class Block:
    def __init__(self, path, line, lang, mark, text):
        self.path, self.line, self.lang, self.mark, self.text = path, line, lang, mark, text

    @property
    def where(self):
        return f"{self.path}:{self.line}"

    @property
    def kind(self):
        return self.mark.split(",")[0].strip() if self.mark else None

    def option(self, key):
        """The word after `key` in the mark (beside lti-run -> lti-run)."""
        for part in (self.mark or "").split(",")[1:]:
            words = part.split()
            if len(words) >= 2 and words[0] == key:
                return words[1]
        return None


def blocks_of(path):
    """Every sh/python block of one Markdown file, with the mark above it."""
    lines = open(os.path.join(ROOT, path) if not os.path.isabs(path) else path, encoding="utf-8").read().split("\n")
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if m and m.group(1):
            lang, start, body = m.group(1), i, []
            i += 1
            while i < len(lines) and not lines[i].startswith("```"):
                body.append(lines[i])
                i += 1
            if lang in ("sh", "bash", "python"):
                mark = MARK.search(lines[start - 1]) if start > 0 else None
                out.append(Block(path, start + 1, lang, mark.group(1) if mark else None, "\n".join(body)))
        i += 1
    return out


def check_marks(blocks):
    """Problems with the marks: unmarked blocks, unknown kinds or fixtures."""
    problems = []
    for b in blocks:
        if b.kind is None:
            problems.append(f"{b.where}: a {b.lang} block without a mark (<!-- readme-test: quick|apart, ...|suite -->)")
        elif b.kind not in ("quick", "apart", "suite"):
            problems.append(f"{b.where}: unknown mark {b.mark!r}")
        elif b.kind == "quick" and (b.option("beside") or b.option("after")) not in (None, *FIXTURES):
            problems.append(f"{b.where}: unknown fixture in {b.mark!r} (known: {', '.join(FIXTURES)})")
        elif b.kind == "apart" and not (b.mark.endswith(("slow", "service")) or b.option("needs")):
            problems.append(f"{b.where}: an apart block says why: 'apart, slow', 'apart, service' or 'apart, needs TOOL'")
    return problems


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def scratch_dir():
    d = tempfile.mkdtemp(prefix="lcrl-readme-")
    for name in LINKED:
        if os.path.exists(os.path.join(ROOT, name)):
            os.symlink(os.path.join(ROOT, name), os.path.join(d, name))
    return d


def substitute(text, ports):
    """The documented substitutions, nothing else."""
    out = []
    for line in text.split("\n"):
        if line.startswith("lcrl "):
            line = "target/debug/" + line
        for fixed, real in ports.items():
            line = re.sub(rf"\b{fixed}\b", str(real), line)
        out.append(line)
        listen = re.search(r"--listen\s+[\d.]+:(\d+).*&\s*(#.*)?$", line)
        if listen:
            out.append(f"for _ in $(seq 600); do (exec 3<>/dev/tcp/127.0.0.1/{listen.group(1)}) 2>/dev/null && break; sleep 0.1; done")
    return "\n".join(out)


def run_block(block, cwd, ports):
    """Runs one block as printed (after substitution); (ok, output)."""
    text = substitute(block.text, ports)
    if block.lang == "python":
        cmd = [os.path.join(cwd, ".venv/bin/python"), "-c", text]
    else:
        script = "set -euo pipefail\ntrap 'kill $(jobs -p) 2>/dev/null || true' EXIT\n" + text + "\n"
        cmd = ["bash", "-c", script]
    try:
        p = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S)
    except subprocess.TimeoutExpired as e:
        return False, f"timed out after {BLOCK_TIMEOUT_S} s\n{e.stdout or ''}{e.stderr or ''}"
    return p.returncode == 0, f"exit {p.returncode}\n--- block as run ---\n{text}\n--- stdout ---\n{p.stdout}--- stderr ---\n{p.stderr}"


class Background:
    """A process a block runs beside; its output lines are kept to be read."""

    def __init__(self, cmd, cwd):
        self.lines, self.proc = [], subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self):
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, pattern, timeout_s=180):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            ended = not self.reader.is_alive()  # then every line it printed is in self.lines
            for line in list(self.lines):
                m = re.search(pattern, line)
                if m:
                    return m
            if ended:
                break
            time.sleep(0.1)
        raise RuntimeError(f"{pattern!r} never appeared; the process printed:\n" + "\n".join(self.lines[-40:]))

    def stop(self):
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()


def lti_run(cwd, ports):
    """`lcrl run --config configs/lti-paper.toml` (a budget long enough to
    outlast the block); the block's PORT is its learner's."""
    bg = Background(["target/debug/lcrl", "run", "--config", "configs/lti-paper.toml", "--episodes", "1000000"], cwd)
    m = bg.wait_for(r"learner at https?://[\d.]+:(\d+)")
    ports["PORT"] = int(m.group(1))
    # The commands `lcrl run` prints to paste are part of what it promises.
    bg.wait_for(r"lcrl status ")
    i = next(k for k, line in enumerate(bg.lines) if line.startswith("query it"))
    printed = [line.strip() for line in bg.lines[i + 1:i + 3]]
    return bg, printed


def learner(cwd, ports):
    """A standalone learner, no token, on loopback: what docs/usage.md queries."""
    port = ports.setdefault("50052", free_port())
    bg = Background(["target/debug/lcrl-learner", "--env", "lti-paper", "--algo", "ppo", "--connection", "local",
                     "--listen", f"127.0.0.1:{port}", "--run-dir", "runs/learner"], cwd)
    bg.wait_for(r"listening on")
    return bg, []


def peg_run(cwd, ports):
    """What scripts/run.sh runs, 20 episodes: runs/peg-group1 to export."""
    p = subprocess.run(["target/debug/lcrl", "run", "--config", "configs/peg-group1-ppo-local.toml", "--run-dir", "runs/peg-group1",
                        "--episodes", "20", "--eval-episodes", "5"], cwd=cwd, capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S)
    if p.returncode != 0:
        raise RuntimeError(f"the short peg run failed (exit {p.returncode}):\n{p.stderr[-3000:]}")
    return None, []


FIXTURES = {"lti-run": lti_run, "learner": learner, "peg-run": peg_run}


def run_quick(blocks, verbose):
    failures = 0
    for b in [b for b in blocks if b.kind == "quick"]:
        cwd, ports = scratch_dir(), {"50051": free_port()}
        fixture = b.option("beside") or b.option("after")
        bg, printed = None, []
        t0 = time.monotonic()
        try:
            if fixture:
                bg, printed = FIXTURES[fixture](cwd, ports)
            ok, out = run_block(b, cwd, ports)
            for line in printed:
                ok_p, out_p = run_block(Block(b.path, b.line, "sh", b.mark, line), cwd, ports)
                ok, out = ok and ok_p, out + f"\n--- printed by lcrl run: {line}\n" + out_p
        except Exception as e:  # a fixture that did not start fails the block
            ok, out = False, str(e)
        finally:
            if bg:
                bg.stop()
            shutil.rmtree(cwd, ignore_errors=True)
        print(f"{'ok  ' if ok else 'FAIL'} {b.where} ({b.mark}, {time.monotonic() - t0:.0f} s)", flush=True)
        if not ok or verbose:
            print(out, flush=True)
        failures += not ok
    return failures


def missing_tool(tool):
    """Why a block needing `tool` cannot run here (None: it can)."""
    if tool is None:
        return None
    if not shutil.which(tool):
        return f"{tool} not on PATH"
    if tool == "kubectl" and subprocess.run(["kubectl", "cluster-info"], capture_output=True, timeout=30).returncode != 0:
        return "kubectl reaches no cluster"
    return None


def run_apart(blocks, dry_run):
    """The apart blocks, in the checkout itself, as a user runs them."""
    failures = 0
    for b in [b for b in blocks if b.kind == "apart"]:
        if b.mark.endswith("service"):
            print(f"by hand {b.where} ({b.mark}): runs until stopped; tests/e2e/deploy.rs runs the compose stack", flush=True)
            continue
        missing = missing_tool(b.option("needs"))
        if missing or dry_run:
            print(f"skip {b.where} ({b.mark}){': ' + missing if missing else ''}", flush=True)
            continue
        t0 = time.monotonic()
        ok, out = run_block(b, ROOT, {})
        print(f"{'ok  ' if ok else 'FAIL'} {b.where} ({b.mark}, {time.monotonic() - t0:.0f} s)", flush=True)
        if not ok:
            failures += 1
            print(out, flush=True)
    return failures


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("what", choices=["list", "quick", "apart"])
    ap.add_argument("--file", nargs="+", default=FILES, help="Markdown files (default: README.md docs/usage.md)")
    ap.add_argument("--dry-run", action="store_true", help="apart: list what would run")
    ap.add_argument("--only", nargs="+", metavar="FILE:LINE", help="only these blocks (as `list` names them)")
    ap.add_argument("-v", "--verbose", action="store_true", help="quick: print every block's output, not only a failing one's")
    args = ap.parse_args()
    blocks = [b for f in args.file for b in blocks_of(f)]
    problems = check_marks(blocks)
    for p in problems:
        print(p, file=sys.stderr)
    if args.what == "list":
        for b in blocks:
            runner = {"quick": "tests/e2e/readme.rs", "apart": APART_SCRIPT, "suite": ".ci/run"}.get(b.kind, "NONE")
            print(f"{b.where}\t{b.mark}\t{runner}")
        return 1 if problems else 0
    if problems:
        return 1
    if args.only:
        blocks = [b for b in blocks if b.where in args.only]
        if not blocks:
            print(f"no block at {' '.join(args.only)}; `list` names them", file=sys.stderr)
            return 2
    failures = run_quick(blocks, args.verbose) if args.what == "quick" else run_apart(blocks, args.dry_run)
    if not args.dry_run:
        print(f"{failures} block(s) failed" if failures else "every block that could run here ran as printed")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
