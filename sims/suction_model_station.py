"""What the station-matched suction model would change (issue #15, "The two fidelities agree").

The grasp sets score suction grasps with the SuctionEvaluator's defaults (Dex-Net 3.0's cup: 30 N,
lip friction 0.5, moment limit 0.24 N m, lip springs stretched by at most 10 %); the stations' cup
(ms_drake/station/suction.py) pulls 40 N, its lip has friction 1.0 and holds f r = 0.6 N m, and
its seal has no stretch criterion. With `--model station` every SuctionEvaluator of this process
defaults to STATION, and each grasp set's suction grasps are re-made with it (the set's own
samples and seeds, as `compute_grasp_set` draws them; jaw grasps unchanged), in memory, cached in
--cache; `--model current` runs the same code unpatched.

    # Largest on Bullet heaps (N = 15, budget 2N), one JSON line per heap (resumable)
    .venv/bin/python sims/suction_model_station.py search --model current --seed-start 1000 --heaps 200 \
        --heap-dir HEAPS --out docs/data/suction_station/largest_current.jsonl
    .venv/bin/python sims/suction_model_station.py search --model station ... --out .../largest_station.jsonl
    # the fidelity benchmark (first attempt per heap, the YuMi's reach) with the station-matched sets
    .venv/bin/python sims/suction_model_station.py fidelity --model station --seed-start 5000 --heaps 100 \
        --heap-dir HEAPS10 --out docs/data/suction_station/fidelity_station.jsonl
"""

from __future__ import annotations

import argparse
import json
import pickle
import zlib
from pathlib import Path

import numpy as np

import ms_drake.grasping.grasp_sets as gsm
import ms_drake.grasping.suction as suc
from ms_drake.objects import get_object

STATION = dict(vacuum_force=40.0, friction=1.0, stiffness=0.6 / (np.pi * 0.015), max_stretch=0.3)


def use_station_model(cache_file: Path) -> None:
    init = suc.SuctionEvaluator.__init__

    def station_init(self, *a, **k):
        for key, v in STATION.items():
            k.setdefault(key, v)
        init(self, *a, **k)

    suc.SuctionEvaluator.__init__ = station_init
    cache = pickle.load(open(cache_file, "rb")) if cache_file.exists() else {}
    load_stored = gsm.load_grasp_set

    def load(full_name, root=None):
        gs = load_stored(full_name, root)
        if gs is None:
            return None
        if full_name not in cache:  # compute_grasp_set's suction half, with the station's model
            p = gs.params
            spec, mesh = get_object(full_name), gsm.object_mesh(full_name)
            mass, com = spec.mass, np.asarray(spec.inertia.com, float)
            seed = (p["seed"] * 1_000_003 + zlib.crc32(full_name.encode())) % (2 ** 31 - 1)
            sev = suc.SuctionEvaluator()
            sucs = gsm.sample_suction_grasps(mesh, np.eye(4), p["suction"], seed=seed + 1)
            q = np.zeros(len(sucs))
            for i, g in enumerate(sucs):
                X = gsm._down(g.approach)
                q[i] = sev.quality(mesh, X, g.transformed(X), mass, p["robust_samples"], seed + 104729 + i, com)
            keep = np.round(100 * q) > 0  # as the packs keep them
            cache[full_name] = (np.array([g.point for g in sucs]).reshape(-1, 3)[keep],
                                -np.array([g.approach for g in sucs]).reshape(-1, 3)[keep], np.round(100 * q[keep]) / 100)
            tmp = cache_file.with_suffix(".tmp")
            pickle.dump(cache, open(tmp, "wb"))
            tmp.replace(cache_file)
        pts, normals, q = cache[full_name]
        return gsm.GraspSet(gs.object, gs.model, gs.jaw_center, gs.jaw_axis, gs.jaw_ref, gs.jaw_width,
                            gs.jaw_quality, pts, normals, q, gs.params)

    gsm.load_grasp_set = load


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=("search", "fidelity"))
    ap.add_argument("--model", choices=("current", "station"), required=True)
    ap.add_argument("--seed-start", type=int, required=True)
    ap.add_argument("--heaps", type=int, required=True)
    ap.add_argument("--heap-dir", required=True, help="cached heaps (made on first use)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cache", type=Path, default=None, help="re-made suction grasps (default: next to --out)")
    a = ap.parse_args()
    if a.model == "station":
        use_station_model(a.cache or a.out.with_name(a.out.stem + "_sets.pkl"))
    from ms_drake.experiments.fidelity import format_summary, heap_job, summarize
    from ms_drake.experiments.harness import rollout_job, search_options

    a.out.parent.mkdir(parents=True, exist_ok=True)
    recs = [json.loads(line) for line in open(a.out)] if a.out.exists() else []
    done = {r["seed"] for r in recs if a.what == "search" or r.get("kind") == "heap"}
    opts = search_options("primitive", heap_engine="bullet")
    with open(a.out, "a") as f:
        for seed in range(a.seed_start, a.seed_start + a.heaps):
            if seed in done:
                continue
            if a.what == "search":
                out = [rollout_job(("largest", 15, seed, "primitive", None, a.heap_dir, "ch7", opts))]
            else:
                out = heap_job((10, seed, a.heap_dir, 1, "largest", "YuMiBin"))
            for r in out:
                r["suction_model"] = a.model
                f.write(json.dumps(r) + "\n")
            f.flush()
            print(seed, flush=True)
    if a.what == "fidelity":
        print(format_summary(summarize([json.loads(line) for line in open(a.out)])))


if __name__ == "__main__":
    main()
