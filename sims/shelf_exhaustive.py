"""Exhaustive breadth-first search of one shelf scene's plans in FOSS: the shortest plan's length,
or a lower bound on it, for a scene the oracles do not solve.

Branches on every action FOSS allows -- every push to the neighbour and stopped short so the blade
still fits (Foss.push_actions(leave_room=True)), and with --suction every placement on the 50 x 8
suction grid -- with duplicate states (object positions to 0.1 mm) merged; stops at the first state
where the camera sees --threshold of the target, or after --depth actions. Prints, per depth, the
number of new states and the best visibility reached.

    .venv/bin/python sims/shelf_exhaustive.py --occluders 8 --seed 22 --depth 6 --suction \
        --out out/shelf_exhaustive/p_8-22.json
"""

import argparse
import json
import time
from pathlib import Path

from ms_drake.experiments.shelf import shelf_geometry
from ms_drake.foss import Foss
from ms_drake.scenes.shelf import generate_shelf_scene


def key(scene) -> tuple:
    return tuple((o.id, round(o.x, 4), round(o.y, 4)) for o in scene.objects)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--occluders", type=int, required=True)
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--depth", type=int, default=5)
    ap.add_argument("--suction", action="store_true", help="branch on suction actions too (Oracle-P+S)")
    ap.add_argument("--threshold", type=float, default=0.8, help="visible fraction of the target that ends the search")
    ap.add_argument("--max-seconds", type=float, default=None,
                    help="CPU budget: stop inside the current depth and record the last complete depth as the bound")
    ap.add_argument("--out", type=Path, default=None, help="JSON summary")
    args = ap.parse_args()
    foss = Foss(shelf_geometry())
    scene = generate_shelf_scene(foss.geometry, args.seed, args.occluders).scene
    t0, t_cpu = time.perf_counter(), time.process_time()
    frontier, seen, best, levels, plan_found = [(scene, [])], {key(scene)}, foss.visible_fraction(scene), [], None
    out_of_time = False
    for depth in range(1, args.depth + 1):
        nxt = []
        for i, (s, plan) in enumerate(frontier):
            if args.max_seconds is not None and i % 200 == 0 and time.process_time() - t_cpu > args.max_seconds:
                out_of_time = True
                break
            acts = foss.push_actions(s, leave_room=True) + (foss.suction_actions(s) if args.suction else [])
            for a in acts:
                s2 = foss.moved(s, a)
                k = key(s2)
                if k in seen:
                    continue
                seen.add(k)
                v = foss.visible_fraction(s2)
                best = max(best, v)
                if v >= args.threshold:
                    plan_found = [dict(kind=x.kind, object=x.object_id, dx=round(x.dx, 4), dy=round(x.dy, 4))
                                  for x in plan + [a]]
                    break
                nxt.append((s2, plan + [a]))
            if plan_found:
                break
        if out_of_time:
            print(f"CPU budget of {args.max_seconds} s spent inside depth {depth}", flush=True)
            break
        levels.append(dict(depth=depth, states=len(nxt), best_visible=round(best, 4),
                           cpu_seconds=round(time.process_time() - t_cpu, 1)))
        print(json.dumps(levels[-1]), flush=True)
        if plan_found:
            print("plan:", json.dumps(plan_found))
            break
        frontier = nxt
    out = dict(occluders=args.occluders, seed=args.seed, suction=args.suction, threshold=args.threshold,
               max_depth=args.depth, levels=levels, plan=plan_found, wall_seconds=round(time.perf_counter() - t0, 1))
    if plan_found is None:
        searched = levels[-1]["depth"] if levels else 0
        out["shortest_plan_at_least"] = searched + 1
        out["exhausted"] = bool(levels) and levels[-1]["states"] == 0  # no reachable state left: no plan of any length
        out["stopped_by_budget"] = out_of_time
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "levels"}))


if __name__ == "__main__":
    main()
