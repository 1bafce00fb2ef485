"""What learned perception costs in the bin search: rollouts of one policy with learned perception
(B) against ground-truth perception (A) on the same heaps (the seeds both files hold).

    .venv/bin/python sims/perception_costs.py A.jsonl B.jsonl [--seed 0]

Prints, on the common seeds: success and mean actions of each, the paired differences B - A with
bootstrap 95 % intervals (2,000 resamples of the heaps, seeded), the heaps only one solves and the
exact sign test (ms-drake bench paired), and B's failure modes.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ms_drake.experiments.harness import final_records, paired_comparison, read_records


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("a", type=Path)
    ap.add_argument("b", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    ra = {int(r["seed"]): r for r in final_records(read_records(args.a))}
    rb = {int(r["seed"]): r for r in final_records(read_records(args.b))}
    seeds = sorted(set(ra) & set(rb))
    if not seeds:
        raise SystemExit(f"{args.a} and {args.b} share no seed")
    sa = np.array([bool(ra[k]["success"]) for k in seeds], float)
    sb = np.array([bool(rb[k]["success"]) for k in seeds], float)
    na = np.array([int(ra[k]["actions"]) for k in seeds], float)
    nb = np.array([int(rb[k]["actions"]) for k in seeds], float)
    both = (sa > 0) & (sb > 0)
    rng = np.random.default_rng(args.seed)
    idx = rng.integers(0, len(seeds), size=(2000, len(seeds)))

    def ci(x):
        v = x[idx].mean(axis=1)
        return float(np.percentile(v, 2.5)), float(np.percentile(v, 97.5))

    ds, dn = sb - sa, nb - na
    bi = np.flatnonzero(both)
    dn_both = (nb - na)[bi]
    idx_b = rng.integers(0, max(len(bi), 1), size=(2000, len(bi))) if len(bi) else None
    p = paired_comparison([ra[k] for k in seeds], [rb[k] for k in seeds])
    fails: dict[str, int] = {}
    for k in seeds:
        if not rb[k]["success"]:
            fails[rb[k].get("failure", "?")] = fails.get(rb[k].get("failure", "?"), 0) + 1
    out = dict(heaps=len(seeds), seeds=[seeds[0], seeds[-1]],
               a=dict(file=str(args.a), success=float(sa.mean()), success_ci=ci(sa), actions=float(na.mean())),
               b=dict(file=str(args.b), success=float(sb.mean()), success_ci=ci(sb), actions=float(nb.mean()),
                      failures=fails),
               success_diff=float(ds.mean()), success_diff_ci=ci(ds),
               actions_diff=float(dn.mean()), actions_diff_ci=ci(dn),
               heaps_both_solve=int(len(bi)),
               actions_diff_both=float(dn_both.mean()) if len(bi) else float("nan"),
               actions_diff_both_ci=(float(np.percentile(dn_both[idx_b].mean(axis=1), 2.5)),
                                     float(np.percentile(dn_both[idx_b].mean(axis=1), 97.5))) if len(bi) else None,
               only_a=len(p["only_a"]), only_b=len(p["only_b"]), sign_test_p=p["p"])
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
