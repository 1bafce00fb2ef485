"""The bin-search benchmark: many rollouts in parallel -> JSON lines -> summary and plots.

A run is a BinSearchConfig (policies.bin_search: the station, the heaps, the controller) searched on
heaps S..S+K-1. One JSON line per rollout (RolloutResult.record(): seed, policy, fidelity, objects,
success, actions, action_kinds, failure, stop_reason, seconds, ...; config, the run's whole config
but the seed, from which `bench replay` re-runs it; heap_digest, the fingerprint of the heap
searched, scenes.heaps.heap_digest, so that two runs compared on "the same heaps" can be checked to
be; and code, the commit that ran it, paths.code_version). A rollout that raises or whose worker
dies becomes a line with failure "worker_died" (and the error), so the benchmark goes on; such
lines are retried by the next run of the same command (resume), every other line is final. Lines
are flushed and fsync'ed one by one: an interrupted run loses at most the rollouts in flight, and a
torn last line is dropped on resume.

Statistics (our choices where the reference is silent): success rate with a percentile bootstrap
95 % interval; mean actions +/- SEM and quartiles over *all* rollouts (the reference's Table C.1
counts actions of every rollout), with a bootstrap interval of the mean; 2000 resamples, seeded.
Also the quartiles over *successful* rollouts (`success_quartiles`: Table 8.2 and the search's
efficiency metric report those).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from scipy.stats import binomtest

from ms_drake.errors import HeapError
from ms_drake.experiments.figures import figure_dir, save_png
from ms_drake.experiments.records import read_record_file
from ms_drake.experiments.rollout import REFERENCE_FAILURE_CLASSES, rollout
from ms_drake.parallel import run_jobs
from ms_drake.paths import code_version
from ms_drake.policies.bin_search import BinSearchConfig
from ms_drake.scenes.heaps import heap_digest
from ms_drake.scenes.layouts import HeapConfig, cached_heap

BOOTSTRAP = 2000


def rollout_job(job: tuple) -> dict:
    """(config as a dict, seed, heap folder) -> the record of that rollout; module-level for pickling."""
    config_dict, seed, heap_dir = job
    config = BinSearchConfig(**config_dict)
    heap = cached_heap(config.heap, seed, heap_dir)
    rec = rollout(config, seed, heap=heap).record()
    rec["heap_digest"] = heap_digest(heap)
    rec["code"] = code_version()
    rec["pid"] = os.getpid()
    return rec


# What a replay must reproduce of a record (the search, action by action).
REPLAY_KEYS = ("success", "actions", "action_kinds", "grasp_kinds", "action_successes", "failure")


def replay_job(rec: dict, heap_dir: str | None) -> tuple:
    """The rollout_job that re-runs a record: its config and seed."""
    return (rec["config"], int(rec["seed"]), heap_dir)


def _records_to_replay(path: Path, seeds=None, count: int | None = None) -> list[dict]:
    recs = [r for r in final_records(read_search_records(path)) if r.get("failure") != "worker_died"]
    if seeds is not None:
        want = {int(k) for k in seeds}
        recs = [r for r in recs if int(r["seed"]) in want]
        missing = sorted(want - {int(r["seed"]) for r in recs})
        if missing:
            raise ValueError(f"{path}: no finished record of seed(s) {', '.join(map(str, missing))}")
    elif count is not None:
        recs = recs[:count]
    return recs


def heap_digest_job(job: tuple) -> str:
    """(heap config as a dict, seed, heap folder) -> the digest of that heap (read from the cache,
    else generated and cached); module-level for pickling."""
    heap, seed, heap_dir = job
    return heap_digest(cached_heap(HeapConfig(**heap), seed, heap_dir))


def check_record_heaps(path: Path, heap_dir: str | None = None, seeds=None, count: int | None = None,
                       workers: int = 1, progress=None) -> list[dict]:
    """The heap half of replay_records, without the searches: whether each record's heap (from
    `heap_dir`, else regenerated from its seed) has the record's digest. Heaps regenerate exactly on
    one machine; a drop on another CPU can end elsewhere, which this finds cheaply. Rows: seed,
    policy, same, differs (["heap"] or []), heap_same (None without a recorded digest), code."""
    by_job = {}  # one heap job for every record of that heap (a file may hold several policies)
    for r in _records_to_replay(path, seeds, count):
        job = (tuple(sorted(r["config"]["heap"].items())), int(r["seed"]), heap_dir)
        by_job.setdefault(job, []).append(r)
    rows = []
    for res in run_jobs(heap_digest_job, [(dict(j[0]), *j[1:]) for j in by_job], workers=workers):
        err = (res.error or "").strip().splitlines()
        for rec in by_job[(tuple(sorted(res.job[0].items())), *res.job[1:])]:
            heap_same = (res.value == rec["heap_digest"]) if res.ok and rec.get("heap_digest") else None
            row = dict(seed=int(rec["seed"]), policy=rec["policy"], same=res.ok and heap_same is not False,
                       differs=["error"] if not res.ok else ([] if heap_same is not False else ["heap"]),
                       heap_same=heap_same, code=rec.get("code", ""), code_now=code_version())
            if not res.ok:
                row["error"] = err[-1] if err else ""
            rows.append(row)
            if progress:
                progress(row)
    return sorted(rows, key=lambda x: (x["policy"], x["seed"]))


def replay_records(path: Path, heap_dir: str | None = None, seeds=None, count: int | None = None,
                   workers: int = 1, progress=None) -> list[dict]:
    """Re-run the records of a `bench search` file (those of `seeds`, else the first `count`, else
    all) and compare each with its record (REPLAY_KEYS, and the heap's digest where the record has
    one). Returns one row per record: seed, policy, same (bool), differs (the keys that differ),
    heap_same (None when the record has no digest), code (recorded) and code_now."""
    recs = _records_to_replay(path, seeds, count)
    def key(job):  # the job without its heap folder, hashable
        return (json.dumps(job[0], sort_keys=True), job[1])

    by_job = {key(replay_job(r, heap_dir)): r for r in recs}
    rows = []
    for res in run_jobs(rollout_job, [replay_job(r, heap_dir) for r in recs], workers=workers):
        old = by_job[key(res.job)]
        if not res.ok:
            err = (res.error or "").strip().splitlines()
            row = dict(seed=int(old["seed"]), policy=old["policy"], same=False, differs=["error"], heap_same=None,
                       code=old.get("code", ""), code_now=code_version(), error=err[-1] if err else "")
        else:
            new = res.value
            differs = [k for k in REPLAY_KEYS if new.get(k) != old.get(k)]
            heap_same = new["heap_digest"] == old["heap_digest"] if old.get("heap_digest") else None
            row = dict(seed=int(old["seed"]), policy=old["policy"], same=not differs and heap_same is not False,
                       differs=differs, heap_same=heap_same, code=old.get("code", ""), code_now=new["code"])
        rows.append(row)
        if progress:
            progress(row)
    return sorted(rows, key=lambda x: (x["policy"], x["seed"]))


def read_records(path: Path) -> list[dict]:
    """Records of a JSON-lines result file a run appends to (records.read_record_file, resuming): a
    missing file has none, a torn last line (killed mid-write) is cut from the file, any other line
    that is not a record with a seed raises RecordFileError naming the file and the line."""
    return read_record_file(path, ("seed",), resume=True)


def read_search_records(path: Path) -> list[dict]:
    """read_records of a `bench search` file: every record must also hold its config."""
    return read_record_file(path, ("seed", "config"), writer="bench search", resume=True)


def config_key(rec: dict) -> str:
    """The record's config as canonical JSON: the records of one run share it."""
    return json.dumps(rec["config"], sort_keys=True)


