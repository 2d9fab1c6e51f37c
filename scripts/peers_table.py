#!/usr/bin/env python3
"""The peer table of docs/peers.md (design:
docs/research/2026-11-28-peers-design.md): Stable-Baselines3's SAC, TD3
and PPO beside lcrl's DDPG and PPO on the peg presets, every seed, each
policy's final return on the best constant's 100 evaluation starts, the
episodes until the 10-episode training mean reached the best constant,
wall time, and the runs that diverged (final eval below a = 0); the
best constant and a = 0 above each table. Then the exploratory
comparisons the design names (Welch's t on eval return, log-rank on
episodes to the best constant), Holm-adjusted over every p printed.

    .venv/bin/python scripts/peers_table.py --peers results/peers --confirm results/lcrl-confirm > table.md
"""

import argparse
import csv
import json
import math
import pathlib
import statistics

ENVS = ["peg-group1", "peg-group2"]
# (row, where its runs are, algorithm folder, connection folder)
CELLS = [
    ("SB3 SAC", "sb3", "sac", None),
    ("SB3 TD3", "sb3", "td3", None),
    ("lcrl DDPG global", "confirm", "ddpg", "global"),
    ("lcrl DDPG local@1", "confirm", "ddpg", "local@1"),
    ("SB3 PPO", "sb3", "ppo", None),
    ("lcrl PPO global", "lcrl-ppo", "ppo", "global"),
    ("lcrl PPO local@1", "lcrl-ppo", "ppo", "local@1"),
    # docs/research/2026-12-04-peers-ppo-nobase-design.md: from scratch, as SB3 acts.
    ("lcrl PPO global, no base", "lcrl-ppo-nobase", "ppo", "global"),
    # Its follow-up (the same design's last section): SB3's initial σ = 1.
    ("lcrl PPO global, no base, initial σ = 1", "lcrl-ppo-nobase-std1", "ppo", "global"),
]
COMPARISONS = [("SB3 SAC", "lcrl DDPG global"), ("SB3 TD3", "lcrl DDPG global"), ("SB3 PPO", "lcrl PPO global"),
               ("lcrl PPO global, no base", "lcrl PPO global"), ("SB3 PPO", "lcrl PPO global, no base"),
               ("lcrl PPO global, no base, initial σ = 1", "lcrl PPO global, no base"), ("SB3 PPO", "lcrl PPO global, no base, initial σ = 1")]
WINDOW = 10


def episodes_to(bar, returns):
    """First episode at which the mean of the last WINDOW training returns
    reaches `bar` (None: never within the budget)."""
    for k in range(WINDOW, len(returns) + 1):
        if statistics.fmean(returns[k - WINDOW:k]) >= bar:
            return k
    return None


def training_returns(run):
    with open(run / "metrics.csv") as f:
        return [float(row["return"]) for row in csv.DictReader(f)]


def runs_of(root, kind, env, algo, connection):
    """Finished runs of one cell: seed, final eval return, training returns, wall s."""
    if kind == "sb3":
        folders = sorted((root["peers"] / "sb3" / env / algo).glob("seed*"))
    elif kind in ("lcrl-ppo", "lcrl-ppo-nobase", "lcrl-ppo-nobase-std1"):
        folders = sorted((root["peers"] / kind / "runs" / env / algo / connection).glob("seed*"))
    else:
        folders = sorted((root["confirm"] / "runs" / env / algo / connection).glob("seed*"))
    runs = []
    for folder in folders:
        if not (folder / "summary.json").is_file():
            continue
        s = json.loads((folder / "summary.json").read_text())
        # The final policy's return (lcrl also hands over the one its
        # validation selected: `eval_return`; SB3 has no such selection).
        # (last_eval_return is none where no selection ran: the handed
        # policy is the last.)
        final = s["eval_return"] if kind == "sb3" or s.get("last_eval_return") is None else s["last_eval_return"]
        runs.append({"seed": s["seed"], "final": final, "returns": training_returns(folder), "wall_s": s.get("total_seconds"), "episodes": s["episodes"]})
    return sorted(runs, key=lambda r: r["seed"])


def searched_cells(root, env):
    """The rows of the settings search's picks (docs/research/
    2026-12-04-peers-search-design.md): folders sb3/ENV/ALGO-NAME, each
    row placed after its algorithm's default row."""
    found = sorted(d.name for d in (root["peers"] / "sb3" / env).glob("*-*") if d.is_dir())
    return [(f"SB3 {name.split('-')[0].upper()} (searched: {name})", "sb3", name, None) for name in found]


