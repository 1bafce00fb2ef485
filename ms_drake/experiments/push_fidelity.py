"""Full fidelity of the push study: each policy's push of an improvable heap executed on
the YuMi station and in the primitive mode from the same state, and whether the objects end up in
the same places.

Per (heap, policy) whose record holds a push (`ms-drake data push-heaps`):
  state      the record's "state" (poses of the objects present before the push), loaded at rest
             into both worlds: PushWorld(fidelity="primitive") and PushWorld(fidelity="full");
  push       the record's push (start, end, object): the policy's plan on that state;
  primitive  PushWorld.execute_push in FloatingGripperBin: the floating closed jaw at 0.15 m/s along
             the segment, broad side leading, at the study's plant step (PushStudyConfig.time_step,
             PRIMITIVE_PUSH_TIME_STEP = 5 ms), then the 0.5 s settle (the study's own execution,
             run again here so both sides come from this code);
  full       the same Push by FullBackend in YuMiBin at the scenario's 2 ms plant step: the right
             arm's closed jaw (tool pointing down, broad side leading, as the primitive jaw) at the
             push's height along the segment (plan_push, <= 0.1 m/s), from the arm's park
             configuration through the station's drivers and back, then the same 0.5 s settle.
             When the planner fails (IK: "unreachable", "collision", ...) the row's status is
             "unreachable" with the planner's status in `plan_status`: counted apart, neither
             agreement nor disagreement.

Agreement (fixed before any result was seen). For every object present before the push: c0 its
centre of mass before, c_p / c_f after the primitive / full push, all in the bin's plane (x, y).
The push agrees when every object has left the bin in both executions, or in neither with
    |c_f - c_p| <= 2 cm + 25 % |c_p - c0|.
The relative part: where a pushed object stops depends on where it slides off the jaw, an error
that grows with how far it travels (the study's pushes are 3-25 cm long); a pure 2 cm bound would
call a 20 cm push that ends 3 cm short a disagreement, and one that moves 1 cm either way an
agreement. Each object's yaw change (the twist about the world z axis of R_after R_before^T, so
a cylinder rolling about its horizontal axis has none) is reported in both, not used.
One diagnostic side, run only where the YuMi executed the push:
  coarse  the primitive side at a 10 ms plant step (COARSE_STEP, the search's non-pushing
          selectors'): at 10 ms the compliant contact launches a pushed object (a box pushed 7.5 cm
          along x ends 3.3 cm to the side, turned 98 degrees; at 5 ms and on the YuMi it slides
          6.6 cm straight; docs/results/ch4_pushing.md), the reason the pushes run at 5 ms.
Gain sign: sign(Q*_o after - Q*_o before) in {-1, 0, +1} (|gain| <= 1e-9 counts as 0), Q*_o by the
study's GraspSets (PushStudyConfig(), seeded by the heap's seed, so both sides score the same grasp
samples of an object in a given tilt); `gain_sign_agree` when the two signs are equal.
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
from pydrake.common.eigen_geometry import Quaternion  # noqa: F401  (RotationMatrix.ToQuaternion's type)
from pydrake.math import RotationMatrix

from ms_drake.experiments.push_study import (
    HEAPS_FILE,
    GraspSets,
    PushWorld,
    PushStudyConfig,
    heap_config,
    _append,
    _center,
    _rewrite_clean,
    read_jsonl,
    state_metrics,
)
from ms_drake.parallel import run_jobs
from ms_drake.pushing.policies import POLICIES, check_push_policy
from ms_drake.scenario import ScenarioRef
from ms_drake.scenes.heaps import heap_from_dict
from ms_drake.types import Action, Heap, Push

AGREE_ABS = 0.02  # m
AGREE_REL = 0.25  # of the primitive displacement
GAIN_EPS = 1e-9
COARSE_STEP = 0.01  # s, the diagnostic primitive side's plant step
SIDES = ("full", "primitive", "coarse")  # executed in this order


def yaw_change(R0: np.ndarray, R1: np.ndarray) -> float:
    """The twist about world z of R1 R0^T (swing-twist decomposition), in (-pi, pi]."""
    q = RotationMatrix(np.asarray(R1, float) @ np.asarray(R0, float).T).ToQuaternion()
    a = 2.0 * np.arctan2(q.z(), q.w())
    return float(a) if -np.pi < a <= np.pi else float((a + np.pi) % (2 * np.pi) - np.pi)


def gain_sign(g: float) -> int:
    return 0 if abs(g) <= GAIN_EPS else int(np.sign(g))


def _centres(world: PushWorld, ids) -> dict:
    return {g.id: _center(g)[:2] for g in world.geometry(ids)}


def object_motion(world: PushWorld, ids, c0: dict, R0: dict) -> dict:
    """Per object of `ids`: final centre (bin plane), displacement, its length, yaw change, left."""
    present = set(world.present())
    c1 = _centres(world, ids)
    out = {}
    for oid in ids:
        d = c1[oid] - c0[oid]
        out[oid] = {"center": [float(v) for v in c1[oid]], "dxy": [float(v) for v in d],
                    "dist": float(np.linalg.norm(d)), "yaw": yaw_change(R0[oid], world.pose(oid)[:3, :3]),
                    "left": oid not in present}
    return out


def agreement(prim: dict, full: dict, abs_tol: float = AGREE_ABS, rel_tol: float = AGREE_REL) -> tuple[bool, dict]:
    """(agree, per object {gap, tol, ok}) of two object_motion results (module docstring)."""
    per = {}
    for oid, p in prim.items():
        f = full[oid]
        gap = float(np.linalg.norm(np.subtract(f["center"], p["center"])))
        tol = abs_tol + rel_tol * p["dist"]
        ok = (p["left"] and f["left"]) or (not p["left"] and not f["left"] and gap <= tol)
        per[oid] = {"gap": gap, "tol": tol, "ok": bool(ok)}
    return all(v["ok"] for v in per.values()), per


class FidelityPair:
    """The two worlds of one heap record, its state loaded in both, its before metrics."""

    def __init__(self, rec: dict, params: PushStudyConfig | None = None, scenario: str | ScenarioRef = "YuMiBin"):
        params = params or PushStudyConfig()
        if "state" not in rec:
            raise ValueError(f"heap {rec.get('seed')}: the record has no pushed state (stop {rec.get('stop')!r})")
        c = time.process_time()
        heap = heap_from_dict(rec["heap"])
        heap = Heap(heap.seed, heap.environment, heap.objects)
        self.seed, self.params = int(rec["seed"]), params
        self.worlds = {}
        for side in SIDES:
            p = replace(params, time_step=COARSE_STEP) if side == "coarse" else params
            w = PushWorld(heap, p, fidelity="full" if side == "full" else "primitive",
                          scenario=scenario if side == "full" else None)
            w.set_state(rec["state"])
            self.worlds[side] = (w, w.snapshot())
        self.build_cpu_s = time.process_time() - c
        prim = self.worlds["primitive"][0]
        self.ids = prim.present()
        self.sets = GraspSets(params, self.seed)
        self.before = state_metrics(prim, self.sets)
        self.c0 = _centres(prim, self.ids)
        self.R0 = {oid: prim.pose(oid)[:3, :3] for oid in self.ids}

    def execute(self, fidelity: str, push: Push) -> dict:
        """The push in one world from the loaded state: status, object motion, after Q*_o, CPU s."""
        w, snap = self.worlds[fidelity]
        w.restore(snap)
        c = time.process_time()
        try:
            done = w.execute_push(push)
        except RuntimeError as e:
            return {"status": "error", "error": str(e).splitlines()[0] if str(e) else "RuntimeError",
                    "cpu_s": time.process_time() - c}
        if isinstance(done, str):
            return {"status": "unreachable", "plan_status": done, "cpu_s": time.process_time() - c}
        sim_cpu = time.process_time() - c
        after = state_metrics(w, self.sets)
        return {"status": "ok", "sim_s": float(done), "cpu_s": sim_cpu, "overall_after": after["overall"],
                "overall_gain": after["overall"] - self.before["overall"],
                "motion": object_motion(w, self.ids, self.c0, self.R0)}

    def compare(self, policy: str, push_rec: dict, recorded_gain: float | None = None) -> dict:
        """One row: the policy's recorded push in the worlds of SIDES and their agreement."""
        push = Push(tuple(push_rec["start"]), tuple(push_rec["end"]), push_rec.get("object", ""))
        res = {}
        for side in SIDES:  # the diagnostic side only where the YuMi executed the push
            if side in ("full", "primitive") or res["full"]["status"] == "ok":
                res[side] = self.execute(side, push)
        prim, full = res["primitive"], res["full"]
        row = {"seed": self.seed, "policy": policy, "push": push_rec, "objects": len(self.ids),
               "before_overall": self.before["overall"], "recorded_overall_gain": recorded_gain,
               "push_length": float(np.linalg.norm(np.subtract(push.end, push.start)[:2])),
               "push_height": float(push.start[2]) - self.worlds["primitive"][0].workspace.floor_z, **res,
               "cpu_s": full["cpu_s"], "primitive_cpu_s": prim["cpu_s"], "build_cpu_s": self.build_cpu_s}
        if any(r["status"] != "ok" for r in res.values()):
            bad = next(side for side in SIDES if side in res and res[side]["status"] != "ok")
            row.update(status=res[bad]["status"] if bad == "full" else f"{bad}_{res[bad]['status']}",
                       plan_status=full.get("plan_status", ""), agree=None, gain_sign_agree=None)
            return row
        agree, per = agreement(prim["motion"], full["motion"])
        sf = gain_sign(full["overall_gain"])
        row.update(status="ok", agree=bool(agree), per_object=per, gain_sign=[gain_sign(prim["overall_gain"]), sf],
                   gain_sign_agree=gain_sign(prim["overall_gain"]) == sf)
        a, per_side = agreement(res["coarse"]["motion"], full["motion"])
        row.update(agree_coarse=bool(a), per_object_coarse=per_side,
                   gain_sign_agree_coarse=gain_sign(res["coarse"]["overall_gain"]) == sf)
        return row


