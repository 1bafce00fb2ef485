"""Speed of the grasp contact models: median time per grasp on ~1,000-triangle objects.

    OMP_NUM_THREADS=1 python sims/bench_grasp_models.py [--grasps 40] [--robust 10]

For each model: the evaluator as shipped (MathematicalProgram built once per structure, fast
exact paths), the naive path (a new MathematicalProgram and pydrake Solve() per grasp, same
contact model), and the robust quality with N = 10 trials. Times are per grasp, median over
grasps, CPU time of this process (time.process_time, robust to other jobs sharing the cores)
and wall time. Prints a markdown table; --write-docs also replaces the
"## Grasp quality" speed table in docs/BENCHMARKS.md.
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from ms_drake.grasping import MODELS, GraspEvaluator  # noqa: E402
from ms_drake.grasping.samplers import sample_antipodal_grasps  # noqa: E402

TARGETS_MS = {"point": 1.0, "reach": 10.0, "6dfc": 10.0}
REFERENCE_MS = {"point": 13.0, "reach": 207.1, "mfe": 247.9, "6dfc": 251.6}  # Table 3.1


def bench_objects():
    objs = {
        "sphere (1280 tri)": trimesh.creation.icosphere(subdivisions=3, radius=0.03),
        "cylinder (1000 tri)": trimesh.creation.cylinder(radius=0.025, height=0.08, sections=250),
        "capsule (~1000 tri)": trimesh.creation.capsule(height=0.06, radius=0.02, count=[24, 22]),
    }
    try:  # mesh sets, when converted: objects with 500-2000 triangles
        from ms_drake.objects import available_sets, get_object_set

        from ms_drake.grasping.meshes import object_mesh

        for s in available_sets():
            if s == "procedural":
                continue
            n = 0
            for o in get_object_set(s).objects:
                m = object_mesh(o.full_name)
                if 500 <= len(m.faces) <= 2000 and m.is_watertight and min(o.extents) < 0.08 and n < 2:
                    objs[f"{o.full_name} ({len(m.faces)} tri)"] = m
                    n += 1
    except Exception as e:  # noqa: BLE001
        print("mesh sets skipped:", e)
    return objs


def timed(fn, items):
    cpu, wall, out = [], [], []
    for it in items:
        c0, w0 = time.process_time(), time.perf_counter()
        out.append(fn(it))
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return 1e3 * float(np.median(cpu)), 1e3 * float(np.median(wall)), out


def run(grasps_per_object: int, robust: int, models=MODELS):
    objs = bench_objects()
    cases = []
    for k, (name, mesh) in enumerate(objs.items()):
        gs = sample_antipodal_grasps(mesh, np.eye(4), grasps_per_object, friction=0.6, max_width=0.1, seed=k,
                                     center_noise=0.004)
        cases += [(name, mesh, g) for g in gs]
    print(f"{len(objs)} objects, {len(cases)} grasps: " + ", ".join(objs))
    rows = []
    for model in models:
        fast = GraspEvaluator(model, friction=0.6)
        naive = GraspEvaluator(model, friction=0.6, solver="naive")
        for _, mesh, g in cases[:3]:  # warm caches (mesh data, programs) outside the timing
            fast.quality(mesh, np.eye(4), g, 0.2)
            naive.quality(mesh, np.eye(4), g, 0.2)
        c, w, q = timed(lambda c: fast.quality(c[1], np.eye(4), c[2], 0.2), cases)
        cn, wn, qn = timed(lambda c: naive.quality(c[1], np.eye(4), c[2], 0.2), cases)
        sub = cases[:: max(1, len(cases) // 30)]
        cr, wr, _ = timed(lambda c: fast.quality(c[1], np.eye(4), c[2], 0.2, robust_samples=robust), sub)
        agree = float(np.mean(np.array(q) == np.array(qn)))
        rows.append(dict(model=model, cpu=c, wall=w, naive_cpu=cn, naive_wall=wn, robust_cpu=cr, robust_wall=wr,
                         resisted=float(np.mean(q)), agree=agree))
        print(f"{model:10s} {c:7.2f} ms  naive {cn:7.2f} ms  robust {cr:7.1f} ms  agree {agree:.3f}", flush=True)
    return objs, cases, rows


def table(rows, robust):
    lines = ["| Model | ms / grasp (CPU) | wall | naive MP per grasp (CPU) | naive / ours | "
             f"robust N={robust} (CPU) | target | reference (Table 3.1) | same answers |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = TARGETS_MS.get(r["model"])
        ref = REFERENCE_MS.get(r["model"])
        lines.append(f"| {r['model']} | {r['cpu']:.2f} | {r['wall']:.2f} | {r['naive_cpu']:.2f} | "
                     f"{r['naive_cpu'] / r['cpu']:.1f}x | {r['robust_cpu']:.1f} | "
                     f"{'<= %g' % t if t else '-'} | {ref if ref else '-'} | {100 * r['agree']:.0f} % |")
    return "\n".join(lines)


def write_docs(text: str, path):
    """Replace the block between the speed markers in the "## Grasp quality" section."""
    start, end = "<!-- grasp-speed:start -->", "<!-- grasp-speed:end -->"
    doc = path.read_text() if path.is_file() else ""
    block = f"{start}\n{text}\n{end}"
    if start in doc and end in doc:
        doc = doc[: doc.index(start)] + block + doc[doc.index(end) + len(end):]
    else:
        raise SystemExit(f"{path} has no {start} ... {end} block in its '## Grasp quality' section")
    path.write_text(doc)


def machine_speed() -> float:
    """CPU ms of a fixed pure-Python loop, sum(range(10**6)): ~30 ms on this 2-core machine even
    when it is idle (load average < 0.7), so a figure well above 30 ms means the run shared the CPU."""
    c0 = time.process_time()
    for _ in range(3):
        sum(range(10 ** 6))
    return 1e3 * (time.process_time() - c0) / 3


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--grasps", type=int, default=40, help="grasps per object")
    ap.add_argument("--robust", type=int, default=10)
    ap.add_argument("--models", nargs="*", default=list(MODELS))
    ap.add_argument("--write-docs", action="store_true")
    args = ap.parse_args()
    speed0 = machine_speed()
    objs, cases, rows = run(args.grasps, args.robust, args.models)
    speed1 = machine_speed()
    text = table(rows, args.robust)
    text += (f"\n\n{len(cases)} grasps on {len(objs)} objects ({', '.join(objs)}); median per grasp; "
             "2 cores, no GPU, one thread (OMP_NUM_THREADS=1); CPU = time.process_time of the process. "
             f"Machine load during the run: the calibration loop sum(range(10**6)) took {speed0:.0f} / "
             f"{speed1:.0f} ms CPU before / after (about 30 ms on this machine when it is idle; a "
             "larger figure means the run shared the CPU with other jobs and ran that much slower).")
    print(text)
    if args.write_docs:
        from pathlib import Path

        write_docs(text, Path(__file__).resolve().parent.parent / "docs" / "BENCHMARKS.md")


if __name__ == "__main__":
    main()