def search_table(root):
    """The search's candidates on their seeds, and each algorithm's pick
    (the highest mean; a tie within 0.05 goes to the earlier candidate)."""
    base = root["peers"] / "sb3-search" / "peg-group1"
    order = ["sac-default", "sac-zoo", "sac-zoo-starts", "td3-default", "td3-noise", "td3-zoo", "td3-zoo-starts",
             # docs/research/2026-12-04-peers-ppo-search-design.md
             "ppo-default", "ppo-zoo", "ppo-zoo-nosde", "ppo-lcrl"]
    rows = []
    for name in order:
        finals = [json.loads((f / "summary.json").read_text()) for f in sorted((base / name).glob("seed*")) if (f / "summary.json").is_file()]
        if finals:
            rows.append((name, finals))
    if not rows:
        return
    print("\n### The settings search (peg-group1, search seeds 300–301; SAC and TD3 200 episodes, PPO 900)\n")
    print("| candidate | settings | every seed | mean | pick |")
    print("|---|---|---|---|---|")
    picks = {}
    for algo in ("sac", "td3", "ppo"):
        best = None
        for name, runs in rows:
            if name.startswith(algo) and len(runs) == 2:
                mean = statistics.fmean(r["eval_return"] for r in runs)
                if best is None or mean > best[1] + 0.05:
                    best = (name, mean)
        if best:
            picks[algo] = best[0]
    for name, runs in rows:
        settings = json.dumps(runs[0]["settings"]) if runs[0]["settings"] else "SB3's defaults"
        every = ", ".join("%d: %.2f" % (r["seed"], r["eval_return"]) for r in runs)
        mean = statistics.fmean(r["eval_return"] for r in runs)
        pick = "**pick**" if picks.get(name.split("-")[0]) == name else ""
        print(f"| {name} | `{settings}` | {every} | {mean:.3f} | {pick} |")


def headroom(env):
    """The headroom reference's return on the same 100 starts: the best
    state-feedback controller a direct search found (references/ENV,
    recomputed by the test suite)."""
    path = pathlib.Path(__file__).resolve().parent.parent / "references" / env / "best_policy.json"
    return json.loads(path.read_text())["mean_return"] if path.is_file() else None


def references(root, env):
    """The best constant's and a = 0's returns on the 100 evaluation starts."""
    for summary in (root["confirm"] / "runs" / env).rglob("summary.json"):
        refs = {r["controller"]: r["mean_return"] for r in json.loads(summary.read_text()).get("references", [])}
        if "best constant" in refs:
            return refs
    raise SystemExit(f"no run of {env} under {root['confirm']} names the best constant")


