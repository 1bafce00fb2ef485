"""The fidelity benchmark's suction attempts: the wrench the other objects exert on the grasped one
in the YuMi station before the approach (the moment about the cup's contact point, the vertical
load), against whether the YuMi's cup lifted it. Asks whether a primitive outcome that accounts for
the heap's load ("whether or not an object can be lifted from the heap") would agree more.

Each attempt's scene is its heap at the start (the attempts of a `--attempts 1` run are every
heap's first), replayed as `ms-drake bench fidelity` does (`build_replay`), read once the arm has
held its park for 0.15 s.

    .venv/bin/python sims/fidelity_load_moment.py docs/data/fidelity_reach_v4_N10.jsonl --heap-dir HEAPS \
        --out docs/data/fidelity_load_moment.jsonl
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from ms_drake.experiments.fidelity import Attempt, build_replay
from ms_drake.experiments.harness import cached_heap
from ms_drake.station import get_plant, get_scene_graph
from ms_drake.types import Grasp


def wrench_on(plant, inspector, context, body: int, point: np.ndarray):
    """(force (3,), moment about `point` (3,)) the other objects' contacts exert on `body`."""
    res = plant.get_contact_results_output_port().Eval(context)

    def is_object(b):
        return plant.GetModelInstanceName(plant.get_body(b).model_instance()).startswith("obj")

    def sign(on, other) -> float:
        """+1 when the force acts on `body` from another object, -1 for its reaction, 0 else."""
        if int(on) == body and is_object(other):
            return 1.0
        return -1.0 if int(other) == body and is_object(on) else 0.0

    F, M = np.zeros(3), np.zeros(3)
    for k in range(res.num_hydroelastic_contacts()):
        c = res.hydroelastic_contact_info(k)
        s = c.contact_surface()
        a = plant.GetBodyFromFrameId(inspector.GetFrameId(s.id_M())).index()
        b = plant.GetBodyFromFrameId(inspector.GetFrameId(s.id_N())).index()
        f = np.asarray(c.F_Ac_W().translational())  # on the body of M, at the centroid
        m = np.asarray(c.F_Ac_W().rotational())
        k_ab = sign(a, b)
        F += k_ab * f
        M += k_ab * (m + np.cross(np.asarray(s.centroid()) - point, f))
    for k in range(res.num_point_pair_contacts()):
        c = res.point_pair_contact_info(k)
        f = np.asarray(c.contact_force())  # on body B, at the contact point
        k_ab = sign(c.bodyB_index(), c.bodyA_index())
        F += k_ab * f
        M += k_ab * np.cross(np.asarray(c.contact_point()) - point, f)
    return F, M


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("records")
    ap.add_argument("--heap-dir", required=True)
    ap.add_argument("--objects", type=int, default=10)
    ap.add_argument("--out", required=True, help="JSON lines, one per suction attempt")
    a = ap.parse_args()
    recs = [r for r in map(json.loads, open(a.records)) if r.get("kind") == "attempt" and r["grasp"] == "suction"
            and r["step"] == 0]
    with open(a.out, "w") as out:
        for r in recs:
            heap = cached_heap(a.objects, r["seed"], a.heap_dir)
            g = Grasp("suction", tuple(r["center"]), tuple(r["approach"]), quality=r["quality"], object_id=r["object"])
            sim, station, executor, backend = build_replay(Attempt(r["seed"], 0, g, heap, ()), seed=r["seed"])
            sim.AdvanceTo(0.15)
            plant = get_plant(station)
            ctx = plant.GetMyContextFromRoot(sim.get_context())
            p, n = np.asarray(r["center"], float), -np.asarray(r["approach"], float)
            F, M = wrench_on(plant, get_scene_graph(station).model_inspector(), ctx, backend.objects[r["object"]], p)
            m_axis = float(M @ n)
            row = dict(seed=r["seed"], object=r["object"], quality=r["quality"], full_lifted=r["full_lifted"],
                       full_load=r.get("full_load"), force=F.tolist(), moment=M.tolist(),
                       tipping_moment=float(np.linalg.norm(M - m_axis * n)), pull=float(F @ n))
            out.write(json.dumps(row) + "\n")
            out.flush()
            print(r["seed"], r["object"][:24], "q", r["quality"], "full", int(r["full_lifted"]),
                  "Fz %.2f pull %.2f tip %.3f N m" % (F[2], row["pull"], row["tipping_moment"]), flush=True)


if __name__ == "__main__":
    main()