def fidelity_job(job: tuple) -> list[dict]:
    """(heap record, policies, PushStudyConfig dict[, robot scenario]) -> one row per policy (module-level
    for pools)."""
    rec, policies, params, *rest = job
    pair = FidelityPair(rec, PushStudyConfig(**params), rest[0] if rest else "YuMiBin")
    return [pair.compare(p, rec["policies"][p]["push"], rec["policies"][p].get("overall_gain")) for p in policies]


def pushed_records(heap_dirs, heaps: int, seed_start: int = 0, policies=POLICIES) -> list[tuple[dict, list[str]]]:
    """The first `heaps` improvable heaps (by seed, seed >= seed_start) of the heap folders (a seed in
    several folders: the first folder's record), each with the `policies` that pushed on it."""
    by_seed = {}
    for d in heap_dirs:
        for r in read_jsonl(Path(d) / HEAPS_FILE):
            if r.get("improvable") and int(r["seed"]) >= seed_start:
                by_seed.setdefault(int(r["seed"]), r)
    out = []
    for s in sorted(by_seed)[:heaps]:
        r = by_seed[s]
        ps = [p for p in policies if r["policies"].get(p, {}).get("pushed")]
        out.append((r, ps))
    return out


def run_push_fidelity(heap_dirs, heaps: int, seed_start: int, out: Path, workers: int = 1, policies=POLICIES,
                      params: PushStudyConfig | None = None, progress=None,
                      scenario: str | ScenarioRef = "YuMiBin") -> dict:
    """Rows of every (heap, policy) push of the first `heaps` improvable heaps into `out` (JSON lines,
    resumable: finished (seed, policy) rows are kept and skipped), the full side on `scenario`'s
    robot. progress(rows) after each heap."""
    for p in policies:
        check_push_policy(p)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = read_jsonl(out)
    _rewrite_clean(out, rows)
    done = {(int(r["seed"]), r["policy"]) for r in rows}
    recs = pushed_records(heap_dirs, heaps, seed_start, policies)
    jobs = []
    for r, ps in recs:
        todo = [p for p in ps if (int(r["seed"]), p) not in done]
        if todo:
            jobs.append((r, todo, asdict(params or heap_config(r)), scenario))
    failed = []
    for res in run_jobs(fidelity_job, jobs, workers=workers):
        if res.ok:
            for row in res.value:
                _append(out, row)
            if progress:
                progress(res.value)
        else:
            failed.append((int(res.job[0]["seed"]), res.error.splitlines()[-1] if res.error else ""))
    wanted = {(int(r["seed"]), p) for r, ps in recs for p in ps}
    got = [r for r in read_jsonl(out) if (int(r["seed"]), r["policy"]) in wanted]
    return {"rows": got, "pushes": len(wanted), "heaps": len(recs), "new_jobs": len(jobs), "failed": failed}


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score 95 % interval of a proportion k / n ((0, 1) for n = 0)."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(max(c - h, 0.0)), float(min(c + h, 1.0))


