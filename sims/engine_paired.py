"""Does the bin-search selector ranking depend on the heap engine? The same selectors on the same
heap seeds dropped with Drake (SEARCH_HEAPS) and with Bullet (`--heap-engine bullet`).

    .venv/bin/python sims/bench_search.py --heap-engine bullet --objects 15 --heaps 100 --seed-start 1000 \\
        --workers 2 --policies largest preempted_random random largest_push preempted_random_push --out B
    .venv/bin/python sims/engine_paired.py --drake docs/data/grasp_sets_fallback_c1 --bullet B \\
        --heaps 100 --seed-start 1000 --out docs/data/engine_paired.json

Per selector and engine: success and mean actions with bootstrap 95 % intervals, the share solved
within 5 actions; the selectors' rank order by mean actions and by success in each engine
(Kendall's tau between the engines); for every pair of selectors, within each engine, the paired
difference in actions on the heaps both solve (Wilcoxon signed-rank) and in success (sign test),
and whether the two engines agree on its direction.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np
from scipy.stats import kendalltau, wilcoxon

from ms_drake.experiments.harness import (
    final_records,
    paired_comparison,
    read_records,
    result_file,
    summarize,
)

POLICIES = ["random", "preempted_random", "preempted_random_push", "largest", "largest_push"]


def load(folder: Path, policy: str, objects: int, engine: str, seeds: range) -> list[dict]:
    recs = [r for r in final_records(read_records(result_file(folder, policy, objects)))
            if r.get("policy") == policy and r.get("objects") == objects and int(r["seed"]) in seeds
            and r.get("heap_engine", "drake") == engine]
    if not recs:
        raise SystemExit(f"{result_file(folder, policy, objects)}: no {engine}-heap records of {policy} N={objects} "
                         f"on seeds {seeds.start}-{seeds.stop - 1}")
    return recs


def pair_stats(a: list[dict], b: list[dict]) -> dict:
    """Selector a vs b on the same heaps: success sign test and actions on the heaps both solve."""
    s = paired_comparison(a, b)
    ra, rb = ({int(r["seed"]): r for r in x} for x in (a, b))
    both = [k for k in sorted(set(ra) & set(rb)) if ra[k]["success"] and rb[k]["success"]]
    da = np.array([ra[k]["actions"] - rb[k]["actions"] for k in both], float)
    p = float(wilcoxon(da).pvalue) if np.any(da != 0) else 1.0
    return {"only_a": len(s["only_a"]), "only_b": len(s["only_b"]), "success_p": s["p"],
            "both_solved": len(both), "mean_action_difference": float(da.mean()) if len(da) else 0.0,
            "actions_p": p}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drake", type=Path, required=True, help="result folder of the Drake-heap runs")
    ap.add_argument("--bullet", type=Path, required=True, help="result folder of the Bullet-heap runs")
    ap.add_argument("--objects", type=int, default=15)
    ap.add_argument("--heaps", type=int, default=100)
    ap.add_argument("--seed-start", type=int, default=1000)
    ap.add_argument("--policies", nargs="+", default=POLICIES)
    ap.add_argument("--out", type=Path, default=None, help="JSON summary")
    args = ap.parse_args(argv)
    seeds = range(args.seed_start, args.seed_start + args.heaps)
    recs = {e: {p: load(d, p, args.objects, e, seeds) for p in args.policies}
            for e, d in (("drake", args.drake), ("bullet", args.bullet))}
    common = set(seeds)
    for e in recs:
        for p in args.policies:
            common &= {int(r["seed"]) for r in recs[e][p]}
    recs = {e: {p: [r for r in rs if int(r["seed"]) in common] for p, rs in by.items()} for e, by in recs.items()}
    out = {"heaps": len(common), "objects": args.objects, "selectors": {}, "rank": {}, "pairs": {}}
    print(f"{len(common)} heaps (seeds in both engines' runs of every selector)\n")
    print("| selector | success Drake | success Bullet | mean actions Drake | mean actions Bullet | within 5 Drake / Bullet |")
    print("|---|---|---|---|---|---|")
    for p in args.policies:
        row = {}
        for e in ("drake", "bullet"):
            s = summarize(recs[e][p])
            w5 = float(np.mean([r["success"] and r["actions"] <= 5 for r in recs[e][p]]))
            row[e] = {"success": s["success_rate"], "success_ci": s["success_ci"], "mean_actions": s["mean_actions"],
                      "actions_ci": s["actions_ci"], "within_5": w5, "failures": s["failures"]}
        out["selectors"][p] = row
        d, b = row["drake"], row["bullet"]
        print(f"| {p} | {100 * d['success']:.0f} % [{100 * d['success_ci'][0]:.0f}, {100 * d['success_ci'][1]:.0f}] "
              f"| {100 * b['success']:.0f} % [{100 * b['success_ci'][0]:.0f}, {100 * b['success_ci'][1]:.0f}] "
              f"| {d['mean_actions']:.2f} [{d['actions_ci'][0]:.2f}, {d['actions_ci'][1]:.2f}] "
              f"| {b['mean_actions']:.2f} [{b['actions_ci'][0]:.2f}, {b['actions_ci'][1]:.2f}] "
              f"| {100 * d['within_5']:.0f} / {100 * b['within_5']:.0f} % |")
    for key in ("mean_actions", "success"):
        vals = {e: [out["selectors"][p][e][key] for p in args.policies] for e in ("drake", "bullet")}
        order = {e: [p for _, p in sorted(zip(v, args.policies), reverse=key == "success")] for e, v in vals.items()}
        tau = kendalltau(vals["drake"], vals["bullet"])
        out["rank"][key] = {"drake": order["drake"], "bullet": order["bullet"], "kendall_tau": float(tau.statistic),
                            "p": float(tau.pvalue)}
        print(f"\nby {key} (best first): Drake {' > '.join(order['drake'])}\n{'':>{len(key) + 4}}Bullet {' > '.join(order['bullet'])}"
              f"\n  Kendall tau {tau.statistic:.2f} (p = {tau.pvalue:.3f})")
    print("\n| pair (a vs b) | engine | a only / b only solved (sign test p) | mean actions a - b on both solved (Wilcoxon p) |")
    print("|---|---|---|---|")
    agree = 0
    for a, b in itertools.combinations(args.policies, 2):
        st = {e: pair_stats(recs[e][a], recs[e][b]) for e in ("drake", "bullet")}
        same = np.sign(st["drake"]["mean_action_difference"]) == np.sign(st["bullet"]["mean_action_difference"])
        agree += bool(same)
        out["pairs"][f"{a} vs {b}"] = {**st, "actions_direction_agrees": bool(same)}
        for e in ("drake", "bullet"):
            x = st[e]
            print(f"| {a} vs {b} | {e} | {x['only_a']} / {x['only_b']} (p = {x['success_p']:.3f}) "
                  f"| {x['mean_action_difference']:+.2f} on {x['both_solved']} (p = {x['actions_p']:.3g}) |")
    n_pairs = len(out["pairs"])
    out["pairs_direction_agree"] = agree
    print(f"\nthe engines agree on the direction of the actions difference for {agree} of {n_pairs} selector pairs")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))
        print(f"summary in {args.out}")


if __name__ == "__main__":
    main()