def final_records(recs: list[dict]) -> list[dict]:
    """The last record per (seed, config): a retried rollout replaces its failure; runs with other
    configs in the same file stay apart."""
    return list({(int(r["seed"]), config_key(r)): r for r in recs}.values())


def result_file(out_dir, config: BinSearchConfig) -> Path:
    """<out_dir>/<policy>_<layout>_N<N>_H<H>.jsonl."""
    return Path(out_dir) / f"{config.policy}_{config.heap.layout}_N{config.heap.objects}_H{config.horizon}.jsonl"


def _done_seeds(path: Path, key: str) -> set[int]:
    return {int(r["seed"]) for r in final_records(read_search_records(path))
            if config_key(r) == key and r.get("failure") != "worker_died"}


def run_suite(runs: list[tuple[BinSearchConfig, Path]], heaps: int, seed_start: int, workers: int = 1,
              use_ray: bool = False, ray_address: str | None = None, progress=None,
              heap_dir: str | None = None) -> list[dict]:
    """The missing rollouts of every run (a config and its result file) on seeds S..S+K-1, all
    through ONE pool of `workers` processes; each record is appended (flushed, fsync'ed) to its
    run's file as it completes, so a killed run loses only the rollouts in flight and the same
    command resumes it (a record counts as done when its config is the run's). Jobs are queued run
    by run, so with a shared `heap_dir` the first run's workers generate the heaps in parallel, each
    heap once, and later runs load them. progress(rec) is called with each record; an object with a
    `start(done, todo)` method is told first what is already done and what will run.
    Returns one summary per run, in order."""
    seeds = set(range(seed_start, seed_start + heaps))
    jobs, done, keys = [], [], []
    for n, (config, out) in enumerate(runs):
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        d = config.to_dict()
        d.pop("seed")
        keys.append(json.dumps(d, sort_keys=True))
        done.append(_done_seeds(out, keys[-1]))
        jobs += [(d, k, heap_dir, n) for k in sorted(seeds - done[-1])]
    if progress is not None and hasattr(progress, "start"):  # before any rollout: (already done, to run)
        progress.start(sum(len(d & seeds) for d in done), len(jobs))
    t0 = time.perf_counter()
    handles = {}
    try:
        for r in run_jobs(_suite_job, jobs, workers=workers, use_ray=use_ray, ray_address=ray_address):
            config_dict, seed, _, n = r.job
            if r.ok:
                rec = r.value
            else:
                err = (r.error or "").strip().splitlines()
                rec = dict(seed=seed, policy=config_dict["policy"], fidelity=config_dict["fidelity"],
                           objects=config_dict["heap"]["objects"], success=False, actions=0, action_kinds=[],
                           failure="worker_died", stop_reason="", error=err[-1] if err else "", seconds=0.0,
                           config=config_dict)
            if n not in handles:
                handles[n] = open(runs[n][1], "a")
            f = handles[n]
            f.write(json.dumps(rec) + "\n")
            f.flush()
            os.fsync(f.fileno())
            if progress is not None:
                progress(rec)
    finally:
        for f in handles.values():
            f.close()
    wall = time.perf_counter() - t0
    out = []
    for n, (config, path) in enumerate(runs):
        recs = [r for r in final_records(read_search_records(path)) if config_key(r) == keys[n] and int(r["seed"]) in seeds]
        summ = summarize(recs)
        summ.update(resumed=len(done[n] & seeds), ran=sum(1 for j in jobs if j[3] == n), wall_seconds=wall)
        out.append(summ)
    return out


