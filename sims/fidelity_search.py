"""Whole searches at full fidelity (the YuMi station) on the heaps of `ms-drake bench fidelity`,
against that run's primitive searches with the YuMi's reach on the same heaps (issue #15: "the
search success in both").

One JSON line per heap (resumable: heaps already in --out are skipped); --report compares them
with the `kind: heap` rows of a `bench fidelity` file (its primitive search on the same heap, with
the reach it was run with).

    .venv/bin/python sims/fidelity_search.py --heaps 50 --seed-start 5000 --objects 10 --heap-dir HEAPS10 \
        --workers 2 --out docs/data/fidelity_search_full_grip_N10.jsonl
    .venv/bin/python sims/fidelity_search.py --report --out docs/data/fidelity_search_full_grip_N10.jsonl \
        --fidelity docs/data/fidelity_grip_N10.jsonl
"""

from __future__ import annotations

import argparse
import collections
import json
import os
from pathlib import Path

import numpy as np
from scipy.stats import binomtest
from tqdm import tqdm

from ms_drake.experiments.harness import cached_heap, read_records
from ms_drake.experiments.rollout import rollout
from ms_drake.parallel import run_jobs
from ms_drake.policies.bin_selectors import check_policy


def search_job(job: tuple) -> dict:
    """(policy, objects, seed, heap_dir, reach, scenario) -> the full-fidelity rollout's record."""
    policy, objects, seed, heap_dir, reach, scenario = job
    heap = cached_heap(objects, seed, heap_dir)
    rec = rollout(policy, objects, seed, fidelity="full", heap=heap, grasp_planner="indexed", reach=reach,
                  scenario_name=scenario).record()
    rec.update(reach=reach, scenario=scenario, pid=os.getpid())
    return rec


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    p, d = k / n, 1 + z * z / n
    c, h = (p + z * z / (2 * n)) / d, z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return 100 * (c - h), 100 * (c + h)


def report(out: Path, fidelity: Path) -> str:
    full = {int(r["seed"]): r for r in read_records(out)}
    prim = {int(r["seed"]): r for r in read_records(fidelity) if r.get("kind") == "heap"}
    seeds = sorted(set(full) & set(prim))
    if not seeds:
        raise SystemExit(f"no heap of {out} is in {fidelity}: run both on the same seeds and heaps")
    fs = np.array([bool(full[s]["success"]) for s in seeds])
    ps = np.array([bool(prim[s]["primitive_success"]) for s in seeds])
    n, fo, po = len(seeds), int((fs & ~ps).sum()), int((~fs & ps).sum())
    both = [s for s in seeds if full[s]["success"] and prim[s]["primitive_success"]]
    fa = np.array([full[s]["actions"] for s in both])
    pa = np.array([prim[s]["primitive_actions"] for s in both])
    grasps = sum(full[s]["action_kinds"].count("grasp") for s in seeds)
    cpu = np.array([full[s]["cpu_seconds"] for s in seeds])
    acts = sum(full[s]["actions"] for s in seeds)
    lo, hi = wilson(int(fs.sum()), n)
    plo, phi = wilson(int(ps.sum()), n)
    p_sign = binomtest(fo, fo + po).pvalue if fo + po else 1.0
    lines = [
        f"heaps {n} (seeds {seeds[0]}-{seeds[-1]}), policy {full[seeds[0]]['policy']}, full fidelity on "
        f"{full[seeds[0]].get('scenario') or 'YuMiBin'} (reach {full[seeds[0]].get('reach', '')!r}), primitive with "
        f"reach {prim[seeds[0]].get('reach', '')!r}",
        f"search success: full {int(fs.sum())}/{n} ({100 * fs.mean():.0f} % [{lo:.0f}, {hi:.0f}]), "
        f"primitive {int(ps.sum())}/{n} ({100 * ps.mean():.0f} % [{plo:.0f}, {phi:.0f}])",
        f"same outcome on {int((fs == ps).sum())}/{n} heaps; full only {fo}, primitive only {po} (sign test p = {p_sign:.2f})",
        f"on the {len(both)} heaps both solve: mean actions full {fa.mean():.2f}, primitive {pa.mean():.2f}; "
        f"the same count on {int((fa == pa).sum())}",
        f"grasps that lifted their object: full {sum(full[s]['grasp_successes'] for s in seeds)}/{grasps}, "
        f"primitive {sum(prim[s]['primitive_lifts'] for s in seeds)}/{sum(prim[s]['primitive_grasps'] for s in seeds)}",
        f"failures: full {dict(collections.Counter(full[s]['failure'] for s in seeds if not full[s]['success']))}, "
        f"primitive {dict(collections.Counter(prim[s]['primitive_failure'] for s in seeds if not prim[s]['primitive_success']))}",
        f"full CPU-s per search: median {np.median(cpu):.1f}, mean {cpu.mean():.1f}; {cpu.sum() / max(acts, 1):.1f} per "
        f"action, {sum(full[s]['sim_seconds'] for s in seeds) / max(acts, 1):.2f} simulated s per action",
        "heaps with different outcomes: " + ", ".join(
            f"{s} ({'full' if full[s]['success'] else 'primitive'} only; "
            f"{full[s]['failure'] or prim[s]['primitive_failure']})" for s in seeds if fs[seeds.index(s)] != ps[seeds.index(s)]),
    ]
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heaps", type=int, default=50)
    ap.add_argument("--seed-start", type=int, default=5000)
    ap.add_argument("--objects", type=int, default=10)
    ap.add_argument("--policy", default="largest")
    ap.add_argument("--heap-dir", type=Path, default=None, help="cached heaps (the bench fidelity run's)")
    ap.add_argument("--reach", default="robot", help="SearchParams.reach of the full search (default: its own robot)")
    ap.add_argument("--scenario", default="YuMiBin", help="the full-fidelity station")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out", type=Path, required=True, help="JSON lines, one per heap")
    ap.add_argument("--report", action="store_true", help="only compare --out with --fidelity")
    ap.add_argument("--fidelity", type=Path, help="a bench fidelity file (its kind: heap rows)")
    a = ap.parse_args()
    if a.out.suffix != ".jsonl":
        raise SystemExit(f"--out {a.out}: give a .jsonl file")
    if a.report:
        if a.fidelity is None:
            raise SystemExit("--report needs --fidelity FILE (a bench fidelity run on the same heaps)")
        print(report(a.out, a.fidelity))
        return
    check_policy(a.policy)
    done = {int(r["seed"]) for r in read_records(a.out)} if a.out.exists() else set()
    jobs = [(a.policy, a.objects, s, str(a.heap_dir) if a.heap_dir else None, a.reach, a.scenario)
            for s in range(a.seed_start, a.seed_start + a.heaps) if s not in done]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "a") as f, tqdm(total=len(jobs), desc="full searches", unit="heap") as bar:
        for r in run_jobs(search_job, jobs, workers=a.workers):
            if r.ok:
                f.write(json.dumps(r.value) + "\n")
                f.flush()
            else:
                tqdm.write(f"seed {r.job[2]}: {r.error.strip().splitlines()[-1] if r.error else 'failed'} (rerun to retry)")
            bar.update(1)


if __name__ == "__main__":
    main()
