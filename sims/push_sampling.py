"""The push study under two grasp samplings scored on the same states and pushes.

`ms-drake data push-heaps --sampling object --compare-sampling tilt_bin` scores every stuck state and
every push with both samplings (StudyParams.sampling, ms_drake/experiments/push_study.py): the
primary one (which also decides Algorithm 1's stop) and the compare one. This script makes, for each
sampling, the study's table on the heaps that sampling calls improvable (some policy's overall gain
> 0, the reference's rejection step), and the paired difference on the heaps both call improvable:

    .venv/bin/python sims/push_sampling.py DIR [--heaps N] [--json FILE] [--figures DIR]

DIR: the data step's folder (heaps.jsonl). --heaps: the first N improvable heaps (by seed) of each
sampling. --figures: Fig. 4.2 / 4.3 of each sampling (push_policies_fig4_*.png in DIR/<sampling>).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from ms_drake.experiments.push_study import (
    HEAPS_FILE,
    METRICS,
    bench_row,
    format_push_table,
    plot_push,
    read_jsonl,
    summarize_push,
)
from ms_drake.pushing import POLICIES


def rows_of(recs: list[dict], which: str) -> tuple[list[dict], list[int]]:
    """Bench rows of every policy under the primary (`which` = "primary") or the compare metric,
    on the heaps that metric calls improvable; and those heaps' seeds."""
    rows, seeds = [], []
    for h in recs:
        if "policies" not in h or (which == "compare" and "compare" not in h):
            continue
        res = {p: (h["policies"][p] if which == "primary" else dict(h["policies"][p], **h["policies"][p]["compare"]))
               for p in POLICIES}
        if not any(r.get("overall_gain", 0.0) > 1e-9 for r in res.values()):
            continue
        seeds.append(int(h["seed"]))
        for p in POLICIES:
            rows.append(bench_row(h, p, res[p], which))
    return rows, seeds


def when_pushed(rows: list[dict]) -> dict:
    """Each structured policy against quasi-random on the heaps where it found a push: mean overall
    gains on those heaps and a two-sided sign test of the paired gains."""
    by = {}
    for r in rows:
        by.setdefault(r["policy"], {})[int(r["seed"])] = r
    out = {}
    for pol in POLICIES[1:]:
        seeds = [s for s, r in by.get(pol, {}).items() if r["pushed"] and s in by.get("quasi_random", {})]
        if not seeds:
            continue
        g = np.array([by[pol][s]["overall_gain"] for s in seeds])
        q = np.array([by["quasi_random"][s]["overall_gain"] for s in seeds])
        better, worse = int(np.sum(g > q + 1e-9)), int(np.sum(g < q - 1e-9))
        pv = float(binomtest(better, better + worse).pvalue) if better + worse else 1.0
        out[pol] = {"heaps": len(seeds), "gain": float(g.mean()), "quasi_random": float(q.mean()),
                    "better": better, "worse": worse, "p": pv}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", type=Path)
    ap.add_argument("--heaps", type=int, default=10**9)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--figures", type=Path)
    a = ap.parse_args(argv)
    recs = sorted(read_jsonl(a.dir / HEAPS_FILE), key=lambda r: int(r["seed"]))
    stuck = [r for r in recs if "policies" in r]
    primary = stuck[0].get("sampling", "tilt_bin") if stuck else "?"
    compare = next((r["compare"]["sampling"] for r in stuck if "compare" in r), "")
    print(f"{len(recs)} heaps dropped (seeds {recs[0]['seed']}-{recs[-1]['seed']}), {len(stuck)} stuck")
    out = {"dropped": len(recs), "stuck": len(stuck), "samplings": {}}
    improvable = {}
    for which, name in (("primary", primary), ("compare", compare)):
        if not name:
            continue
        rows, seeds = rows_of(stuck, which)
        keep = set(seeds[: a.heaps])
        rows = [r for r in rows if int(r["seed"]) in keep]
        improvable[which] = keep
        s = summarize_push(rows)
        out["samplings"][name] = {"role": which, "improvable": len(seeds), "summary": s}
        print(f"\n== sampling {name!r} ({which}: {'decides Algorithm 1' if which == 'primary' else 'same states'}): "
              f"{len(seeds)} of {len(stuck)} stuck heaps improvable")
        print(format_push_table(s))
        out["samplings"][name]["when_pushed"] = when_pushed(rows)
        for pol, v in out["samplings"][name]["when_pushed"].items():
            print(f"  where {pol} pushed ({v['heaps']} heaps): {pol} {v['gain']:+.3f}, quasi-random {v['quasi_random']:+.3f} "
                  f"on the same heaps; higher on {v['better']}, lower on {v['worse']} (sign test p = {v['p']:.2g})")
        if a.figures:
            for p in plot_push(s, a.figures / name):
                print("figure", p)
    # The two metrics on the same stuck states, every policy (no improvable filter): what the draw
    # alone adds to a gain.
    if compare:
        print("\n== both metrics on every stuck state (no filter): mean overall gain, primary / compare")
        both = {}
        for p in POLICIES:
            g1 = np.array([h["policies"][p]["overall_gain"] for h in stuck if "compare" in h])
            g2 = np.array([h["policies"][p]["compare"]["overall_gain"] for h in stuck if "compare" in h])
            moved = np.array([bool(h["policies"][p]["pushed"]) for h in stuck if "compare" in h])
            both[p] = {"n": len(g1), "primary": float(g1.mean()), "compare": float(g2.mean()),
                       "primary_pushed": float(g1[moved].mean()) if moved.any() else 0.0,
                       "compare_pushed": float(g2[moved].mean()) if moved.any() else 0.0}
            print(f"{p:18s} {g1.mean():+.3f} / {g2.mean():+.3f}   when pushed ({moved.sum()}): "
                  f"{both[p]['primary_pushed']:+.3f} / {both[p]['compare_pushed']:+.3f}")
        out["all_stuck"] = both
        b1 = np.array([h["before"]["overall"] for h in stuck if "compare" in h])
        b2 = np.array([h["compare"]["before"]["overall"] for h in stuck if "compare" in h])
        print(f"Q*_o before the push: primary mean {b1.mean():.3f}, compare {b2.mean():.3f}; "
              f"equal on {np.mean(b1 == b2):.0%} of {len(b1)}")
        out["before"] = {"primary": float(b1.mean()), "compare": float(b2.mean()), "equal": float(np.mean(b1 == b2))}
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
