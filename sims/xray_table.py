"""Table 8.2 from the result files of several policies, on the heaps all of them searched.

    .venv/bin/python sims/xray_table.py docs/data/xray82_xray.jsonl docs/data/xray82_largest.jsonl \
        docs/data/xray82_preempted_random.jsonl --out docs/img/xray82

One argument per policy; `a.jsonl,b.jsonl` pools the records of several files of one policy (e.g.
two seed ranges; a seed in both keeps the record of the file given first).

Per policy (ms_drake.experiments.harness.summarize): success with its bootstrap 95 % interval,
action quartiles over successes, failures, where the failed grasps went (harness.failed_grasps;
`--by-object K`: the K object models with the most failed grasps); the paired sign test of every pair
(harness.paired_comparison, with the paired bootstrap interval of the difference) and, on the heaps both solve, a sign test on who needed fewer
actions; the seen fraction of the target at the start splits the heaps
(heap.visible_ratios, from --heap-dir: the heap files of the records' protocol) when given; the
Fig. 8.6 histogram and the cumulative successes (harness.plot) of the common heaps into --out.
"""

import argparse
import itertools
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from ms_drake.experiments.harness import (
    OPTION_DEFAULTS,
    failed_grasps,
    final_records,
    format_summary,
    paired_comparison,
    plot,
    summarize,
)
from ms_drake.errors import MsDrakeError
from ms_drake.experiments.records import RECORD_FIELDS, read_record_file
from ms_drake.scenes.heaps import load_heap


