"""Does quasi-random lead the push study because its push is not collision-checked? An ablation.

Quasi-random pushes a random object a fixed 8 cm in a random direction through its
centre, clipped to the bin only; the other four policies push only where the object is free to
move. The study's ablation switch `ablation.quasi_random_checked` (PushStudyConfig) keeps quasi-random's random draw but pushes only as
far as the object is free (its clearance, at most 8 cm) with the jaw's start free, drawing again
(up to 16 times) while no such push exists. Both run from the stored states of a data step's
improvable heaps (as `policies_from_state`, each heap's own config), so each pair
is the same state, the same grasp samples and, on the first draw, the same object and direction;
the other four policies run on the same states in the same job, so every row is one code and one
physics:

    .venv/bin/python sims/push_ablation.py DIR --heaps 103 --out FILE.jsonl [--workers K] [--json SUMMARY]

Prints per row the heaps pushed, mean overall / jaw / suction / separation gain (+- SE), the
share of pushes that tip or roll the pushed object (> 20 degrees), and paired sign tests of the
overall gain: quasi-random against its checked variant, and the checked variant against each
other policy. Resumable (one line per heap in FILE).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from ms_drake.experiments.push_study import (
    GraspSets,
    PushWorld,
    PushStudyConfig,
    _append,
    improvable_records,
    read_jsonl,
    heap_config,
    run_policy,
    state_metrics,
)
from ms_drake.parallel import run_jobs
from ms_drake.pushing import POLICIES, PolicyParams
from ms_drake.scenes.heaps import heap_from_dict

# (policy, its PolicyParams) by row name: both quasi-random variants and the other four policies
VARIANTS = {"quasi_random": ("quasi_random", PolicyParams()),
            "quasi_random_checked": ("quasi_random", PolicyParams(quasi_random_checked=True)),
            **{p: (p, PolicyParams()) for p in POLICIES if p != "quasi_random"}}
GAINS = ("overall_gain", "jaw_gain", "suction_gain", "separation_gain")
TURNED = 20.0  # degrees: the pushed object tipped over or rolled


def ablation_job(job: tuple) -> dict:
    """(heap record, PushStudyConfig dict) -> every row's (VARIANTS) run_policy record on its stored state."""
    rec, params = job
    c = time.process_time()
    params = PushStudyConfig(**params)
    world = PushWorld(heap_from_dict(rec["heap"]), params)
    world.set_state(rec["state"])
    sets = GraspSets(params, int(rec["seed"]))
    before = state_metrics(world, sets)
    snap = world.snapshot()
    out = {name: run_policy(world, snap, before, sets, policy, int(rec["seed"]), policy_params=pp)
           for name, (policy, pp) in VARIANTS.items()}
    for r in out.values():
        r.pop("after_per_object", None)
    return {"before": {k: before[k] for k in ("D", "jaw", "suction", "overall")}, "variants": out,
            "cpu_s": time.process_time() - c}


def summarize(rows: list[dict]) -> dict:
    out = {}
    for name in VARIANTS:
        vs = [r["variants"][name] for r in rows]
        pushed = [v for v in vs if v.get("pushed") and "pushed_tilt_deg" in v]
        s = {"heaps": len(vs), "pushed": len(pushed),
             "turned": sum(v["pushed_tilt_deg"] > TURNED for v in pushed)}
        for g in GAINS:
            x = np.array([v.get(g, 0.0) for v in vs])
            s[g] = {"mean": float(x.mean()), "se": float(x.std(ddof=1) / np.sqrt(len(x))) if len(x) > 1 else 0.0}
        s["gain_when_pushed"] = float(np.mean([v["overall_gain"] for v in pushed])) if pushed else 0.0
        s["displacement"] = float(np.mean([v["pushed_displacement"] for v in pushed])) if pushed else 0.0
        out[name] = s
    b = np.array([r["variants"]["quasi_random_checked"].get("overall_gain", 0.0) for r in rows])
    out["paired_overall"] = {}
    for name in VARIANTS:
        if name == "quasi_random_checked":
            continue
        a = np.array([r["variants"][name].get("overall_gain", 0.0) for r in rows])
        hi, lo = int(np.sum(a > b + 1e-9)), int(np.sum(b > a + 1e-9))
        out["paired_overall"][name] = {"higher": hi, "checked_higher": lo,
                                       "p": float(binomtest(hi, hi + lo, 0.5).pvalue) if hi + lo else 1.0}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", type=Path, help="a `ms-drake data push-heaps` folder")
    ap.add_argument("--heaps", type=int, default=103)
    ap.add_argument("--seed-start", type=int, default=0, help="the first N improvable heaps with seed >= S")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--figure", type=Path, help="bar plot of the four gains per row (PNG)")
    a = ap.parse_args(argv)
    done = {int(r["seed"]) for r in read_jsonl(a.out) if set(VARIANTS) <= set(r["variants"])}
    todo = [h for h in improvable_records(a.dir, a.heaps, a.seed_start) if int(h["seed"]) not in done]
    jobs = [(h, asdict(heap_config(h))) for h in todo]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    for r in run_jobs(ablation_job, jobs, workers=a.workers):
        if r.ok:
            rec = {"seed": int(r.job[0]["seed"]), "objects": r.job[0]["objects"], **r.value}
            _append(a.out, rec)
            print(f"seed {rec['seed']}: " + ", ".join(f"{k} {v.get('overall_gain', 0):+.2f}"
                                                        for k, v in rec["variants"].items()), flush=True)
        else:
            print(f"seed {r.job[0]['seed']}: failed: {(r.error or '').strip().splitlines()[-1:]}", flush=True)
    rows = sorted((r for r in read_jsonl(a.out) if r["seed"] >= a.seed_start and set(VARIANTS) <= set(r["variants"])),
                  key=lambda r: r["seed"])[: a.heaps]
    s = summarize(rows)
    print(f"\n{len(rows)} heaps")
    for name in VARIANTS:
        v = s[name]
        print(f"{name:22s} pushed {v['pushed']:3d}, turned > {TURNED:.0f} deg {v['turned']:3d}; " + ", ".join(
            f"{g.replace('_gain', '')} {v[g]['mean']:+.3f} +- {v[g]['se']:.3f}" for g in GAINS)
            + f"; when pushed {v['gain_when_pushed']:+.3f}, displacement {100 * v['displacement']:.1f} cm")
    for name, p in s["paired_overall"].items():
        print(f"overall gain, {name} vs quasi_random_checked: higher on {p['higher']}, lower on "
              f"{p['checked_higher']} heaps (sign test p = {p['p']:.3g})")
    if a.json:
        a.json.write_text(json.dumps(s, indent=1))
    if a.figure:
        figure(s, len(rows), a.figure)
    return s


def figure(s: dict, heaps: int, path: Path) -> None:
    """Fig. 4.2-style bars: each row's mean gains with standard errors."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(VARIANTS)
    fig, ax = plt.subplots(figsize=(9, 4))
    w = 0.8 / len(GAINS)
    for k, g in enumerate(GAINS):
        x = np.arange(len(names)) + (k - (len(GAINS) - 1) / 2) * w
        ax.bar(x, [s[n][g]["mean"] for n in names], w, yerr=[s[n][g]["se"] for n in names], capsize=2,
               label=g.replace("_", " "))
    ax.set_xticks(np.arange(len(names)), [n.replace("_", "\n") for n in names], fontsize=8)
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_ylabel("mean gain (+- SE)")
    ax.set_title(f"Quasi-random with and without a collision check, and the other policies ({heaps} heaps)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
