"""Bin mechanical-search pilot benchmark: every selector on K heaps (N objects, primitive fidelity),
then a Markdown table for docs/BENCHMARKS.md; optionally 1 vs 2 workers on a few small heaps.

    .venv/bin/python sims/bench_search.py --heaps 8 --objects 15 --out sims/out/search
    .venv/bin/python sims/bench_search.py --scaling --objects 5 --heaps 4 --out sims/out/search

Results go to <out>/<policy>_N<N>.jsonl (resumable: rerun to finish an interrupted run).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ms_drake.experiments.harness import format_summary, run_bench

POLICIES = ("random", "preempted_random", "preempted_random_push", "largest", "largest_push", "xray", "oracle")


def table(rows) -> str:
    lines = ["| policy | heaps | success % [95 % CI] | actions mean +/- SEM [95 % CI] | quartiles | median wall s / CPU s per rollout | failures |",
             "|---|---|---|---|---|---|---|"]
    for policy, s in rows:
        q = s["quartiles"]
        fails = ", ".join(f"{k} {v}" for k, v in sorted(s["failures"].items())) or "-"
        lines.append(f"| {policy} | {s['rollouts']} | {100 * s['success_rate']:.0f} [{100 * s['success_ci'][0]:.0f}, "
                     f"{100 * s['success_ci'][1]:.0f}] | {s['mean_actions']:.2f} +/- {s['sem_actions']:.2f} "
                     f"[{s['actions_ci'][0]:.2f}, {s['actions_ci'][1]:.2f}] | {q[0]:g} / {q[1]:g} / {q[2]:g} | "
                     f"{s['median_seconds']:.1f} / {s['median_cpu_seconds']:.1f} | {fails} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heaps", type=int, default=10)
    ap.add_argument("--objects", type=int, default=15)
    ap.add_argument("--seed-start", type=int, default=1000)
    ap.add_argument("--policies", nargs="*", default=list(POLICIES))
    ap.add_argument("--horizon", type=int, default=None)
    ap.add_argument("--out", type=Path, default=Path("sims/out/search"))
    ap.add_argument("--scaling", action="store_true", help="time 1 vs 2 workers (largest) instead")
    ap.add_argument("--report", action="store_true", help="only summarize the result files already written")
    args = ap.parse_args(argv)
    if args.scaling:
        walls = {}
        for w in (1, 2):
            out = args.out / f"scaling_w{w}_N{args.objects}.jsonl"
            if out.exists():
                out.unlink()
            t = time.perf_counter()
            run_bench("largest", args.objects, args.heaps, args.seed_start, out, workers=w)
            walls[w] = time.perf_counter() - t
            print(f"workers {w}: {walls[w]:.1f} s for {args.heaps} rollouts (N={args.objects})", flush=True)
        print(f"speed-up 2 vs 1 workers: {walls[1] / walls[2]:.2f}x")
        return
    rows = []
    for p in args.policies:
        f = args.out / f"{p}_N{args.objects}.jsonl"
        if args.report:
            from ms_drake.experiments.harness import (
                final_records,
                read_records,
                summarize,
            )

            recs = final_records(read_records(f))
            if not recs:
                continue
            s = summarize(recs)
        else:
            s = run_bench(p, args.objects, args.heaps, args.seed_start, f, horizon=args.horizon,
                          heap_dir=str(args.out / "heaps"))
        print(format_summary(p, s), flush=True)
        rows.append((p, s))
    print(table(rows))


if __name__ == "__main__":
    main()
