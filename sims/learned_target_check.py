"""First image of Table 8.2 heaps (xray protocol) seen through the learned segmenter: which mask
the colour and the learned target detectors pick, and whether it lies on the target.

    .venv/bin/python sims/learned_target_check.py  # seeds 5000-5019, heap cache /work/occ/heaps_s4

Columns per detector: target pixels visible, masks, visible, confidence, chosen mask px, its px on the target.
"""
import numpy as np
from ms_drake.scenario import load_scenario
from ms_drake.experiments.harness import cached_heap
from ms_drake.experiments.rollout import SearchParams, build_search, _set_initial
from ms_drake.perception.masks import object_labels
for seed in range(5000, 5020):
    heap = cached_heap(14, seed, '/work/occ/heaps_s4', 'xray')
    out = [seed]
    for det in ("color", "learned"):
        system = build_search(load_scenario(None, 'FloatingGripperBin'), heap,
                              SearchParams(policy='largest', seed=seed, time_step=0.01, segmenter='learned', detector=det))
        ctx = system.diagram.CreateDefaultContext()
        _set_initial(system, ctx, heap)
        masks = system.output(ctx, 'masks'); t = system.output(ctx, 'target')
        sc = system.station.GetMyContextFromRoot(ctx)
        lab = np.array(system.station.GetOutputPort('overhead.label_image').Eval(sc).data)[:, :, 0]
        l2i = object_labels(system.plant)
        tl = {v: k for k, v in l2i.items()}[system.target_id]
        tpx = int((lab == tl).sum())
        on_target = int((t.mask & (lab == tl)).sum()) if t.visible else 0
        out += [det, tpx, len(masks), bool(t.visible), round(float(t.confidence), 2), int(t.mask.sum()), on_target]
    print(*out, flush=True)
