"""Bin mechanical-search benchmark: selectors x heaps (primitive fidelity) -> JSON lines -> tables.

One pool of --workers processes runs every missing (policy, N, seed) rollout; the workers generate
the heaps themselves (cached in <out>/heaps, each once, shared by every selector). Results go to
<out>/<policy>_N<N>.jsonl (budget 2N) or <out>/<policy>_N<N>_H<H>.jsonl (--horizon H); rerun the
same command to resume a killed run (finished rollouts are kept, the ones in flight are redone).

    # Table C.1 (Ch. 7 selectors, N = 15, budget 2N)
    .venv/bin/python sims/bench_search.py --objects 15 --heaps 200 --seed-start 1000 --workers 2 \
        --policies random preempted_random preempted_random_push largest largest_push --out sims/out/tables
    # Table 8.2 (H = 10): X-Ray and the oracle; Random (= preempted_random) and Largest come from
    # the 2N runs above, truncated at 10 actions (harness.truncate_record)
    .venv/bin/python sims/bench_search.py --objects 15 --heaps 200 --seed-start 1000 --workers 2 \
        --policies xray oracle --horizon 10 --out sims/out/tables
    # Fig. 7.4 A (heap size): the same at N = 10 and 20
    .venv/bin/python sims/bench_search.py --objects 10 20 --heaps 200 --seed-start 1000 --workers 2 \
        --policies largest --out sims/out/tables
    # the tables
    .venv/bin/python sims/bench_search.py --report --objects 15 --out sims/out/tables
    .venv/bin/python sims/bench_search.py --report --objects 15 --horizon 10 \
        --policies preempted_random largest xray oracle --out sims/out/tables
    .venv/bin/python sims/bench_search.py --report --objects 10 15 20 --policies largest --out sims/out/tables
    # 1 vs 2 workers on 4 small heaps (heap generation included), with the load average
    .venv/bin/python sims/bench_search.py --scaling --objects 5 --heaps 4 --seed-start 2000 --out sims/out/tables
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

from ms_drake.experiments.harness import (
    HEAP_ENGINES,
    action_breakdown,
    failure_classes,
    final_records,
    format_summary,
    read_records,
    result_file,
    run_suite,
    summarize,
    truncate_record,
)
from ms_drake.policies.bin_search import GRASP_PLANNERS

POLICIES = ("random", "preempted_random", "preempted_random_push", "largest", "largest_push", "xray", "oracle")


def table(rows) -> str:
    lines = ["| policy | N | H | heaps | success % [95 % CI] | actions mean +/- SEM [95 % CI] (all) | quartiles (all) | "
             "quartiles (successes) | median wall s / CPU s per rollout | failures |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for policy, n, h, s in rows:
        q = s["quartiles"]
        fails = ", ".join(f"{k} {v}" for k, v in sorted(s["failures"].items())) or "-"
        lines.append(f"| {policy} | {n} | {h} | {s['rollouts']} | {100 * s['success_rate']:.0f} "
                     f"[{100 * s['success_ci'][0]:.0f}, {100 * s['success_ci'][1]:.0f}] | {s['mean_actions']:.2f} "
                     f"+/- {s['sem_actions']:.2f} [{s['actions_ci'][0]:.2f}, {s['actions_ci'][1]:.2f}] | "
                     f"{q[0]:g} / {q[1]:g} / {q[2]:g} | {' / '.join(f'{x:g}' for x in s['success_quartiles'])} | "
                     f"{s['median_seconds']:.1f} / {s['median_cpu_seconds']:.1f} | "
                     f"{fails} |")
    return "\n".join(lines)


def report_records(out: Path, policy: str, objects: int, horizon: int | None, engine: str = "drake",
                   grasp_planner: str = "indexed"):
    """(records, label of H) of one table row (heaps of `engine`, searched with `grasp_planner`):
    the file run at `horizon`, else (H given) the 2N file truncated at H."""
    def mine(r):
        return (r.get("policy") == policy and r.get("objects") == objects and r.get("heap_engine", "drake") == engine
                and r.get("grasp_planner", "image") == grasp_planner)

    f = result_file(out, policy, objects, horizon)
    recs = [r for r in final_records(read_records(f)) if mine(r)]
    if recs or horizon is None:
        return recs, str(horizon) if horizon is not None else "2N"
    full = [r for r in final_records(read_records(result_file(out, policy, objects))) if mine(r)]
    return [truncate_record(r, horizon) for r in full], f"{horizon} (2N run cut)"


def scaling(args) -> None:
    """1 vs 2 workers on the same rollouts, heap generation included (fresh heap folders)."""
    walls, n = {}, args.objects[0]
    for w in (1, 2):
        d = args.out / f"scaling_w{w}"
        shutil.rmtree(d, ignore_errors=True)
        load0 = os.getloadavg()
        t = time.perf_counter()
        s = run_suite([("largest", n, result_file(d, "largest", n))], args.heaps,
                      args.seed_start, workers=w, heap_dir=str(d / "heaps"))[("largest", n)]
        walls[w] = time.perf_counter() - t
        load1 = os.getloadavg()
        print(f"workers {w}: {walls[w]:.1f} s wall for {args.heaps} heaps + rollouts (N={n}), "
              f"median {s['median_cpu_seconds']:.1f} s CPU per rollout; load average "
              f"{load0[0]:.2f} before, {load1[0]:.2f} after (1-min)", flush=True)
    print(f"speed-up 2 vs 1 workers: {walls[1] / walls[2]:.2f}x")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heaps", type=int, default=10)
    ap.add_argument("--objects", type=int, nargs="+", default=[15])
    ap.add_argument("--seed-start", type=int, default=1000)
    ap.add_argument("--policies", nargs="*", default=list(POLICIES))
    ap.add_argument("--horizon", type=int, default=None, help="action budget H (default 2N)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("sims/out/tables"))
    ap.add_argument("--scaling", action="store_true", help="time 1 vs 2 workers (largest) instead")
    ap.add_argument("--report", action="store_true", help="only summarize the result files already written")
    ap.add_argument("--heap-engine", choices=list(HEAP_ENGINES), default="drake",
                    help="drop physics of the heaps (Bullet: ~4x cheaper per heap); records and cached heaps "
                         "of the two engines stay apart")
    ap.add_argument("--grasp-planner", choices=["", *GRASP_PLANNERS], default="",
                    help="'' = the primitive fidelity's default (indexed: grasp sets + image fallback) | image")
    args = ap.parse_args(argv)
    if args.scaling:
        scaling(args)
        return
    if args.report:
        rows, breakdown = [], []
        for n in args.objects:
            for p in args.policies:
                recs, h = report_records(args.out, p, n, args.horizon, args.heap_engine,
                                          args.grasp_planner or "indexed")
                if recs:
                    rows.append((p, n, h, summarize(recs)))
                    breakdown.append((p, n, action_breakdown(recs), failure_classes(recs)))
        print(table(rows))
        print("\n| policy | N | actions | grasps | pushes (share) | jaw grasps (success) | suction grasps (success) |")
        print("|---|---|---|---|---|---|---|")
        for p, n, b, _ in breakdown:
            jaw, suc = b["parallel_jaw"], b["suction"]
            print(f"| {p} | {n} | {b['actions']} | {b['grasps']} | {b['pushes']} ({100 * b['push_share']:.1f} %) "
                  f"| {jaw['grasps']} ({jaw['success_rate']:.2f}) | {suc['grasps']} ({suc['success_rate']:.2f}) |")
        print("\n| policy | N | failures (share of rollouts) | (1) no action | (2) target removed | (3) horizon | other |")
        print("|---|---|---|---|---|---|---|")
        for p, n, _, f in breakdown:
            cells = " | ".join(f"{f[c]['count']} ({100 * f[c]['share']:.0f} %)" if f["failures"] else "0"
                               for c in ("no_action", "target_removed", "horizon", "other"))
            print(f"| {p} | {n} | {f['failures']} ({100 * f['failure_share']:.1f} %) | {cells} |")
        return
    runs = [(p, n, result_file(args.out, p, n, args.horizon)) for n in args.objects for p in args.policies]
    t0, count = time.perf_counter(), [0]

    def progress(rec):
        count[0] += 1
        print(f"[{time.perf_counter() - t0:7.0f} s] {rec['policy']} N={rec['objects']} seed {rec['seed']}: "
              f"{'success' if rec['success'] else rec['failure']} after {rec['actions']} actions, "
              f"{rec.get('cpu_seconds', 0.0):.1f} s CPU ({count[0]} done)", flush=True)

    summ = run_suite(runs, args.heaps, args.seed_start, workers=args.workers, horizon=args.horizon,
                     heap_dir=str(args.out / "heaps"), progress=progress, heap_engine=args.heap_engine,
                     grasp_planner=args.grasp_planner)
    rows = []
    for (p, n), s in summ.items():
        print(format_summary(f"{p} N={n}", s), flush=True)
        rows.append((p, n, str(args.horizon) if args.horizon is not None else "2N", s))
    print(table(rows))


if __name__ == "__main__":
    main()
