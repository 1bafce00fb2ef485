"""Replay one grasp attempt of the fidelity benchmark on the YuMi with a log every 50 ms: how far
the tool centre is from the grasp point, how far the grasped object rose and turned, the suction
cup's state (holding, gap) and, with --contacts, the contact forces on the object and on the
robot (which bodies touch it). --alone removes every other object first (an object resting on
others then falls before the cup arrives: read it for objects on the floor only).

    .venv/bin/python sims/fidelity_replay_log.py --seed 5023 --heap-dir HEAPS [--attempt 0] [--contacts] [--alone]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
from pydrake.multibody.tree import BodyIndex, ModelInstanceIndex

from ms_drake.experiments.fidelity import build_replay, object_load, primitive_attempts
from ms_drake.experiments.harness import cached_heap
from ms_drake.station import get_plant, get_scene_graph


def find_system(diagram, name):
    for s in diagram.GetSystems():
        if s.get_name() == name:
            return s
        if hasattr(s, "GetSystems"):
            found = find_system(s, name)
            if found is not None:
                return found
    return None


def robot_contacts(plant, inspector, context, body: int) -> dict:
    """{other body: vertical force on it} for contacts of the object `body` and of robot bodies."""
    res = plant.get_contact_results_output_port().Eval(context)

    def name(b):
        return f"{plant.GetModelInstanceName(plant.get_body(b).model_instance())}:{plant.get_body(b).name()}"

    out = {}
    for i in range(res.num_hydroelastic_contacts()):
        c = res.hydroelastic_contact_info(i)
        a = plant.GetBodyFromFrameId(inspector.GetFrameId(c.contact_surface().id_M())).index()
        b = plant.GetBodyFromFrameId(inspector.GetFrameId(c.contact_surface().id_N())).index()
        if body in (int(a), int(b)) or any("yumi" in name(x) for x in (a, b)):
            out[f"{name(a)} <- {name(b)}"] = np.round(c.F_Ac_W().translational(), 2)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--objects", type=int, default=10)
    ap.add_argument("--heap-dir", default=None)
    ap.add_argument("--attempt", type=int, default=0)
    ap.add_argument("--reach", default="YuMiBin")
    ap.add_argument("--contacts", action="store_true")
    ap.add_argument("--alone", action="store_true")
    ap.add_argument("--until", type=float, default=8.0)
    a = ap.parse_args()
    heap = cached_heap(a.objects, a.seed, a.heap_dir)
    attempt = primitive_attempts(heap, max_attempts=a.attempt + 1, reach=a.reach)[0][a.attempt]
    g = attempt.grasp
    if a.alone:  # objects are named obj<k>__<set>__<name>, k their index in the heap
        k = int(g.object_id.split("__")[0][3:])
        attempt = dataclasses.replace(attempt, removed=tuple(i for i in range(len(heap.objects)) if i != k))
    sim, station, ex, backend = build_replay(attempt, seed=attempt.seed)
    ctx = sim.get_mutable_context()
    plant = get_plant(station)
    pc = plant.GetMyContextFromRoot(ctx)
    inspector = get_scene_graph(station).model_inspector()
    body = backend.objects[g.object_id]
    b = plant.get_body(BodyIndex(body))
    X0 = plant.EvalBodyPoseInWorld(pc, b)
    com = X0 @ b.CalcCenterOfMassInBodyFrame(pc)
    print(f"grasp {g.kind} {g.object_id} quality {g.quality} centre {np.round(g.center, 3)} approach "
          f"{np.round(g.approach, 3)}; mass {b.default_mass():.3f} kg, grasp point {100 * np.linalg.norm(np.asarray(g.center)[:2] - com[:2]):.1f} cm "
          f"from the centre of mass (horizontally); primitive lifted {attempt.primitive_lifted}")
    arm, port = backend.suction if g.kind == "suction" else backend.jaw
    tool = next(plant.GetFrameByName("tcp", ModelInstanceIndex(i)) for i in range(plant.num_model_instances())
                if plant.GetModelInstanceName(ModelInstanceIndex(i)) == port)
    cup = find_system(station, f"{port}_cup") if g.kind == "suction" else None
    ex_ctx = ex.GetMyContextFromRoot(ctx)
    k = 0
    while k * 0.05 < a.until:
        k += 1
        t = k * 0.05
        sim.AdvanceTo(t)
        X = plant.EvalBodyPoseInWorld(pc, b)
        R = X0.rotation().matrix().T @ X.rotation().matrix()
        turn = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
        err = np.linalg.norm(tool.CalcPoseInWorld(pc).translation() - np.asarray(g.center))
        line = f"t={t:.2f} tcp-grasp {1000 * err:6.1f} mm  rise {1000 * (X.translation()[2] - X0.translation()[2]):6.1f} mm  turned {turn:5.1f} deg"
        if cup is not None:
            hit = cup.evaluate(cup.GetMyContextFromRoot(ctx))
            line += "  cup: off" if hit is None else f"  cup: {hit[0]:.0f} N, gap {1000 * hit[2]:.1f} mm"
        print(line)
        if a.contacts and k % 4 == 0:
            load, pressed = object_load(plant, inspector, pc, body)
            print(f"   load of other objects {load:+.2f} N ({pressed} pressing down); contacts {robot_contacts(plant, inspector, pc, body)}")
        h = ex.GetOutputPort("history").Eval(ex_ctx)
        if h:
            print("outcome", h[0].success, h[0].message or "lifted")
            break


if __name__ == "__main__":
    main()