def summarize_fidelity(rows: list[dict]) -> dict:
    """Counts by status; agreement and gain-sign agreement shares (Wilson 95 %) over the rows that
    executed in both; per policy; CPU per push (full side) and per heap world build."""

    def share(sub, key):
        k, n = sum(1 for r in sub if r[key]), len(sub)
        lo, hi = wilson(k, n)
        return {"k": k, "n": n, "share": k / n if n else 0.0, "ci95": [lo, hi]}

    ok = [r for r in rows if r["status"] == "ok"]
    out = {"pushes": len(rows), "status": {}, "agree": share(ok, "agree"),
           "gain_sign_agree": share(ok, "gain_sign_agree"), "agree_coarse": share(ok, "agree_coarse"),
           "gain_sign_agree_coarse": share(ok, "gain_sign_agree_coarse"), "policies": {}}
    for r in rows:
        out["status"][r["status"]] = out["status"].get(r["status"], 0) + 1
    rec = [r for r in rows if r["primitive"].get("status") == "ok" and r.get("recorded_overall_gain") is not None]
    out["rerun_sign_matches_record"] = share(
        [{"m": gain_sign(r["primitive"]["overall_gain"]) == gain_sign(r["recorded_overall_gain"])} for r in rec], "m")
    for p in POLICIES:
        sub = [r for r in rows if r["policy"] == p]
        if sub:
            oks = [r for r in sub if r["status"] == "ok"]
            out["policies"][p] = {"pushes": len(sub), "unreachable": sum(r["status"] == "unreachable" for r in sub),
                                  "agree": share(oks, "agree"), "gain_sign_agree": share(oks, "gain_sign_agree")}
    cpu = [r["cpu_s"] for r in ok]
    out["cpu_s_per_push"] = {"median": float(np.median(cpu)) if cpu else 0.0,
                             "mean": float(np.mean(cpu)) if cpu else 0.0,
                             "primitive_median": float(np.median([r["primitive_cpu_s"] for r in ok])) if ok else 0.0}
    builds = {int(r["seed"]): r["build_cpu_s"] for r in rows}
    out["build_cpu_s_per_heap"] = float(np.median(list(builds.values()))) if builds else 0.0
    gaps = [v["gap"] for r in ok for v in r["per_object"].values()]
    out["gap_m"] = {"median": float(np.median(gaps)) if gaps else 0.0,
                    "p90": float(np.percentile(gaps, 90)) if gaps else 0.0}
    return out


