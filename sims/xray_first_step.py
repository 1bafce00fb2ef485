"""X-Ray's first choice on the `xray_compact` heaps, against the oracle's.

    .venv/bin/python sims/xray_first_step.py SEED_FROM SEED_TO OUT.jsonl HEAP_DIR

Per heap, at its start (before any action): for X-Ray's occupancy estimators (the shipped network,
models/weights/occupancy_compact.pt, and `analytic_image`: the ground-truth generator on the
depth image and the target's box) the share of the distribution on the target's true amodal mask,
whether X-Ray's first-ranked mask is the oracle's (the mask covering the target's amodal mask
most) and whether it covers the target at all; then the means over the heaps.
"""
import json
import sys

import numpy as np

from ms_drake.experiments.harness import cached_heap
from ms_drake.experiments.rollout import SearchParams, build_search, primitive_time_step, SCENARIOS, _set_initial
from ms_drake.policies.bin_selectors import priority_xray, priority_oracle
from ms_drake.scenario import load_scenario
sc = load_scenario(None, SCENARIOS["primitive"])
out = open(sys.argv[3], "w")
rows = []
for seed in range(int(sys.argv[1]), int(sys.argv[2])):
    heap = cached_heap(14, seed, sys.argv[4], "xray_compact", "drake")
    row = dict(seed=seed)
    sysd = {}
    for name, pol, occ, w in (("oracle", "oracle", "learned", ""), ("learned", "xray", "learned", ""),
                              ("tuned", "xray", "learned", "models/weights/occupancy_compact.pt"),
                              ("analytic_image", "xray", "analytic_image", "")):
        p = SearchParams(policy=pol, fidelity="primitive", horizon=10, seed=seed, time_step=primitive_time_step(pol),
                         grasp_planner="image", grasp_samples=32, occupancy=occ, occupancy_weights=w)
        s = build_search(sc, heap, p)
        ctx = s.diagram.CreateDefaultContext()
        _set_initial(s, ctx, heap)
        sysd[name] = (s, ctx)
    s, ctx = sysd["oracle"]
    masks = s.output(ctx, "masks")
    sel = s.controller.GetSubsystemByName("policy_selector")
    amodal = sel.GetInputPort("target_amodal").Eval(sel.GetMyContextFromRoot(ctx))
    amodal = np.asarray(getattr(amodal, "mask", amodal), bool)
    oracle_order = priority_oracle(masks, s.target_id, amodal)
    cover = (masks.masks & amodal[None]).reshape(len(masks), -1).sum(1)
    row["amodal_px"] = int(amodal.sum()); row["oracle_top"] = masks.ids[oracle_order[0]]
    for name in ("learned", "tuned", "analytic_image"):
        s2, c2 = sysd[name]
        rho = s2.output(c2, "occupancy").distribution
        order = priority_xray(masks, s2.output(c2, "occupancy"), None)
        row[name] = dict(mass_on_target=float(rho[amodal].sum()), top_is_oracle=bool(order[0] == oracle_order[0]),
                         top_cover=int(cover[order[0]]), top_covers=bool(cover[order[0]] > 0),
                         support=int((rho > 0.1 * rho.max()).sum()))
    out.write(json.dumps(row) + "\n"); out.flush()
    rows.append(row)
for name in ("learned", "tuned", "analytic_image"):
    r = [x[name] for x in rows]
    print(f"{name}: {len(r)} heaps, mass on the target median {np.median([x['mass_on_target'] for x in r]):.3f}, "
          f"first mask = the oracle's {np.mean([x['top_is_oracle'] for x in r]):.0%}, "
          f"covers the target {np.mean([x['top_covers'] for x in r]):.0%}")