def _suite_job(job: tuple) -> dict:
    return rollout_job(job[:3])


def run_bench(config: BinSearchConfig, heaps: int, seed_start: int, out: Path, workers: int = 1,
              use_ray: bool = False, ray_address: str | None = None, progress=None,
              heap_dir: str | None = None) -> dict:
    """Run the missing rollouts of `config` on seeds S..S+K-1, append them to `out`; returns the summary."""
    return run_suite([(config, Path(out))], heaps, seed_start, workers=workers, use_ray=use_ray,
                     ray_address=ray_address, progress=progress, heap_dir=heap_dir)[0]


def truncate_record(rec: dict, horizon: int) -> dict:
    """The record a rollout would have had with the smaller action budget `horizon`. The first
    `horizon` actions of a rollout do not depend on its budget (the selector's choices, the grasp
    draws and the simulation are functions of the seed and the step; the budget is checked only
    before choosing the next action), so: fewer than `horizon` actions -> unchanged; more -> it
    stops after `horizon` actions with failure "horizon"; exactly `horizon` -> unchanged when it
    ended by success, target_removed, sim_blew_up or timeout (the last two: only the failure's
    name could differ, never success or the count), else "horizon" (the budget is checked before
    a no_action / too_many_pushes choice). Lets Table 8.2's Random and Largest at H = 10 come from
    the Ch. 7 runs at 2N (tests/test_harness.py checks it against a run at the smaller budget).
    Timing fields stay those of the whole rollout; `truncated_from` keeps its action count."""
    r = dict(rec)
    n = int(r["actions"])
    if r.get("failure") == "worker_died" or n < horizon or (
            n == horizon and (r.get("success") or r.get("failure") in ("target_removed", "sim_blew_up", "timeout"))):
        return r
    r.update(actions=horizon, action_kinds=list(r.get("action_kinds", []))[:horizon], success=False,
             failure="horizon", stop_reason="horizon", truncated_from=n)
    if "config" in r:
        r["config"] = {**r["config"], "horizon": int(horizon)}
    for k in ("grasp_kinds", "action_successes"):
        if k in r:
            r[k] = list(r[k])[:horizon]
    r.pop("grasp_successes", None)
    r.pop("grasp_plans", None)
    return r