def pooled_records(spec: str) -> list[dict]:
    """The final records of FILE[,FILE...] (one policy and one set of search options), a seed once
    (the first file's record wins)."""
    out: dict[int, dict] = {}
    kinds = {}
    for f in spec.split(","):
        for r in final_records(read_record_file(f, RECORD_FIELDS["bench search"], "bench search")):
            if r.get("failure") != "worker_died":
                out.setdefault(int(r["seed"]), r)
                kind = (r["policy"], r.get("protocol", ""), r.get("horizon"),
                        *(r.get(k, d) for k, d in OPTION_DEFAULTS))
                kinds.setdefault(kind, f)
    if len(kinds) > 1:
        (a, fa), (b, fb) = list(kinds.items())[:2]
        names = ("policy", "protocol", "horizon", *(k for k, _ in OPTION_DEFAULTS))
        diff = ", ".join(f"{n} {x!r} ({fa}) vs {y!r} ({fb})" for n, x, y in zip(names, a, b) if x != y)
        raise SystemExit(f"{spec}: pooled records differ in {diff}; pool the files of one policy and one set of options")
    return list(out.values())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("files", nargs="+", help="one per policy: FILE or FILE,FILE,... (pooled)")
    ap.add_argument("--out", type=Path, default=None, help="folder for the histogram PNGs")
    ap.add_argument("--heap-dir", type=Path, default=None, help="cached heaps: split by the target's start")
    ap.add_argument("--by-object", type=int, default=0, metavar="K",
                    help="also print the K object models with the most failed grasps (failed / grasps)")
    args = ap.parse_args()
    recs = {f: pooled_records(f) for f in args.files}
    common = set.intersection(*({int(r["seed"]) for r in rs} for rs in recs.values()))
    print(f"{len(common)} heaps in every file (seeds {min(common)}-{max(common)})" if common else "no common heaps")
    if not common:
        return
    recs = {f: sorted((r for r in rs if int(r["seed"]) in common), key=lambda r: r["seed"]) for f, rs in recs.items()}
    for f, rs in recs.items():
        print(format_summary(rs[0]["policy"], summarize(rs)))
        fg = failed_grasps(rs)
        if fg["rollouts"]:  # records that name each grasp's object
            print(f"  failed grasps: {fg['failed']} of {fg['grasps']} ({fg['failed_on_target']} on the target, "
                  f"{fg['failed_retries']} right after a failure on the same object; by quality "
                  f"{fg['failed_by_quality']}) in {fg['rollouts']} rollouts")
            if args.by_object:
                print("  failed / grasps by object: " + ", ".join(
                    f"{k} {v[1]}/{v[0]}" for k, v in list(fg["by_object"].items())[:args.by_object]))
        within = {k: np.mean([r["success"] and r["actions"] <= k for r in rs]) for k in (1, 2, 3, 5)}
        print("  success within k actions: " + ", ".join(f"k = {k}: {100 * v:.1f} %" for k, v in within.items()))
    for fa, fb in itertools.combinations(args.files, 2):
        c = paired_comparison(recs[fa], recs[fb], (str(fa), str(fb)))
        print(f"{recs[fa][0]['policy']} vs {recs[fb][0]['policy']}: only A {len(c['only_a'])}, only B "
              f"{len(c['only_b'])}, both {c['both']}, neither {c['neither']}; sign test p = {c['p']:.3g}; "
              f"difference {c['diff']:.1f} points, bootstrap 95 % [{c['diff_ci'][0]:.1f}, {c['diff_ci'][1]:.1f}]")
        # actions on the heaps both solve: who needed fewer (sign test on the heaps that differ)
        a = {int(r["seed"]): int(r["actions"]) for r in recs[fa] if r["success"]}
        b = {int(r["seed"]): int(r["actions"]) for r in recs[fb] if r["success"]}
        both = sorted(set(a) & set(b))
        fewer_a = sum(1 for k in both if a[k] < b[k])
        fewer_b = sum(1 for k in both if b[k] < a[k])
        p_act = float(binomtest(fewer_a, fewer_a + fewer_b, 0.5).pvalue) if fewer_a + fewer_b else 1.0
        print(f"  actions on the {len(both)} heaps both solve: mean {np.mean([a[k] for k in both]):.2f} vs "
              f"{np.mean([b[k] for k in both]):.2f}; fewer: A on {fewer_a}, B on {fewer_b} (sign test p = {p_act:.3g})")
    if args.heap_dir is not None:
        seen = {}
        for k in common:
            first = recs[args.files[0]][0]
            h = load_heap(args.heap_dir / f"heap_{first.get('protocol', 'xray')}_N{first['objects']}_s{k}.json")
            seen[k] = h.visible_ratios[h.target_index]
        v = np.array(list(seen.values()))
        print(f"target seen fraction at the start: 0 in {(v == 0).sum()}, < 0.1 in {(v < 0.1).sum()}, "
              f"median {np.median(v):.2f}")
        for lo, hi, name in ((0, 1e-9, "hidden"), (1e-9, 0.1, "seen < 10 %"), (0.1, 1.01, "seen >= 10 %")):
            parts = []
            for f, rs in recs.items():
                sel = [r for r in rs if lo <= seen[int(r["seed"])] < hi]
                if sel:
                    parts.append(f"{rs[0]['policy']} {100 * np.mean([r['success'] for r in sel]):.0f} %")
            n = sum(1 for k in common if lo <= seen[k] < hi)
            print(f"  {name}: {n} heaps; " + ", ".join(parts))
    if args.out is not None:
        policies = [rs[0]["policy"] for rs in recs.values()]
        if len(set(policies)) < len(policies):  # harness.plot groups the records by policy
            raise SystemExit(f"--out: several files hold the same policy ({', '.join(policies)}); the figures "
                             "group records by policy, so draw each setting's files in a run of their own")
        with tempfile.TemporaryDirectory() as tmp:
            files = []
            for f, rs in recs.items():
                p = Path(tmp) / Path(f.split(",")[0]).name
                p.write_text("".join(json.dumps(r) + "\n" for r in rs))
                files.append(p)
            for p in plot(files, args.out):
                print(f"wrote {p}")


if __name__ == "__main__":
    try:
        main()
    except MsDrakeError as e:  # a result file that cannot be read: one line, no traceback
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
