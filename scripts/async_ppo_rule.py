#!/usr/bin/env python3
"""The asynchronous PPO parity rule (docs/research/2026-12-05-async-ppo-design.md),
read from the runs of `MAX_STALENESS=1 bash scripts/parity.sh PRESET 5 1 2 4`:
per preset and actor count, the paired difference per seed (lcrl run minus
lcrl train, eval return), its one-sided 95% lower bound (t, 4 df) against
-0.30, and failed training episodes within +2 of lcrl train's.

    python3 scripts/async_ppo_rule.py [DIR]   (default results/async-ppo; or runs/parity)
"""
import csv, json, pathlib, statistics, sys
ROOT = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "results/async-ppo")
T95_4 = 2.131847  # one-sided 95%, 4 df
out = []
ok_all = True
for preset in ["peg-group1-ppo-local", "peg-group2-ppo-local"]:
    base = ROOT / f"{preset}-lag1"
    def load(loop, seed):
        p = base / loop / f"seed{seed}" / "summary.json"
        s = json.loads(p.read_text())
        m = p.parent / "metrics.csv" if (p.parent / "metrics.csv").is_file() else p.parent / "learner" / "metrics.csv"
        rows = list(csv.DictReader(open(m)))
        failed = sum(r["success"] == "false" for r in rows)
        bc = next((r["mean_return"] for r in s.get("references", []) if r["controller"] == "best constant"), None)
        a0 = next((r["mean_return"] for r in s.get("references", []) if r["controller"].startswith("a = 0")), None)
        svc = s.get("service") or {}
        return s["eval_return"], failed, bc, a0, s.get("total_seconds"), s.get("discarded_stale", svc.get("discarded_stale")), s.get("env_steps")
    for actors in (1, 2, 4):
        diffs, fails_ok, rows = [], True, []
        for seed in range(5):
            tr = load("train", seed); rn = load(f"run{actors}", seed)
            d = rn[0] - tr[0]; diffs.append(d)
            if rn[1] > tr[1] + 2: fails_ok = False
            rows.append(f"{seed}: {rn[0]:.3f} − {tr[0]:.3f} = {d:+.3f} (failed {rn[1]} vs {tr[1]}; best constant {tr[2]:.3f}, a = 0 {tr[3]:.3f}; wall {rn[4]:.0f} s vs {tr[4]:.0f} s; discarded {rn[5]} of {rn[6]} stored)")
        m = statistics.fmean(diffs); sd = statistics.stdev(diffs); lb = m - T95_4 * sd / 5 ** 0.5
        passed = lb > -0.30 and fails_ok
        ok_all &= passed
        out.append(f"### {preset}, {actors} actor(s)\nmean paired difference {m:+.3f}, one-sided 95% lower bound {lb:+.3f} (sd {sd:.3f}); failures within +2: {fails_ok}; cell {'passes' if passed else 'FAILS'}\n" + "\n".join("- " + r for r in rows))
print("\n\n".join(out))
print("\nRULE:", "every cell passes: the default becomes max_staleness = 1" if ok_all else "a cell fails: the default stays 0")