def _boot(x: np.ndarray, stat, rng) -> tuple[float, float]:
    if len(x) == 0:
        return (float("nan"), float("nan"))
    idx = rng.integers(0, len(x), size=(BOOTSTRAP, len(x)))
    vals = stat(x[idx], axis=1)
    return float(np.percentile(vals, 2.5)), float(np.percentile(vals, 97.5))


def summarize(recs: list[dict], seed: int = 0) -> dict:
    """Success rate, mean actions +/- SEM, quartiles, bootstrap 95 % intervals, failure counts."""
    rng = np.random.default_rng(seed)
    succ = np.array([bool(r["success"]) for r in recs], float)
    acts = np.array([int(r["actions"]) for r in recs], float)
    n = len(recs)
    failures: dict[str, int] = {}
    for r in recs:
        if not r["success"]:
            failures[r.get("failure") or "unknown"] = failures.get(r.get("failure") or "unknown", 0) + 1
    secs = np.array([float(r.get("seconds", 0.0)) for r in recs if r.get("failure") != "worker_died"])
    cpu = np.array([float(r["cpu_seconds"]) for r in recs if "cpu_seconds" in r])
    return dict(
        rollouts=n,
        success_rate=float(succ.mean()) if n else float("nan"),
        success_ci=_boot(succ, np.mean, rng),
        mean_actions=float(acts.mean()) if n else float("nan"),
        sem_actions=float(acts.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan"),
        actions_ci=_boot(acts, np.mean, rng),
        quartiles=tuple(float(q) for q in np.percentile(acts, [25, 50, 75])) if n else (float("nan"),) * 3,
        success_quartiles=(tuple(float(q) for q in np.percentile(acts[succ > 0], [25, 50, 75])) if succ.any()
                           else (float("nan"),) * 3),
        median_seconds=float(np.median(secs)) if len(secs) else float("nan"),
        median_cpu_seconds=float(np.median(cpu)) if len(cpu) else float("nan"),
        failures=failures)


def check_same_heaps(recs_a: list[dict], recs_b: list[dict], names=("A", "B")) -> None:
    """Raise HeapError when two runs' records of the same seed searched different heaps
    (their `heap_digest`s differ: a heap cache made by other generator code, or a generator that
    changed between the runs). Records without a digest are not checked."""
    da = {int(r["seed"]): r["heap_digest"] for r in final_records(recs_a) if r.get("heap_digest")}
    db = {int(r["seed"]): r["heap_digest"] for r in final_records(recs_b) if r.get("heap_digest")}
    bad = sorted(k for k in set(da) & set(db) if da[k] != db[k])
    if bad:
        shown = ", ".join(map(str, bad[:10])) + (" ..." if len(bad) > 10 else "")
        raise HeapError(
            f"{names[0]} and {names[1]} searched different heaps on {len(bad)} seed(s) ({shown}): their "
            "records' heap_digest differ. Re-run one of them on the other's heap cache (--heap-dir), or both "
            "on a fresh one, before comparing them.")


def paired_comparison(recs_a: list[dict], recs_b: list[dict], names=("A", "B")) -> dict:
    """Success of two policies on the same heaps (seeds in both): heaps only A solves, only B
    solves, both, neither, and the two-sided exact sign test (binomial, p = 1/2) on the
    discordant heaps; diff: A's success minus B's in points, diff_ci its paired bootstrap 95 %
    interval (the heaps resampled 10,000 times, seed 0). Records that carry heap digests must agree
    on them (check_same_heaps; `names` name the two runs in its error)."""
    check_same_heaps(recs_a, recs_b, names)
    a = {int(r["seed"]): bool(r["success"]) for r in final_records(recs_a)}
    b = {int(r["seed"]): bool(r["success"]) for r in final_records(recs_b)}
    seeds = sorted(set(a) & set(b))
    only_a = [k for k in seeds if a[k] and not b[k]]
    only_b = [k for k in seeds if b[k] and not a[k]]
    both = sum(1 for k in seeds if a[k] and b[k])
    n = len(only_a) + len(only_b)
    p = float(binomtest(len(only_a), n, 0.5).pvalue) if n else 1.0
    d = np.array([float(a[k]) - float(b[k]) for k in seeds])
    diff, ci = 100.0 * float(d.mean()) if len(d) else 0.0, (0.0, 0.0)
    if len(d):
        means = d[np.random.default_rng(0).integers(0, len(d), (10_000, len(d)))].mean(axis=1)
        ci = tuple(100.0 * float(x) for x in np.percentile(means, [2.5, 97.5]))
    return dict(heaps=len(seeds), only_a=only_a, only_b=only_b, both=both, neither=len(seeds) - both - n, p=p,
                diff=diff, diff_ci=ci)


def action_breakdown(recs: list[dict]) -> dict:
    """Table C.2: grasps and pushes, pushes as a share of actions, and per gripper kind the grasps
    and their success rate (records with `grasp_kinds` / `action_successes` only for the kinds)."""
    kinds = [k for r in recs for k in r.get("action_kinds", [])]
    out = {"actions": len(kinds), "grasps": kinds.count("grasp"), "pushes": kinds.count("push")}
    out["push_share"] = out["pushes"] / out["actions"] if out["actions"] else float("nan")
    for g in ("parallel_jaw", "suction"):
        ok = [s for r in recs for k, s in zip(r.get("grasp_kinds", []), r.get("action_successes", [])) if k == g]
        out[g] = {"grasps": len(ok), "success_rate": float(np.mean(ok)) if ok else float("nan")}
    out["with_kinds"] = sum(1 for r in recs if "grasp_kinds" in r)
    return out


def failed_grasps(recs: list[dict]) -> dict:
    """Where the failed grasps of the rollouts went (records with `grasp_objects`, see
    rollout.RolloutResult): grasps, failed, failed on the target, failed right after a failed grasp
    on the same object (a retry), the failures per grasp quality, and per object model
    (`by_object`: the object id without its "objNN__" heap index, e.g. "ycb_unseen__037_scissors")
    [grasps, failed], most failures first."""
    out = {"rollouts": sum(1 for r in recs if "grasp_objects" in r), "grasps": 0, "failed": 0,
           "failed_on_target": 0, "failed_retries": 0, "failed_by_quality": {}, "by_object": {}}
    for r in recs:
        prev = None
        for obj, ok, q in zip(r.get("grasp_objects", []), r.get("action_successes", []),
                              r.get("grasp_qualities", [])):
            if not obj:  # a push
                prev = None
                continue
            out["grasps"] += 1
            model = obj.split("__", 1)[1] if obj.startswith("obj") and "__" in obj else obj
            counts = out["by_object"].setdefault(model, [0, 0])
            counts[0] += 1
            counts[1] += not ok
            if not ok:
                out["failed"] += 1
                out["failed_on_target"] += obj == "target"
                out["failed_retries"] += prev == (obj, False)
                key = f"{q:.2f}"
                out["failed_by_quality"][key] = out["failed_by_quality"].get(key, 0) + 1
            prev = (obj, bool(ok))
    out["failed_by_quality"] = dict(sorted(out["failed_by_quality"].items()))
    out["by_object"] = dict(sorted(out["by_object"].items(), key=lambda kv: (-kv[1][1], kv[0])))
    return out


def failure_classes(recs: list[dict]) -> dict:
    """Failures in the reference's three modes (REFERENCE_FAILURE_CLASSES; lines 1326-1328: failures
    6-12 % of the rollouts, 85-90 % of them "no action"): rollouts, failures and their share of the
    rollouts, and per class its count and share of the failures."""
    fails = [r.get("failure") or "unknown" for r in recs if not r["success"]]
    out = {"rollouts": len(recs), "failures": len(fails),
           "failure_share": len(fails) / len(recs) if recs else float("nan")}
    for c in ("no_action", "target_removed", "horizon", "other"):
        k = sum(1 for f in fails if REFERENCE_FAILURE_CLASSES.get(f, "other") == c)
        out[c] = {"count": k, "share": k / len(fails) if fails else float("nan")}
    return out


def format_summary(policy: str, s: dict) -> str:
    q = s["quartiles"]
    fails = ", ".join(f"{k} {v}" for k, v in sorted(s["failures"].items())) or "none"
    return (f"{policy}: {s['rollouts']} rollouts, success {100 * s['success_rate']:.1f} % "
            f"[{100 * s['success_ci'][0]:.1f}, {100 * s['success_ci'][1]:.1f}], "
            f"actions {s['mean_actions']:.2f} +/- {s['sem_actions']:.2f} (SEM) "
            f"[{s['actions_ci'][0]:.2f}, {s['actions_ci'][1]:.2f}], quartiles {q[0]:g}/{q[1]:g}/{q[2]:g} "
            f"(successes only: {'/'.join(f'{x:g}' for x in s['success_quartiles'])}), "
            f"median {s['median_seconds']:.1f} s wall / {s['median_cpu_seconds']:.1f} s CPU per rollout; failures: {fails}")


def plot(files: list[Path], out_dir: Path) -> list[Path]:
    """Fig. 7.4 B (cumulative successes vs actions, one curve per policy) and Fig. 8.6 (histogram
    of actions per successful rollout) as PNG. Returns the written paths."""
    by_policy: dict[str, list[dict]] = {}
    for f in files:
        for r in final_records(read_search_records(Path(f))):
            by_policy.setdefault(f"{r.get('policy')} (N={r.get('objects')})", []).append(r)
    out_dir = figure_dir(out_dir)
    fig, ax = plt.subplots(figsize=(6, 4))
    top = max([int(r["actions"]) for rs in by_policy.values() for r in rs] or [1])
    xs = np.arange(0, top + 1)
    for n, (name, rs) in enumerate(sorted(by_policy.items())):
        acts = np.array([int(r["actions"]) for r in rs if r["success"]])
        ax.step(xs, [(acts <= x).sum() for x in xs], where="post", color=f"C{n}", label=f"{name}, {len(rs)} heaps")
    ax.set_xlabel("actions")
    ax.set_ylabel("cumulative successes")
    ax.set_title("Successful searches within k actions (cf. Fig. 7.4 B)")
    ax.legend(fontsize=7)
    p1 = save_png(fig, out_dir / "cumulative_successes.png")
    # Fig. 8.6: side-by-side bars per policy, each policy's median as a dashed line of its colour
    fig, ax = plt.subplots(figsize=(6, 4))
    names = sorted(by_policy)
    width = 0.8 / max(len(names), 1)
    ks = np.arange(1, top + 1)
    for n, name in enumerate(names):
        acts = np.array([int(r["actions"]) for r in by_policy[name] if r["success"]])
        label = f"{name}, median {np.median(acts):g}" if len(acts) else name
        ax.bar(ks + (n - (len(names) - 1) / 2) * width, [(acts == k).sum() for k in ks], width=width,
               color=f"C{n}", label=label)
        if len(acts):
            ax.axvline(float(np.median(acts)), color=f"C{n}", linestyle="--", linewidth=1)
    ax.set_xticks(ks)
    ax.set_xlabel("actions to extract the target")
    ax.set_ylabel("successful rollouts")
    ax.set_title("Actions per successful search (cf. Fig. 8.6)")
    ax.legend(fontsize=7)
    p2 = save_png(fig, out_dir / "actions_histogram.png")
    return [p1, p2]
