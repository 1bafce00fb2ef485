"""What each push policy's push does to the objects, and what that buys in grasp quality.

Re-executes the five policies from the stored states of the first N improvable heaps of a data
step's folder (`policies_from_state`, the sampling and transfer speed the heaps were recorded with)
and records, with the gains, how far the pushed object moved and turned (`motion_of`):

    .venv/bin/python sims/push_motion.py DIR --heaps 60 [--seed-start S] --out FILE.jsonl [--workers K]

then prints per policy the share of pushes that change the pushed object's tilt by more than 20 degrees (it
tips over or rolls) and the mean overall gain of the pushes that do and do not. Resumable (FILE
keeps one line per heap).
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ms_drake.experiments.push_study import (
    _append,
    improvable_records,
    read_jsonl,
    recorded_params,
    state_job,
)
from ms_drake.parallel import run_jobs
from ms_drake.pushing import POLICIES

TURNED = 20.0  # degrees: the pushed object tipped over or rolled


def summarize(rows: list[dict]) -> dict:
    out = {}
    for p in POLICIES:
        pushes = [r["policies"][p] for r in rows if r["policies"][p].get("pushed") and "pushed_tilt_deg" in r["policies"][p]]
        turned = [x for x in pushes if x["pushed_tilt_deg"] > TURNED]
        slid = [x for x in pushes if x["pushed_tilt_deg"] <= TURNED]
        mean = lambda xs, k: float(np.mean([x[k] for x in xs])) if xs else float("nan")  # noqa: E731
        out[p] = {"heaps": len(rows), "pushes": len(pushes), "turned": len(turned),
                  "gain_turned": mean(turned, "overall_gain"), "gain_slid": mean(slid, "overall_gain"),
                  "displacement": mean(pushes, "pushed_displacement"),
                  "tilt_deg_median": float(np.median([x["pushed_tilt_deg"] for x in pushes])) if pushes else 0.0,
                  "gain_all": float(np.mean([r["policies"][p].get("overall_gain", 0.0) for r in rows])) if rows else 0.0}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", type=Path)
    ap.add_argument("--heaps", type=int, default=60)
    ap.add_argument("--seed-start", type=int, default=0, help="the first N improvable heaps with seed >= S")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    done = {int(r["seed"]) for r in read_jsonl(a.out)}
    todo = [h for h in improvable_records(a.dir, a.heaps, a.seed_start) if int(h["seed"]) not in done]
    jobs = [(h, POLICIES, asdict(recorded_params(h))) for h in todo]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    for r in run_jobs(state_job, jobs, workers=a.workers):
        if r.ok:
            rec = {"seed": int(r.job[0]["seed"]), "objects": r.job[0]["objects"], **r.value}
            _append(a.out, rec)
            print(f"seed {rec['seed']}: " + ", ".join(
                f"{p} {v.get('overall_gain', 0):+.2f}/{v.get('pushed_tilt_deg', 0):.0f}deg" for p, v in rec["policies"].items()),
                flush=True)
    rows = sorted((r for r in read_jsonl(a.out) if r["seed"] >= a.seed_start), key=lambda r: r["seed"])[: a.heaps]
    s = summarize(rows)
    print(f"\n{len(rows)} heaps; per policy: pushes, turned > {TURNED:.0f} deg, mean overall gain turned / not, all heaps")
    for p, v in s.items():
        print(f"{p:18s} {v['pushes']:4d} pushes, {v['turned']:4d} turned ({100 * v['turned'] / max(1, v['pushes']):4.0f} %), "
              f"gain {v['gain_turned']:+.3f} / {v['gain_slid']:+.3f}, displacement {100 * v['displacement']:.1f} cm, "
              f"median tilt change {v['tilt_deg_median']:.0f} deg; all heaps {v['gain_all']:+.3f}")
    if a.json:
        a.json.write_text(json.dumps(s, indent=1))
    return s


if __name__ == "__main__":
    main()