def format_fidelity(s: dict) -> str:
    a, g = s["agree"], s["gain_sign_agree"]
    lines = [f"{s['pushes']} pushes: " + ", ".join(f"{k} {v}" for k, v in sorted(s["status"].items())),
             (f"agree {a['k']}/{a['n']} = {100 * a['share']:.0f} % (Wilson 95 % {100 * a['ci95'][0]:.0f}-"
              f"{100 * a['ci95'][1]:.0f} %); gain sign agrees {g['k']}/{g['n']} = {100 * g['share']:.0f} % "
              f"({100 * g['ci95'][0]:.0f}-{100 * g['ci95'][1]:.0f} %)")]
    for key, label in (("agree_coarse", "full vs primitive at 10 ms"),
                       ("gain_sign_agree_coarse", "gain sign, full vs primitive at 10 ms"),
                       ("rerun_sign_matches_record", "primitive rerun's gain sign = the data step's")):
        v = s[key]
        lines.append(f"  {label}: {v['k']}/{v['n']} ({100 * v['ci95'][0]:.0f}-{100 * v['ci95'][1]:.0f} %)")
    for p, v in s["policies"].items():
        lines.append(f"  {p:18s} pushes {v['pushes']:3d}  unreachable {v['unreachable']:3d}  agree "
                     f"{v['agree']['k']}/{v['agree']['n']}  gain sign {v['gain_sign_agree']['k']}/"
                     f"{v['gain_sign_agree']['n']}")
    c = s["cpu_s_per_push"]
    lines.append(f"CPU s per push: full median {c['median']:.1f} (mean {c['mean']:.1f}), primitive median "
                 f"{c['primitive_median']:.1f}; worlds per heap {s['build_cpu_s_per_heap']:.1f}; centre gap "
                 f"median {100 * s['gap_m']['median']:.1f} cm, p90 {100 * s['gap_m']['p90']:.1f} cm")
    return "\n".join(lines)


def reach_probe(heap_dirs, heaps: int, seed_start: int = 0, heights=(0.0, 0.02, 0.025), policies=POLICIES) -> dict:
    """Which recorded pushes FullBackend's arm can plan (plan_push, either jaw yaw, from the park
    configuration) when the tool centre is raised to at least floor + h, for each h of `heights`
    (0: the recorded height). The closed jaw's fingertips reach 1.5 cm below the tool centre and
    the IK keeps 5 mm from the floor, so a push below ~2 cm needs the raise. Planning only."""
    recs = pushed_records(heap_dirs, heaps, seed_start, policies)
    if not recs:
        return {"pushes": 0}
    heap = heap_from_dict(recs[0][0]["heap"])
    w = PushWorld(Heap(heap.seed, heap.environment, heap.objects), fidelity="full")
    b = w.backend
    floor = w.workspace.floor_z
    out = {"pushes": 0, "reachable": {str(h): 0 for h in heights}, "push_z": []}
    for r, ps in recs:
        for p in ps:
            pr = r["policies"][p]["push"]
            out["pushes"] += 1
            out["push_z"].append(float(pr["start"][2]) - floor)
            for h in heights:
                a = np.array(pr["start"], float)
                e = np.array(pr["end"], float)
                a[2] = e[2] = max(a[2], floor + h)
                plan = b.plan(Action("push", push=Push(tuple(a), tuple(e), pr.get("object", ""))), b.initial_commands(), 0)
                out["reachable"][str(h)] += not isinstance(plan, str)
    z = np.array(out.pop("push_z"))
    out["push_height_m"] = {"median": float(np.median(z)), "below_0.02": int(np.sum(z < 0.02 - 1e-9))}
    return out
