"""One shelf scene searched by a policy under FOSS's two suction lift rules (or, with
--target-push, by an oracle with the target left in place and pushed), drawn from above.

For each row the search runs as in Table 9.1 (`shelf_rollout`'s Diagram, ground-truth occupancy)
and the figure shows the shelf seen from above at the start and after each action: objects (the
target red, the moved one orange, heights in cm), and for each suction the object's sweeps to and
from the front (dashed); the camera looks from below the panel.

    .venv/bin/python sims/shelf_lift_example.py --occluders 10 --seed 4 --policy bluction_dar \
        --out docs/figures/shelf_lift_example.png
    .venv/bin/python sims/shelf_lift_example.py --occluders 6 --seed 43 --policy oracle_p --target-push \
        --out docs/figures/shelf_target_push_example.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Circle, Rectangle  # noqa: E402
from pydrake.systems.analysis import Simulator  # noqa: E402

from ms_drake.experiments.shelf import DEFAULT_TARGET, SCENARIO, build_shelf_search, shelf_geometry  # noqa: E402
from ms_drake.foss import SUCTION_LIFTS, Foss, FossParams  # noqa: E402
from ms_drake.policies.shelf import ShelfPolicyParams, check_shelf_policy  # noqa: E402
from ms_drake.scenes.shelf import generate_shelf_scene  # noqa: E402


def search(policy: str, occluders: int, seed: int, lift: str, push_target: bool = False):
    """[(scene, action or None)] from the start to the end of the search, and whether it succeeded."""
    geometry = shelf_geometry(SCENARIO)
    foss = Foss(geometry, FossParams.for_suction_lift(lift))
    scene = generate_shelf_scene(geometry, seed, occluders, DEFAULT_TARGET).scene
    params = ShelfPolicyParams(seed=seed, oracle_push_target=push_target)
    diagram = build_shelf_search(foss, scene, policy, params, DEFAULT_TARGET)
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    period = diagram.GetSubsystemByName("foss").period
    states, steps = [], 0
    while True:
        sc = diagram.GetOutputPort("scene").Eval(ctx)
        visible = float(diagram.GetOutputPort("visible_fraction").Eval(ctx)[0])
        if visible >= foss.params.visibility_threshold or steps >= 2 * occluders:
            states.append((sc, None, visible))
            break
        action = diagram.GetOutputPort("action").Eval(ctx)
        if action.kind != "shelf":
            states.append((sc, None, visible))
            break
        states.append((sc, action.shelf, visible))
        steps += 1
        sim.AdvanceTo((steps + 0.5) * period)
    return states, visible >= foss.params.visibility_threshold, geometry


def draw(ax, geometry, scene, action, visible: float, title: str):
    hx, hy = geometry.half
    ax.add_patch(Rectangle((-hx, -hy), 2 * hx, 2 * hy, fill=False, lw=1.5, color="k"))
    for o in (*scene.objects, scene.target):
        red = o is scene.target
        moved = action is not None and o.id == action.object_id
        face = "tab:red" if red else ("tab:orange" if moved else "0.75")
        if o.kind == "cylinder":
            ax.add_patch(Circle((o.x, o.y), o.width / 2, fc=face, ec="k", lw=0.6))
        else:
            ax.add_patch(Rectangle((o.x - o.width / 2, o.y - o.depth / 2), o.width, o.depth, fc=face, ec="k", lw=0.6))
        if not red:
            ax.text(o.x, o.y, f"{o.height * 100:.0f}", ha="center", va="center", fontsize=6)
    if action is not None:
        o = scene.target if action.object_id == scene.target.id else scene.object(action.object_id)
        if action.kind == "suction":  # the sweeps: out to the front, and in to the placement
            x1, y1 = o.x + action.dx, -hy + action.dy + o.depth / 2
            for x, y in ((o.x, o.y), (x1, y1)):
                ax.add_patch(Rectangle((x - o.width / 2, -hy - o.depth), o.width, y - (-hy - o.depth) + o.depth / 2,
                                       fill=False, ls="--", ec="tab:blue", lw=1.0))
            ax.annotate("", (x1, y1), (o.x, o.y), arrowprops=dict(arrowstyle="->", color="tab:blue"))
        else:
            ax.annotate("", (o.x + action.dx, o.y), (o.x, o.y), arrowprops=dict(arrowstyle="->", color="tab:green"))
    ax.set_xlim(-hx - 0.02, hx + 0.02)
    ax.set_ylim(-hy - 0.25, hy + 0.02)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    what = "" if action is None else f"\n{action.kind} {action.object_id}"
    ax.set_title(f"{title}{what}\nseen {100 * visible:.0f} %", fontsize=7)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--occluders", type=int, default=10)
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--policy", default="bluction_dar")
    ap.add_argument("--max-panels", type=int, default=6, help="panels per row (the last state always shown)")
    ap.add_argument("--target-push", action="store_true",
                    help="rows: the oracle with the target left in place and pushing it (--lift's rule)")
    ap.add_argument("--lift", default="over", choices=sorted(SUCTION_LIFTS), help="the lift rule with --target-push")
    ap.add_argument("--out", type=Path, default=Path("docs/figures/shelf_lift_example.png"))
    a = ap.parse_args()
    check_shelf_policy(a.policy)
    if a.target_push:
        if a.policy not in ("oracle_p", "oracle_ps"):
            ap.error(f"--target-push: only the oracles push the target (oracle_p, oracle_ps), not {a.policy}")
        runs = {name: search(a.policy, a.occluders, a.seed, a.lift, push) for name, push in
                (("target stays", False), ("target pushed", True))}
    else:
        runs = {f"lift {lift}": search(a.policy, a.occluders, a.seed, lift) for lift in SUCTION_LIFTS}
    cols = max(min(len(states), a.max_panels) for states, _, _ in runs.values())
    fig, axes = plt.subplots(len(runs), cols, figsize=(2.2 * cols, 2.6 * len(runs)), squeeze=False)
    for row, (name, (states, ok, geometry)) in enumerate(runs.items()):
        shown = states[: a.max_panels - 1] + [states[-1]] if len(states) > a.max_panels else states
        for col in range(cols):
            ax = axes[row, col]
            if col >= len(shown):
                ax.axis("off")
                continue
            sc, action, vis = shown[col]
            step = states.index(shown[col])
            draw(ax, geometry, sc, action, vis, f"{name}, step {step}")
        axes[row, 0].set_ylabel(f"{name}: {'found' if ok else 'not found'} in {len(states) - 1} actions",
                                fontsize=8)
        print(f"{name}: {'success' if ok else 'failure'} after {len(states) - 1} actions: "
              + ", ".join(f"{s[1].kind} {s[1].object_id}" for s in states if s[1] is not None))
    fig.suptitle(f"{a.policy}, {a.occluders} occluders, scene {a.seed} (from above; the front and camera below; "
                 "numbers: heights in cm)", fontsize=8)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(a.out, dpi=130)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