def _betacf(a, b, x):
    """Continued fraction of the regularized incomplete beta (Numerical Recipes)."""
    qab, qap, qam, c, d = a + b, a + 1, a - 1, 1.0, 1 - (a + b) * x / (a + 1)
    d = 1 / (d if abs(d) > 1e-300 else 1e-300)
    h = d
    for m in range(1, 300):
        m2 = 2 * m
        for aa in (m * (b - m) * x / ((qam + m2) * (a + m2)), -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
            d = 1 + aa * d
            d = 1 / (d if abs(d) > 1e-300 else 1e-300)
            c = 1 + aa / c if abs(1 + aa / c) > 1e-300 else 1e-300
            h *= d * c
        if abs(d * c - 1) < 1e-12:
            break
    return h


def t_two_sided(t, df):
    """P(|T| >= |t|) for Student's t with `df` degrees of freedom."""
    x = df / (df + t * t)
    front = math.exp(math.lgamma((df + 1) / 2) - math.lgamma(df / 2) - math.lgamma(0.5) + (df / 2) * math.log(x) + 0.5 * math.log(1 - x)) if 0 < x < 1 else 0.0
    if x == 0:
        return 0.0
    ibeta = front * _betacf(df / 2, 0.5, x) / (df / 2) if x < (df / 2 + 1) / (df / 2 + 0.5 + 2) else 1 - front * _betacf(0.5, df / 2, 1 - x) / 0.5
    return min(1.0, max(0.0, ibeta))


def t_975(df):
    """Student's t 97.5% quantile (95% intervals), by bisection on t_two_sided."""
    low, high = 0.0, 100.0
    for _ in range(60):
        mid = (low + high) / 2
        low, high = (mid, high) if t_two_sided(mid, df) > 0.05 else (low, mid)
    return (low + high) / 2


def welch(a, b):
    """Mean of a − mean of b, and Welch's two-sided p."""
    va, vb = statistics.variance(a) / len(a), statistics.variance(b) / len(b)
    diff = statistics.fmean(a) - statistics.fmean(b)
    if va + vb == 0:
        return diff, 0.0 if diff else 1.0
    df = (va + vb) ** 2 / (va * va / (len(a) - 1) + vb * vb / (len(b) - 1))
    return diff, t_two_sided(diff / math.sqrt(va + vb), df)


def logrank(a, b):
    """Two-sided log-rank p for times to an event (None: censored at the budget)."""
    events = sorted({t for t in a + b if t is not None})
    observed_minus_expected, variance = 0.0, 0.0
    for t in events:
        at_risk_a = sum(1 for x in a if x is None or x >= t)
        at_risk_b = sum(1 for x in b if x is None or x >= t)
        d_a, d_b = a.count(t), b.count(t)
        n, d = at_risk_a + at_risk_b, d_a + d_b
        if n < 2:
            continue
        observed_minus_expected += d_a - d * at_risk_a / n
        variance += d * (at_risk_a / n) * (at_risk_b / n) * (n - d) / (n - 1)
    if variance == 0:
        return 1.0
    return math.erfc(abs(observed_minus_expected) / math.sqrt(2 * variance))


def holm(ps):
    order = sorted(range(len(ps)), key=lambda k: ps[k])
    adjusted, running = [0.0] * len(ps), 0.0
    for rank, k in enumerate(order):
        running = max(running, min(1.0, (len(ps) - rank) * ps[k]))
        adjusted[k] = running
    return adjusted


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--peers", type=pathlib.Path, default=pathlib.Path("results/peers"), help="the peer study's folder (sb3/, lcrl-ppo/)")
    parser.add_argument("--confirm", type=pathlib.Path, default=pathlib.Path("results/lcrl-confirm"), help="the confirmatory study (lcrl's DDPG cells)")
    args = parser.parse_args()
    root = {"peers": args.peers, "confirm": args.confirm}
    tests = []
    search_table(root)
    for env in ENVS:
        refs = references(root, env)
        bar = refs["best constant"]
        print(f"\n### {env}\n")
        room = headroom(env)
        room_words = f", headroom reference {room:.3f} (references/{env}/best_policy.json)" if room is not None else ""
        print(f"Best constant {bar:.3f}, a = 0 {refs['a = 0']:.3f}{room_words} (the same 100 evaluation starts, seeds 0–99).\n")
        print("| learner | seeds | final eval return, mean [95% CI] | every seed | reached the best constant (10-episode training mean) | episodes to it, median of those that did | wall s, median | diverged (eval below a = 0) |")
        print("|---|---|---|---|---|---|---|---|")
        cells = {}
        searched = searched_cells(root, env)
        rows = []
        for cell in CELLS:
            rows.append(cell)
            rows += [c for c in searched if c[2].split("-")[0] == cell[2] and cell[0].startswith("SB3")]
        for name, kind, algo, connection in rows:
            runs = runs_of(root, kind, env, algo, connection)
            cells[name] = runs
            if not runs:
                print(f"| {name} | 0 | not run yet | | | | | |")
                continue
            finals = [r["final"] for r in runs]
            mean = statistics.fmean(finals)
            half = t_975(len(finals) - 1) * statistics.stdev(finals) / math.sqrt(len(finals)) if len(finals) > 1 else 0.0
            ci = f" [{mean - half:.3f}, {mean + half:.3f}]" if len(finals) > 1 else ""
            reached = [episodes_to(bar, r["returns"]) for r in runs]
            hit = [e for e in reached if e is not None]
            walls = [r["wall_s"] for r in runs if r["wall_s"]]
            every = ", ".join("%d: %.2f" % (r["seed"], r["final"]) for r in runs)
            wall = "%.0f" % statistics.median(walls) if walls else "–"
            to_bar = statistics.median(hit) if hit else "–"
            diverged = sum(1 for f in finals if f < refs["a = 0"])
            print(f"| {name} | {len(runs)} | {mean:.3f}{ci} | {every} | {len(hit)} of {len(runs)} | {to_bar} | {wall} | {diverged} of {len(runs)} |")
        # Each pick beside lcrl's learner of its kind: PPO's beside lcrl's
        # PPO, the off-policy picks beside lcrl's DDPG.
        comparisons = COMPARISONS + [(name, "lcrl PPO global" if algo.startswith("ppo") else "lcrl DDPG global") for name, _, algo, _ in searched]
        for peer, ours in comparisons:
            a, b = cells[peer], cells[ours]
            if len(a) >= 2 and len(b) >= 2:
                diff, p = welch([r["final"] for r in a], [r["final"] for r in b])
                tests.append((env, f"{peer} − {ours}, final eval return", diff, p))
                times = lambda runs: [episodes_to(bar, r["returns"]) for r in runs]  # noqa: E731
                tests.append((env, f"{peer} against {ours}, episodes to the best constant (log-rank)", None, logrank(times(a), times(b))))
    if tests:
        print("\n### Exploratory comparisons (Welch's t; log-rank), Holm over every p below\n")
        print("| preset | comparison | difference | p | Holm p |")
        print("|---|---|---|---|---|")
        for (env, what, diff, p), adjusted in zip(tests, holm([t[3] for t in tests])):
            print(f"| {env} | {what} | {'' if diff is None else f'{diff:+.3f}'} | {p:.3g} | {adjusted:.3g} |")


if __name__ == "__main__":
    main()
