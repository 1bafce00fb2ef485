"""`ms-drake reproduce NAME`: one recipe per table and figure of the reference that ms_drake reproduces.

A recipe is a small record -- its name, a one-line title, the reference's figures, a small and a
full size, the seed it starts from -- and a run function that calls the experiment functions the
`ms-drake bench ...` / `data ...` commands call. `reproduce(name, ...)` runs one and writes

- OUT/NAME/: the records, in the form the bench writes them (its JSON lines, dataset shards and
  caches). The benches skip the work their records already hold, so a second run with the same
  arguments does no new work, and a full run goes on from a small run's records (the seeds and
  shards of the small size are the first ones of the full size);
- OUT/NAME/NAME.md: a markdown table, our figure and its 95 % interval beside the reference's, the
  command that made it, the machine (platform and CPU count), the date and the code's commit,
  followed by the bench's own table where it prints one;
- OUT/NAME/*.png: the bench's figure, where it draws one (`plot_push`, `plot_shelf`).

Sizes: "small" takes <= 15 minutes on 2 cores (measured minutes below); "full" is the
reference's count (its number of grasps, images, scenes or heaps). `sizes` (a dict, for the tests)
overrides a size's counts through the Python API.

Intervals: a percentile bootstrap 95 % interval over the bench's units (grasped objects, images,
scenes, heaps), as the benches that report an interval compute it (ms_drake.experiments.harness:
2,000 resamples, seeded); where the bench reports one (Table 9.1's success rates) it is taken as
reported. A statistic that is recomputed from scratch for every resample (the leave-one-object-out
AP / AR of Tables 2.1 and 3.1, COCO mask AP) gets 200 resamples. Table 6.1's AP is pooled over all
queries of all scenes and the bench keeps no per-query scores, so it has no interval.

Minutes of the small sizes (`Recipe.minutes_small`): CPU minutes of `reproduce(NAME)` with one
worker from empty records (the process and its workers: on a free core, its wall time), 2-core AMD
EPYC, no GPU, shared with other jobs (load 1-5), 2026-12-07: table_2_1 4.1, table_3_1 4.7, fig_4_2
6.3, table_b_1 10.4, table_6_1 4.1, table_6_3 9.3, table_c_1 19.1, fig_7_4 30.3, table_8_1 5.9,
table_8_2 21.7, table_9_1 12.4, table_9_2 2.7 (two workers halve the wall time of the bin searches).
"""

from __future__ import annotations

import json
import math
import os
import platform
import resource
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from functools import partial
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from ms_drake.errors import MsDrakeError
from ms_drake.experiments.collision_learning import bench_collision
from ms_drake.experiments.occupancy_data import load_dataset, write_occupancy_dataset
from ms_drake.experiments.occupancy_learning import (
    bench_occupancy,
    diagonals,
    occupancy_metrics,
    predict,
    target_scales,
)
from ms_drake.experiments.push_study import METRICS as PUSH_METRICS
from ms_drake.experiments.push_study import (
    PushStudyConfig,
    format_push_table,
    improvable_records,
    plot_push,
    read_jsonl,
    run_push_bench,
    summarize_push,
    write_push_heaps,
)
from ms_drake.experiments.rearrange import rearrange_records, rearrange_table, run_rearrange_bench
from ms_drake.experiments.figures import save_png
from ms_drake.experiments.harness import paired_comparison, plot, read_search_records, run_suite
from ms_drake.experiments.records import read_record_file
from ms_drake.experiments.segmentation_learning import bench_job as segmentation_job
from ms_drake.experiments.shelf import plot_shelf, record_scenario, run_shelf_bench, shelf_records, shelf_table
from ms_drake.experiments.shelf_physics import physics_records, physics_table, run_shelf_physics_bench
from ms_drake.grasping import labels as grasp_labels
from ms_drake.parallel import run_jobs
from ms_drake.paths import code_version
from ms_drake.perception.occupancy_net import TARGET_RATIOS
from ms_drake.perception.occupancy_net import load_model as load_occupancy_model
from ms_drake.perception.segmentation import coco_metrics
from ms_drake.policies.bin_search import load_bin_search_config
from ms_drake.policies.shelf_search import ShelfSearchConfig
from ms_drake.pushing import POLICIES as PUSH_POLICIES
from ms_drake.robots import PadConfig
from ms_drake.scenes.layouts import HeapConfig

SIZES = ("small", "full")
BOOTSTRAP = 2000  # resamples of a mean or a ratio (as harness.summarize)
BOOTSTRAP_RECOMPUTED = 200  # resamples of a statistic recomputed from scratch per resample
DEFAULT_OUT = Path("out/reproduce")


class ReproduceError(MsDrakeError, ValueError):
    """An unknown recipe name or size, or a size override with unknown counts."""


# ----------------------------------------------------------------------------------- data types
@dataclass(frozen=True)
class Ref:
    """One figure of the reference: `value` a number (in the unit of our matching row) or text."""
    row: str
    metric: str
    value: float | str


@dataclass
class Measure:
    """One of our figures: `value` (a number or text), its 95 % interval (None: none), its format."""
    row: str
    metric: str
    value: float | str
    interval: tuple[float, float] | None = None
    fmt: str = "{:.3g}"


@dataclass
class Result:
    """What a run function returns: our figures, the PNG files, the record files, the bench's own
    table (markdown) and notes for the reader."""
    measures: list[Measure]
    figures: list[Path] = field(default_factory=list)
    records: list[Path] = field(default_factory=list)
    bench_table: str = ""
    notes: list[str] = field(default_factory=list)


class Progress:
    """Counts finished work items for the caller's callback `(done, total)`; items a resumed run
    finds in its records count as done at once."""

    def __init__(self, callback: Callable[[int, int], None] | None, total: int):
        self.callback, self.total, self.done = callback, int(total), 0

    def set(self, done: int) -> None:
        self.done = max(0, min(int(done), self.total))
        if self.callback is not None:
            self.callback(self.done, self.total)

    def add(self, k: int = 1) -> None:
        self.set(self.done + k)


@dataclass
class Run:
    """A recipe's settings for its run function: the records' folder OUT/NAME, the size's counts,
    the first seed, workers / Ray (for the benches that take them), progress and a log."""
    dir: Path
    size: dict
    seed_start: int
    workers: int
    use_ray: bool
    progress: Progress
    log: Callable[[str], None]


@dataclass(frozen=True)
class Recipe:
    name: str
    title: str  # one line a robotics user understands
    reference: tuple[Ref, ...]  # the reference's figures (line numbers of its text in the code comments)
    small: dict  # counts of the small size (<= 15 minutes on 2 cores)
    full: dict  # counts of the full size (the reference's)
    run: Callable[[Run], Result]
    total: Callable[[dict], int]  # work items of a size, for the progress bar
    seed_start: int = 0
    interval: str = ""  # how our interval is made (one line in the markdown)
    minutes_small: float | None = None  # CPU minutes of the small size with one worker (module docstring)
    options: tuple[str, ...] = ()  # further keys `sizes` may give (tiny runs in the tests)


# ----------------------------------------------------------------------------------- helpers
def _records(path: Path) -> list[dict]:
    """The records of a JSON-lines file (none when it is missing; a torn last line is dropped)."""
    return read_record_file(path, required=(), resume=True)


def _append(path: Path, rec: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        f.write(json.dumps(rec) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _interval(n: int, stat: Callable[[np.ndarray], float | np.ndarray], resamples: int = BOOTSTRAP,
              seed: int = 0):
    """Percentile bootstrap 95 % interval of `stat(indices)` over n units drawn with replacement;
    a vector statistic gives one interval per component. None with fewer than two units."""
    if n < 2:
        return None
    rng = np.random.default_rng(seed)
    vals = np.array([np.atleast_1d(stat(rng.integers(0, n, n))) for _ in range(resamples)], float)
    out = []
    for col in vals.T:
        col = col[np.isfinite(col)]
        out.append((float(np.percentile(col, 2.5)), float(np.percentile(col, 97.5))) if len(col) else None)
    return out if vals.shape[1] > 1 else out[0]


def _mean_interval(x) -> tuple[float, float] | None:
    x = np.asarray(x, float)
    return _interval(len(x), lambda i: x[i].mean())


def _ratio_interval(a, b, scale: float = 1.0) -> tuple[float, float] | None:
    """Interval of scale * sum(a) / sum(b), units resampled together (e.g. placements per object)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return _interval(len(a), lambda i: scale * a[i].sum() / max(b[i].sum(), 1e-12))


def _scaled(interval, k: float):
    return None if interval is None else (k * interval[0], k * interval[1])


def _median_iqr(q) -> str:
    """Quartiles (q1, median, q3) in the reference's "Median Steps (IQR)" form: 'median (q1 - q3)'."""
    return "-" if any(math.isnan(v) for v in q) else f"{q[1]:.1f} ({q[0]:.1f} - {q[2]:.1f})"


def _quartiles(x) -> str:
    """_median_iqr of the values x ('-' for none)."""
    return _median_iqr(np.percentile(np.asarray(x, float), [25, 50, 75])) if len(x) else "-"


def _refs(rows, metrics: tuple[str, ...], values) -> tuple[Ref, ...]:
    """The reference's figures of a table given row by row: values[i][j] is rows[i]'s metrics[j]."""
    return tuple(Ref(row, metric, v) for row, vals in zip(rows, values, strict=True)
                 for metric, v in zip(metrics, vals, strict=True))


def _seeds(run: Run, count: int) -> range:
    return range(run.seed_start, run.seed_start + int(count))


# ----------------------------------------------------------------------------------- Tables 2.1 / 3.1
# The physics labels and the AP / AR table as docs/results/ch2_3_grasping.md reports
# them (sims/grasp_labels.py): the 20 x 20 mm pad, 4 parameter sets, robust models with N = 5.
LABEL_PAD = PadConfig(width=0.02, length=0.02, hydroelastic_modulus=1e5, relaxation_time=0.05, mu_static=0.8,
                      mu_dynamic=0.8, resolution_hint=0.003)
PARAM_SETS = 4
ROBUST_SAMPLES = 5


def _grasp_total(models: tuple[str, ...], size: dict) -> int:
    return size["objects"] * size["grasps"] + len(models) * PARAM_SETS * 2


def _loo_bootstrap(labels: Path, predictions: Path, groups: set, seed: int = 0) -> dict:
    """{(model, robust): [(AP lo, hi), (AR lo, hi)]} for the (model, robust) `groups`: the
    leave-one-object-out table recomputed on objects drawn with replacement (a drawn object's copies
    are distinct objects), BOOTSTRAP_RECOMPUTED times."""
    rows = [{k: r[k] for k in ("object", "index", "label")} for r in _records(labels)]
    preds = [{k: p[k] for k in ("model", "robust", "params", "quality", "ms_per_grasp")} for p in _records(predictions)
             if (p["model"], p["robust"]) in groups]
    objects = sorted({r["object"] for r in rows})
    members = {o: [i for i, r in enumerate(rows) if r["object"] == o] for o in objects}
    if len(objects) < 2:
        return {}
    rng = np.random.default_rng(seed)
    draws: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        lab, pre = Path(tmp) / "labels.jsonl", Path(tmp) / "predictions.jsonl"
        for _ in range(BOOTSTRAP_RECOMPUTED):
            new, cols = [], []
            for k, j in enumerate(rng.integers(0, len(objects), len(objects))):
                for i in members[objects[j]]:
                    new.append(dict(rows[i], object=f"{objects[j]}#{k}"))
                    cols.append(i)
            keys = grasp_labels._keys_hash(new)
            lab.write_text("".join(json.dumps(r) + "\n" for r in new))
            pre.write_text("".join(json.dumps(dict(p, quality=[p["quality"][i] for i in cols], keys_sha1=keys)) + "\n"
                                   for p in preds))
            with warnings.catch_warnings():  # a draw without an object of both outcomes has no AP: NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                table = grasp_labels.loo_table(lab, pre)
            for t in table:
                draws.setdefault((t["model"], t["robust"]), []).append((t["AP"], t["AR"]))
    out = {}
    for key, v in draws.items():
        v = np.array(v, float)
        out[key] = [(float(np.nanpercentile(v[:, c], 2.5)), float(np.nanpercentile(v[:, c], 97.5)))
                    if np.isfinite(v[:, c]).any() else None for c in (0, 1)]
    return out


def _grasp_table(run: Run, models: tuple[str, ...], rows: tuple[tuple[str, str, bool], ...]) -> Result:
    """Physics labels on `objects` x `grasps` (each simulated `trials` times), every model's
    quality under PARAM_SETS parameter sets, the leave-one-object-out AP / AR table
    (ms_drake.grasping.labels, as sims/grasp_labels.py runs it). rows: (row name, model, robust)."""
    s = run.size
    folder = run.dir / f"objects{s['objects']}_grasps{s['grasps']}_trials{s['trials']}"
    labels, predictions = folder / "labels.jsonl", folder / "predictions.jsonl"
    names = grasp_labels.default_label_objects(s["objects"])
    run.progress.set(len(_records(labels)))
    grasp_labels.generate_labels(names, labels, s["grasps"], s["trials"], run.seed_start, pad=LABEL_PAD,
                                 log=lambda msg: run.progress.set(len(_records(labels))))
    base = s["objects"] * s["grasps"]
    run.progress.set(base + len(_records(predictions)))
    grasp_labels.predict(labels, predictions, models, PARAM_SETS, ROBUST_SAMPLES, seed=run.seed_start,
                         log=lambda msg: run.progress.add(1))
    table = {(t["model"], t["robust"]): t for t in grasp_labels.loo_table(labels, predictions)}
    ci = _loo_bootstrap(labels, predictions, {(m, ROBUST_SAMPLES if robust else 0) for _, m, robust in rows if m})
    measures = []
    for row, model, robust in rows:
        t = table.get((model, ROBUST_SAMPLES if robust else 0))
        if t is None:
            continue
        iv = ci.get((model, t["robust"]), [None, None])
        measures += [Measure(row, "AP", t["AP"], iv[0], "{:.2f}"), Measure(row, "AR", t["AR"], iv[1], "{:.2f}"),
                     Measure(row, "ms / grasp", t["ms_per_grasp"], None, "auto")]
    n = len(_records(labels))
    pos = sum(r["label"] >= 0.5 for r in _records(labels))
    return Result(measures, records=[labels, predictions],
                  bench_table=grasp_labels.format_table(list(table.values()), n, len(names)),
                  notes=[f"{n} grasps on {len(names)} objects ({', '.join(names)}); physics trials per grasp: "
                         f"{s['trials']}; "
                         f"positives (success rate >= 0.5): {pos}. Our objects are simulated ones (procedural, YCB, "
                         "random_urdfs meshes), the reference's 3D-printed objects on a physical YuMi; ms / grasp is "
                         "wall time per grasp inside the prediction run (the reference's is on its own machine).",
                         "Robust rows: N = 5 perturbed trials; parameters chosen per held-out object from "
                         f"{PARAM_SETS} sets drawn from the reference's ranges (the reference: 100)."])


# Table 2.1 (lines 237-244): AP, AR, run time (s / grasp, given here in ms). The reference's "Point"
# rows are soft point contacts (its baseline, lines 211-213): our soft_point model.
TABLE_2_1_ROWS = (("Point (ours: soft point)", "soft_point", False),
                  ("Point Robust (ours: soft point)", "soft_point", True),
                  ("Elliptical Area", "elliptical", False), ("Elliptical Area Robust", "elliptical", True),
                  ("Flex Simulation", "", False), ("REACH (non-robust)", "reach", False), ("REACH", "reach", True))
TABLE_2_1_REF = _refs([r[0] for r in TABLE_2_1_ROWS], ("AP", "AR", "ms / grasp"),
                      [(0.76, 0.55, 6.0), (0.82, 0.55, 40.0), (0.73, 0.47, 24.0), (0.73, 0.47, 220.0),
                       (0.86, 0.54, 10300.0), (0.77, 0.72, 53.0), (0.82, 0.66, 520.0)])
# Table 3.1 (lines 432-436): mean AP, mean AR (+- 0.01-0.02 over 5 runs), runtime ms / grasp. Its
# parameters include the robustness sample deviation (line 440): the robust models.
TABLE_3_1_ROWS = (("Point (ours: soft point, robust)", "soft_point", True), ("REACH (robust)", "reach", True),
                  ("MFE (robust)", "mfe", True), ("6DFC (robust)", "6dfc", True))
TABLE_3_1_REF = _refs([r[0] for r in TABLE_3_1_ROWS], ("AP", "AR", "ms / grasp"),
                      [(0.80, 0.50, 13.0), (0.83, 0.61, 207.1), (0.83, 0.60, 247.9), (0.82, 0.67, 251.6)])
TABLE_2_1_MODELS = ("soft_point", "elliptical", "reach")
TABLE_3_1_MODELS = ("soft_point", "reach", "mfe", "6dfc")


# ----------------------------------------------------------------------------------- Fig. 4.2
PUSH_NAMES = {"quasi_random": "Quasi-random (baseline)", "boundary_shear": "Boundary shear", "free_space": "Free space",
              "max_clearance": "Max clearance", "cluster_diffusion": "Cluster diffusion"}
PUSH_METRIC_NAMES = {"separation_gain": "separation gain", "jaw_gain": "jaw quality gain",
                     "suction_gain": "suction quality gain", "overall_gain": "overall quality gain"}


def _fig_4_2(run: Run) -> Result:
    """Improvable heaps (`data push-heaps`: household objects, Algorithm 1) until `heaps` of them are
    found, then `bench push` for the five policies, `bench push-table`'s summary and figures."""
    wanted = run.size["heaps"]
    heap_dir, rows_file = run.dir / "push_heaps", run.dir / "push_bench.jsonl"
    params = PushStudyConfig()
    found = len(improvable_records(heap_dir, wanted, run.seed_start))
    run.progress.set(found)
    dropped = [int(r["seed"]) for r in read_jsonl(heap_dir / "heaps.jsonl") if int(r["seed"]) >= run.seed_start]
    count = max(dropped) - run.seed_start + 1 if dropped else 0
    limit = 40 * wanted + 100  # about 25 % of the dropped heaps are improvable
    while found < wanted:
        if count >= limit:
            raise ReproduceError(f"fig_4_2: only {found} improvable heaps in {count} dropped (seeds {run.seed_start}-"
                                 f"{run.seed_start + count - 1}); {wanted} asked for")
        count += max(run.workers, min(wanted - found, 4 * run.workers))  # about a quarter of them will do
        write_push_heaps(count, heap_dir, run.seed_start, workers=run.workers, use_ray=run.use_ray, params=params,
                         bar=lambda r: run.progress.add(1) if r.ok and r.value.get("improvable") else None)
        found = len(improvable_records(heap_dir, wanted, run.seed_start))
    run.progress.set(wanted)
    heaps = improvable_records(heap_dir, wanted, run.seed_start)
    for policy in PUSH_POLICIES:
        run_push_bench(policy, wanted, run.seed_start, rows_file, heap_dir)
    seeds = {int(h["seed"]) for h in heaps}
    study = json.dumps(asdict(params), sort_keys=True)  # the data step's own pushes, not a re-run's
    rows = [r for r in read_jsonl(rows_file) if int(r["seed"]) in seeds
            and json.dumps(r.get("config"), sort_keys=True) == study]
    s = summarize_push(rows)
    by = {(r["policy"], int(r["seed"])): r for r in rows}
    common = sorted(seeds)
    measures = []
    for p in PUSH_POLICIES:
        for m in PUSH_METRICS:
            x = [by[p, k][m] for k in common if (p, k) in by]
            measures.append(Measure(PUSH_NAMES[p], PUSH_METRIC_NAMES[m], s["policies"][p][m]["mean"],
                                    _mean_interval(x), "{:+.3f}"))
    for m, a in s["anova"].items():
        measures.append(Measure("all policies", f"ANOVA, {PUSH_METRIC_NAMES[m]}",
                                f"F({a['df'][0]}, {a['df'][1]}) = {a['F']:.2f}, p = {a['p']:.2g}"))
    figures = plot_push(s, run.dir)
    dropped_n = len([r for r in read_jsonl(heap_dir / "heaps.jsonl") if int(r["seed"]) >= run.seed_start])
    return Result(measures, figures=figures, records=[heap_dir / "heaps.jsonl", rows_file],
                  bench_table="```\n" + format_push_table(s) + "\n```",
                  notes=[f"{len(heaps)} improvable heaps of household objects ({params.object_set}), found among "
                         f"{dropped_n} dropped heaps from seed {run.seed_start} (the reference: 481 of over 1,000); "
                         "mean gain per heap, every policy on the same heaps. The reference gives its gains as "
                         "text around its figure; its ANOVA compares four policies."])


# Fig. 4.2 (line 700: free space 17 %, boundary shear 18 %, 7 and 8 points above the baseline;
# max clearance a third of their overall gain; line 730: the ANOVAs).
FIG_4_2_REF = (
    Ref("Quasi-random (baseline)", "overall quality gain", "~0.10"),
    Ref("Boundary shear", "overall quality gain", 0.18),
    Ref("Free space", "overall quality gain", 0.17),
    Ref("Max clearance", "overall quality gain", "~0.06"),
    Ref("Max clearance", "separation gain", "the best policy"),
    Ref("all policies", "ANOVA, separation gain", "F(3, 1907) = 19.01, p < 0.001"),
    Ref("all policies", "ANOVA, jaw quality gain", "F(3, 1205) = 21.38, p < 0.001"),
    Ref("all policies", "ANOVA, suction quality gain", "not significant"),
    Ref("all policies", "ANOVA, overall quality gain", "F(3, 1205) = 24.81, p < 0.001"),
)


# ----------------------------------------------------------------------------------- Table B.1
SEGMENTATION_BACKENDS = (("Euclidean Clustering", "euclidean"), ("Region Growing", "region_growing"),
                         ("SD Mask R-CNN (ours: the learned segmenter, segmentation.pt)", "learned"))
SEGMENTATION_CHUNK = 10  # images per job, as bench_segmentation


def _rles_json(masks: dict) -> dict:
    return dict(masks, rles=[dict(r, counts=r["counts"].decode("ascii") if isinstance(r["counts"], bytes)
                                  else r["counts"]) for r in masks["rles"]])


def _rles_coco(masks: dict) -> dict:
    return dict(masks, rles=[dict(r, counts=r["counts"].encode("ascii")) for r in masks["rles"]])


def _coco_ap_ar(gt: list[dict], dt: list[dict], images: np.ndarray) -> list[float]:
    """COCO mask AP and AR@100 of the images at these indices (repeats allowed)."""
    m = coco_metrics([gt[k] for k in images], [dt[k] for k in images])
    return [m["AP"], m["AR100"]]


def _table_b_1(run: Run) -> Result:
    """`bench segmentation` for each backend on the same held-out images (seeds S..S+N-1, rendered
    once into OUT/table_b_1/images): its per-image job (segmentation_learning.bench_job) in chunks,
    each image's masks kept as a JSON line; COCO mask AP and AR@100 by its coco_metrics."""
    seeds = _seeds(run, run.size["images"])
    cache = run.dir / "images"
    measures, records, table = [], [], ["| method | AP | AP50 | AR@100 | images | masks | CPU s / image (median) |",
                                        "|---|---|---|---|---|---|---|"]
    for row, backend in SEGMENTATION_BACKENDS:
        path = run.dir / f"{backend}.jsonl"
        records.append(path)
        have = {int(r["seed"]) for r in _records(path)}
        todo = [s for s in seeds if s not in have]
        run.progress.add(len(seeds) - len(todo))
        jobs = [(backend, tuple(todo[i:i + SEGMENTATION_CHUNK]), 0.0, 0.0, None, str(cache), "none", True)
                for i in range(0, len(todo), SEGMENTATION_CHUNK)]
        for r in run_jobs(segmentation_job, jobs, workers=run.workers, use_ray=run.use_ray, max_tasks_per_child=5):
            if not r.ok:
                last = (r.error or "").strip().splitlines()[-1:] or ["no message"]
                raise ReproduceError(f"table_b_1: {backend} on images {r.job[1][0]}-{r.job[1][-1]} failed: {last[0]}; "
                                     "run again to retry them")
            for img in r.value:
                _append(path, {**img, **{k: _rles_json(img[k]) for k in ("gt", "dt") if k in img}})
            run.progress.add(len(r.value))
        ok = sorted((r for r in _records(path) if int(r["seed"]) in seeds and "gt" in r), key=lambda r: r["seed"])
        gt, dt = [_rles_coco(r["gt"]) for r in ok], [_rles_coco(r["dt"]) for r in ok]
        m = coco_metrics(gt, dt)
        ci = _interval(len(ok), partial(_coco_ap_ar, gt, dt), BOOTSTRAP_RECOMPUTED) or [None, None]
        measures += [Measure(row, "AP", m["AP"], ci[0], "{:.3f}"), Measure(row, "AR", m["AR100"], ci[1], "{:.3f}")]
        cpu = np.median([r["cpu_seconds"] for r in ok]) if ok else float("nan")
        table.append(f"| {backend} | {m['AP']:.3f} | {m['AP50']:.3f} | {m['AR100']:.3f} | {len(ok)} | {m['gt']} gt, "
                     f"{m['dt']} detected | {cpu:.3f} |")
    return Result(measures, records=records, bench_table="\n".join(table),
                  notes=[f"Images: seeds {seeds.start}-{seeds.stop - 1}, heaps of held-out objects (the test split of "
                         "ycb / random_urdfs / procedural) under a jittered overhead camera, noise-free depth; the "
                         "reference's are WISDOM-Sim test images (its own renderer and objects)."])


# Table B.1 (lines 1924-1927): COCO AP and AR on WISDOM-Sim.
TABLE_B_1_REF = _refs([r for r, _ in SEGMENTATION_BACKENDS], ("AP", "AR"),
                      [(0.161, 0.252), (0.172, 0.274), (0.664, 0.748)])


# ----------------------------------------------------------------------------------- Table 6.1
# Our checkers beside the reference's: the point-distance test against the scene SDF's (MC+SDFS),
# coal on convex hulls of the camera cloud's clusters against FCL on marching-cubes meshes of it.
COLLISION_ROWS = (("MC+SDFO", ""), ("MC+SDFS (ours: sdf, point distance 1 cm)", "sdf"),
                  ("MC+FCL (10x) (ours: coal_reconstruction)", "coal_reconstruction"), ("MC+FCL (10x, FO)", ""),
                  ("PointNet Grid (ours: pointnet_grid)", "pointnet_grid"), ("SceneCollisionNet (ours: net)", "net"))


def _table_6_1(run: Run) -> Result:
    """`bench collision` for each method on held-out scenes S..S+N-1 (made once, kept in
    OUT/table_6_1/scenes): scene by scene (a JSON line each: resumable, and the units of the
    interval), then once over all scenes for the pooled AP and the CPU time per query."""
    n = run.size["scenes"]
    seeds = _seeds(run, n)
    cache = run.dir / "scenes"
    measures, records = [], []
    table = ["| method | accuracy | AP | CPU us / query | set-up ms / scene | queries |", "|---|---|---|---|---|---|"]
    for row, method in COLLISION_ROWS:
        if not method:
            continue
        path = run.dir / f"{method}.jsonl"
        pooled_path = run.dir / f"{method}_pooled_{seeds.start}-{seeds.stop - 1}.json"
        records += [path, pooled_path]
        have = {int(r["seed"]) for r in _records(path)}
        run.progress.add(sum(1 for s in seeds if s in have))
        for s in seeds:
            if s not in have:
                _append(path, {"seed": s, **bench_collision(method, 1, s, cache=cache)})
                run.progress.add(1)
        if pooled_path.exists():
            pooled = json.loads(pooled_path.read_text())
            run.progress.add(n)
        else:
            pooled = bench_collision(method, n, seeds.start, cache=cache, progress=lambda k: run.progress.add(1))
            pooled_path.write_text(json.dumps(pooled, indent=1))
        per = {int(r["seed"]): r for r in _records(path)}
        acc = np.array([per[s]["accuracy"] for s in seeds]), np.array([per[s]["queries"] for s in seeds])
        acc_ci = _scaled(_ratio_interval(acc[0] * acc[1], acc[1]), 100)  # the pooled accuracy, scenes resampled
        measures += [Measure(row, "accuracy", 100 * pooled["accuracy"], acc_ci, "{:.1f} %"),
                     Measure(row, "AP", pooled["ap"], None, "{:.3f}"),
                     Measure(row, "time / query (us)", pooled["us_per_query"], None, "auto")]
        table.append(f"| {method} | {100 * pooled['accuracy']:.1f} % | {pooled['ap']:.3f} | "
                     f"{pooled['us_per_query']:.1f} | "
                     f"{pooled['setup_ms_per_scene']:.1f} | {pooled['queries']} ({100 * pooled['positive']:.1f} % in "
                     "collision) |")
    return Result(measures, records=records, bench_table="\n".join(table),
                  notes=[f"{n} held-out tabletop scenes (seeds {seeds.start}-{seeds.stop - 1}), test-split objects, "
                         "2,048 queries each along linear trajectories, labels by coal on the true meshes. Our time is "
                         "CPU per query on one thread (the scene set-up apart); the reference's is per query on a GPU "
                         "(networks) or 10 processes (FCL). Accuracy's interval: scenes resampled; AP is pooled over "
                         "all queries, which the bench does not keep, so it has none."])


# Table 6.1 (lines 1116-1122): accuracy (%), AP, time per query (ms, given here in us).
TABLE_6_1_REF = _refs([r for r, _ in COLLISION_ROWS], ("accuracy", "AP", "time / query (us)"),
                      [(70.2, 0.651, 27000.0), (80.0, 0.781, 24000.0), (75.4, 0.824, 490.0), (83.4, 0.832, 740.0),
                       (76.7, 0.928, 26.0), (93.2, 0.990, 10.0)])


# ----------------------------------------------------------------------------------- Table 6.3
REARRANGE_ROWS = (("MC+FCL (10x) (ours: coal_reconstruction)", "coal_reconstruction"),
                  ("SceneCollisionNet (ours: net)", "net"))


def _table_6_3(run: Run) -> Result:
    """`bench rearrange` for each checker on scenes S..S+N-1 of `objects` objects (one JSON line per
    scene in OUT/table_6_3/rearrange.jsonl); counts per 100 objects, the reference's 10 x 10."""
    scenes, objects = run.size["scenes"], run.size["objects"]
    seeds = _seeds(run, scenes)
    path = run.dir / "rearrange.jsonl"

    def mine(method):
        return [r for r in rearrange_records([path]) if path.exists() and r["method"] == method
                and int(r["seed"]) in seeds and r.get("objects") == objects
                and r.get("trajectories", 300) == 300 and r.get("horizon", 40) == 40]

    measures, recs = [], []
    for k, (row, method) in enumerate(REARRANGE_ROWS):
        run.progress.set(k * scenes + len(mine(method)))
        run_rearrange_bench(method, scenes, seeds.start, path, objects=objects, workers=run.workers,
                            log=lambda msg, k=k, method=method: (run.log(msg),
                                                                 run.progress.set(k * scenes + len(mine(method)))))
        rs = mine(method)
        recs += rs
        n_obj = [r["objects"] for r in rs]
        for metric, key in (("grasps per 100 objects", "grasps"), ("placements per 100 objects", "placements"),
                            ("sim minutes per 100 objects", "minutes")):
            x = [r[key] for r in rs]
            measures.append(Measure(row, metric, 100 * sum(x) / max(sum(n_obj), 1), _ratio_interval(x, n_obj, 100),
                                    "{:.0f}"))
    return Result(measures, records=[path], bench_table=rearrange_table(recs),
                  notes=[f"{scenes} scenes of {objects} procedural test-split objects on the PandaTable station "
                         "(Drake physics), MPPI T = 300, H = 40, two attempts per object; the reference: 10 scenes of "
                         "10 objects in Isaac Gym, its policy queried at 1 Hz (its minutes are interaction time)."])


# Table 6.3 (lines 1144-1146): grasps, placements and minutes over 10 scenes x 10 objects.
TABLE_6_3_REF = _refs([r for r, _ in REARRANGE_ROWS],
                      ("grasps per 100 objects", "placements per 100 objects", "sim minutes per 100 objects"),
                      [(109, 92, 164), (110, 99, 100)])


# ----------------------------------------------------------------------------------- Table 8.1
# The held-out sets: test-only shards (occluders from the test splits) from dataset seeds the shipped
# occupancy.pt never saw (it was trained on seed 0; models/weights/occupancy.md). Out-of-set targets
# as docs/results/ch8_xray.md: the lid, the domino, the flute (a cylinder lying flat).
OCCUPANCY_SETS = (("test", 0, None), ("lid", 1, (0.06, 0.06, 0.005)), ("domino", 2, (0.05, 0.025, 0.01)),
                  ("flute", 3, ("cylinder", 0.15, 0.015)))
OCCUPANCY_SHARD = 32  # images per shard: 8 views x 4 heaps (the data command's defaults)
OCCUPANCY_ROWS = (  # (row, set, input scaling, aspect-ratio channel or None for every image)
    ("test, 1:1 box", "test", False, 1), ("test, 2:1 box", "test", False, 2), ("test, 5:1 box", "test", False, 5),
    ("test, 10:1 box", "test", False, 10), ("lid (1:1 channel, input scaling)", "lid", True, None),
    ("lid (1:1 channel, no scaling)", "lid", False, None),
    ("domino (2:1 channel, input scaling)", "domino", True, None),
    ("flute (10:1 channel, input scaling)", "flute", True, None))


def _occupancy_images(size: dict, name: str) -> int:
    return size["test_images"] if name == "test" else size["ood_images"]


def _occupancy_total(size: dict) -> int:
    return sum(math.ceil(_occupancy_images(size, n) / OCCUPANCY_SHARD) for n, _, _ in OCCUPANCY_SETS)


def _table_8_1(run: Run) -> Result:
    """Held-out occupancy sets (`data occupancy --test-only`, OUT/table_8_1/<set>), then `bench
    occupancy` on each (with and without input scaling as the rows need); the intervals resample the
    images, whose metrics come from the bench's own predict / occupancy_metrics. The bench reads every
    shard of a set's folder: after a full run, a small one reports on the full sets (the bench's own
    table gives the images)."""
    for name, offset, target in OCCUPANCY_SETS:
        folder = run.dir / name
        shards = math.ceil(_occupancy_images(run.size, name) / OCCUPANCY_SHARD)
        run.progress.add(sum(1 for k in range(shards) if (folder / f"shard_{k:05d}_test.npz").exists()))
        res = write_occupancy_dataset(folder, shards * OCCUPANCY_SHARD, seed=run.seed_start + offset,
                                      workers=run.workers, use_ray=run.use_ray, test_only=True,
                                      targets=None if target is None else [target],
                                      progress=lambda r: run.progress.add(1))
        if res["failed"]:
            raise ReproduceError(f"table_8_1: {name} shards {[f[0] for f in res['failed']]} failed; run again to retry")
    net, _ = load_occupancy_model(None)
    measures, table, cache = [], ["| set | scaling | images | hidden | bal. acc. % | IoU | CPU ms / image |",
                                  "|---|---|---|---|---|---|---|"], {}
    for row, name, scaling, ratio in OCCUPANCY_ROWS:
        folder = run.dir / name
        if (name, scaling) not in cache:
            res = bench_occupancy(folder, None, scaling)
            d = load_dataset(folder, "test")
            pred = predict(net, d["x"], d["ratio"], target_scales(d["size"]) if scaling else None,
                           diag=diagonals(d["size"]))
            cache[name, scaling] = res, d, occupancy_metrics(pred, d["y"].astype(np.float32))
            all_row = next(r for r in res["rows"] if r["ratio"] == "all")
            table.append(f"| {name} | {'input' if scaling else 'none'} | {all_row['images']} | {all_row['hidden']} | "
                         f"{100 * all_row['balanced_accuracy']:.1f} | {all_row['iou']:.2f} | "
                         f"{res['cpu_ms_per_image']:.1f} |")
        res, d, m = cache[name, scaling]
        sel = np.ones(len(d["ratio"]), bool) if ratio is None else d["ratio"] == TARGET_RATIOS.index(ratio)
        if not sel.any():
            continue
        bench_row = next(r for r in res["rows"] if r["ratio"] == (ratio if ratio is not None else "all"))
        bal, iou = m["balanced_accuracy"][sel], m["iou"][sel]
        measures += [Measure(row, "balanced accuracy", 100 * bench_row["balanced_accuracy"],
                             _scaled(_mean_interval(bal), 100), "{:.1f} %"),
                     Measure(row, "IoU", bench_row["iou"], _mean_interval(iou), "{:.2f}")]
    res = cache["test", False][0]
    measures.append(Measure("inference", "ms / image", res["cpu_ms_per_image"], None, "auto"))
    return Result(measures, records=[run.dir / name for name, _, _ in OCCUPANCY_SETS], bench_table="\n".join(table),
                  notes=["One network with a channel per aspect ratio (the reference: one network per ratio); the "
                         "out-of-set targets take the channel of their nearest ratio. Held-out sets from dataset seeds "
                         f"{run.seed_start}-{run.seed_start + 3} (the shipped weights were trained on seed 0), "
                         "occluders from the test splits only. Inference: CPU per 640 x 480 image on one torch thread "
                         "(the reference: 6 ms on a V100)."])


# Table 8.1 (lines 1441-1446): balanced accuracy and IoU per network, on its test set and the out-of-set
# targets with the closest network; the lid without input scaling from line 1468.
TABLE_8_1_REF = _refs([r[0] for r in OCCUPANCY_ROWS], ("balanced accuracy", "IoU"),
                      [(98, 0.91), (97, 0.90), (97, 0.90), (97, 0.87), (93, 0.70), (63.0, 0.186), (96, 0.81),
                       (82, 0.41)]) + (Ref("inference", "ms / image", 6.0),)  # line 1462: a forward pass on a V100


# ----------------------------------------------------------------------------------- Table 9.1
SHELF_POLICIES_91 = (("Oracle-P", "oracle_p"), ("Oracle-P+S", "oracle_ps"), ("DAR", "dar"), ("DER-3", "der3"),
                     ("Bluction-DAR", "bluction_dar"))
SHELF_OCCLUDERS = (4, 6, 8, 10)


def _table_9_1(run: Run) -> Result:
    """`bench shelf` (FOSS, ground-truth occupancy) for the reference's five policies on scenes
    S..S+K-1 at each occluder count, one JSON line per search in OUT/table_9_1/<policy>.jsonl; the
    success rates and their bootstrap intervals as the bench reports them; `bench shelf-table`'s
    figure."""
    scenes = run.size["scenes"]
    counts = list(run.size.get("occluders", SHELF_OCCLUDERS))
    seeds = _seeds(run, scenes)
    measures, files = [], []

    def mine(path, config):
        key = config.record()
        return [r for r in (shelf_records([path]) if path.exists() else []) if int(r["seed"]) in seeds
                and int(r["objects"]) in counts and r["config"] == key]

    for row, policy in SHELF_POLICIES_91:
        path, config = run.dir / f"{policy}.jsonl", ShelfSearchConfig(policy=policy)
        files.append(path)
        run.progress.add(sum(1 for r in mine(path, config) if r.get("failure") != "worker_died"))
        s = run_shelf_bench(config, counts, scenes, seeds.start, path, workers=run.workers, use_ray=run.use_ray,
                            progress=lambda rec: run.progress.add(1))
        for n in counts + ["all"]:
            label = "All" if n == "all" else str(n)
            measures += [Measure(f"{label} occluders, {row}", "success", 100 * s[n]["success_rate"],
                                 _scaled(s[n]["success_ci"], 100), "{:.0f} %"),
                         Measure(f"{label} occluders, {row}", "median steps (IQR)",
                                 _median_iqr(s[n]["success_quartiles"]))]
    recs = [r for (_, p), f in zip(SHELF_POLICIES_91, files) for r in mine(f, ShelfSearchConfig(policy=p))]
    return Result(measures, figures=[plot_shelf(recs, run.dir)], records=files,
                  bench_table=shelf_table(recs, tuple(p for _, p in SHELF_POLICIES_91)),
                  notes=[f"{scenes} scenes per occluder count (seeds {seeds.start}-{seeds.stop - 1}), the same scenes "
                         "for every policy; FOSS with the Fetch bluction tool's 4 mm blade, target 6 x 6 x 6 cm, "
                         "success at 80 % visible, H = 2n, psi = 1.3; ground-truth occupancy (the reference: its "
                         "learned network); the oracles as they run by default (staged search, then 60 / 120 CPU-s)."])


# Table 9.1 (lines 1654-1665): success rate and median steps (IQR) per occluder count, 100 scenes each.
_T91 = {  # occluders: (success % per policy in SHELF_POLICIES_91 order), (median steps (IQR) strings)
    "4": ((100, 100, 77, 83, 96), ("1.5 (1.0 - 2.0)", "1.5 (1.0 - 2.0)", "2.0 (1.0 - 3.0)", "2.0 (1.0 - 3.0)",
                                   "2.0 (1.0 - 2.5)")),
    "6": ((100, 100, 68, 72, 92), ("3.0 (2.0 - 3.0)", "2.0 (2.0 - 3.0)", "3.0 (1.8 - 5.0)", "3.0 (1.0 - 4.3)",
                                   "2.0 (2.0 - 4.0)")),
    "8": ((99, 100, 45, 50, 88), ("3.0 (2.0 - 4.0)", "2.5 (2.0 - 3.0)", "3.0 (1.0 - 4.0)", "3.0 (2.0 - 4.0)",
                                  "3.0 (2.0 - 5.0)")),
    "10": ((94, 100, 24, 34, 67), ("4.0 (3.0 - 6.0)", "3.0 (2.0 - 4.0)", "4.5 (2.0 - 6.0)", "3.0 (2.0 - 5.0)",
                                   "6.0 (3.0 - 8.0)")),
    "All": ((98, 100, 54, 60, 86), ("3.0 (2.0 - 4.0)", "2.0 (1.0 - 3.0)", "2.0 (1.0 - 4.0)", "3.0 (1.0 - 4.0)",
                                    "3.0 (2.0 - 4.0)")),
}
TABLE_9_1_REF = tuple(Ref(f"{n} occluders, {row}", metric, v)
                      for n, (rates, steps) in _T91.items() for k, (row, _) in enumerate(SHELF_POLICIES_91)
                      for metric, v in (("success", rates[k]), ("median steps (IQR)", steps[k])))


# ----------------------------------------------------------------------------------- Table 9.2
SHELF_POLICIES_92 = (("DER-3", "der3"), ("Bluction-DAR", "bluction_dar"))
PHYSICS_OCCLUDERS = (8, 10, 12)  # cycled over the seeds, the reference's physical densities
PHYSICS_STATION = "FetchWideShelf"  # the reference's physical shelf, 0.8 x 0.5 x 0.5 m


def _table_9_2(run: Run) -> Result:
    """`bench shelf-physics` (the Fetch with the bluction tool in Drake physics at the reference's
    physical shelf, ground-truth perception) for DER-3 and Bluction-DAR on scenes S..S+N-1,
    occluders cycling 8, 10, 12; one JSON line per scene in OUT/table_9_2/<policy>.jsonl."""
    scenes = run.size["scenes"]
    seeds = _seeds(run, scenes)
    horizon = run.size.get("horizon")
    measures, files, recs = [], [], []

    def mine(path):
        return [r for r in (physics_records([path], "ground_truth") if path.exists() else [])
                if int(r["seed"]) in seeds and record_scenario(r) == PHYSICS_STATION]

    for k, (row, policy) in enumerate(SHELF_POLICIES_92):
        path = run.dir / f"{policy}.jsonl"
        files.append(path)
        run.progress.set(k * scenes + len(mine(path)))
        run_shelf_physics_bench(ShelfSearchConfig(policy=policy, horizon=horizon), scenes, seeds.start, path,
                                list(PHYSICS_OCCLUDERS), workers=run.workers, scenario_name=PHYSICS_STATION,
                                log=lambda msg, k=k, path=path: (run.log(msg),
                                                                 run.progress.set(k * scenes + len(mine(path)))))
        rs = mine(path)
        recs += rs
        for n in PHYSICS_OCCLUDERS:
            at = [r for r in rs if r["occluders"] == n]
            ok = [r for r in at if r["success"]]
            if at:
                measures += [Measure(f"{n} occluders, {row}", "successes", f"{len(ok)}/{len(at)}"),
                             Measure(f"{n} occluders, {row}", "no. steps",
                                     ", ".join(str(r["steps"]) for r in ok) or "(-)")]
        succ = [float(r["success"]) for r in rs]
        measures += [Measure(f"All, {row}", "success rate", 100 * float(np.mean(succ)) if succ else float("nan"),
                             _scaled(_mean_interval(succ), 100), "{:.0f} %"),
                     Measure(f"All, {row}", "median steps (IQR)", _quartiles([r["steps"] for r in rs if r["success"]]))]
    return Result(measures, records=files, bench_table=physics_table(recs, tuple(p for _, p in SHELF_POLICIES_92)),
                  notes=[f"{scenes} simulated scenes per policy (seeds {seeds.start}-{seeds.stop - 1}, occluders "
                         f"cycling 8, 10, 12) on the {PHYSICS_STATION} station (the reference's physical shelf, "
                         "0.8 x 0.5 x 0.5 m) in Drake physics, target 6 x 6 x 6 cm, "
                         "ground-truth perception" + (f", horizon {horizon}" if horizon else ", H = 2n")
                         + "; the reference: 9 physical scenes (3 per density), 6 x 6 x 3 cm target, its camera."])


# Table 9.2 (lines 1691-1699): the physical Fetch, 3 scenes per occluder count.
TABLE_9_2_REF = (
    Ref("8 occluders, DER-3", "successes", "0/3"), Ref("8 occluders, DER-3", "no. steps", "(-)"),
    Ref("8 occluders, Bluction-DAR", "successes", "3/3"), Ref("8 occluders, Bluction-DAR", "no. steps", "3, 4, 4"),
    Ref("10 occluders, DER-3", "successes", "2/3"), Ref("10 occluders, DER-3", "no. steps", "7, 4"),
    Ref("10 occluders, Bluction-DAR", "successes", "3/3"), Ref("10 occluders, Bluction-DAR", "no. steps", "4, 5, 4"),
    Ref("12 occluders, DER-3", "successes", "1/3"), Ref("12 occluders, DER-3", "no. steps", "4"),
    Ref("12 occluders, Bluction-DAR", "successes", "3/3"), Ref("12 occluders, Bluction-DAR", "no. steps", "6, 7, 7"),
    Ref("All, DER-3", "success rate", 33), Ref("All, DER-3", "median steps (IQR)", "4.0 (4.0 - 5.5)"),
    Ref("All, Bluction-DAR", "success rate", 100), Ref("All, Bluction-DAR", "median steps (IQR)", "4.0 (4.0 - 6.0)"),
)


# ----------------------------------------------------------------------------------- bin searches
class _SuiteProgress:
    """run_suite's progress (start(done, todo), then one call per record) as the recipe's."""

    def __init__(self, progress: Progress):
        self.progress = progress

    def start(self, done: int, todo: int) -> None:
        self.progress.set(done)

    def __call__(self, rec: dict) -> None:
        self.progress.add(1)


def _bin_search_recipe(run: Run, setting: str, rows: tuple[tuple[str, str], ...], objects: tuple[int, ...],
                       margin: tuple[str, str] | None = None, reading: str = "") -> Result:
    """`bench search` with the named setting (policies.bin_search.named_search_configs) for each
    selector of `rows` and each N of `objects` on heaps S..S+K-1 shared through OUT/NAME/heaps (one
    JSON-lines file per selector and N); the Ch. 7 setting's budget is 2N. margin: (row A, row B)
    whose paired success difference is reported (the heaps resampled)."""
    heaps = run.size["heaps"]
    runs, labels = [], []
    for n in objects:
        for row, policy in rows:
            cfg = load_bin_search_config(setting, policy=policy)
            cfg.heap = HeapConfig(cfg.heap.layout, n)
            if setting == "ch7":
                cfg.horizon = 2 * n
            runs.append((cfg, run.dir / f"{policy}_N{n}.jsonl"))
            labels.append(f"N = {n}, {row}" if len(objects) > 1 else row)
    summaries = run_suite(runs, heaps, run.seed_start, workers=run.workers, use_ray=run.use_ray,
                          progress=_SuiteProgress(run.progress), heap_dir=str(run.dir / "heaps"))
    measures = []
    for label, s in zip(labels, summaries):
        measures += [Measure(label, "success", 100 * s["success_rate"], _scaled(s["success_ci"], 100), "{:.1f}"),
                     Measure(label, "mean actions", s["mean_actions"], tuple(s["actions_ci"]), "{:.2f}"),
                     Measure(label, "actions quartiles (successes)",
                             " / ".join(f"{q:g}" for q in s["success_quartiles"]) if s["success_rate"] > 0 else "-")]
    files = [path for _, path in runs]
    notes = [f"{heaps} heaps per selector (seeds {run.seed_start}-{run.seed_start + heaps - 1}); the setting "
             f"`{setting}` (`ms-drake bench config --config {setting}` prints it)."]
    if margin is not None:
        a, b = (files[labels.index(r)] for r in margin)
        c = paired_comparison(read_search_records(a), read_search_records(b), (str(a), str(b)))
        measures.append(Measure(f"{margin[0]} - {margin[1]}", "success margin (points)", c["diff"],
                                tuple(c["diff_ci"]), "{:.1f}"))
        notes.append(f"{margin[0]} vs {margin[1]} on the same heaps: {len(c['only_a'])} heaps only {margin[0]} "
                     f"solves, {len(c['only_b'])} only {margin[1]}; sign test p = {c['p']:.2g}.")
    if reading:
        notes.append(reading)
    figures = plot(files, run.dir)
    if len(objects) > 1:
        figures.append(_actions_by_objects(run.dir, rows, objects, summaries))
    return Result(measures, figures=figures, records=files, notes=notes)


def _actions_by_objects(folder: Path, rows, objects, summaries) -> Path:
    """Fig. 7.4 A: mean actions (95 % interval) against N, one line per selector."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for k, (row, _) in enumerate(rows):
        s = [summaries[j * len(rows) + k] for j in range(len(objects))]
        mean = [x["mean_actions"] for x in s]
        err = np.array([[m - x["actions_ci"][0], x["actions_ci"][1] - m] for m, x in zip(mean, s)]).T
        ax.errorbar(objects, mean, yerr=err, marker="o", capsize=3, label=row)
    ax.set_xlabel("objects in the heap (N)")
    ax.set_ylabel("mean actions")
    ax.set_xticks(list(objects))
    ax.set_title("Actions to extract the target (cf. Fig. 7.4 A)")
    ax.legend(fontsize=7)
    return save_png(fig, folder / "actions_by_objects.png")


# Table C.1 (lines 1941-1946): success rate and mean actions (+- SEM), 1,000 trials each, N = 15.
C1_POLICIES = (("Random", "random"), ("Preempted Random", "preempted_random"),
               ("Preempted Random + Pushing", "preempted_random_push"), ("Largest-First", "largest"),
               ("Largest-First + Pushing", "largest_push"))
TABLE_C_1_REF = _refs([r for r, _ in C1_POLICIES], ("success", "mean actions"),
                      [(88.8, 11.26), (89.7, 8.55), (94.3, 8.87), (90.3, 6.35), (93.3, 6.51)])
# Fig. 7.4 (caption, line 1312): A: heaps of 10, 15 and 20 objects, 1,000 simulated rollouts per
# policy and size. The text gives its numbers only for N = 15 (Table C.1, lines 1941-1946); the
# N = 10 and 20 values are in the figure's image alone.
FIG_7_4_REF = tuple(Ref(f"N = 15, {r.row}", r.metric, r.value) for r in TABLE_C_1_REF)
# Table 8.2 (lines 1501-1504): success rate and the quartiles of actions over successful rollouts,
# 1,000 rollouts each, N = 14 + target, H = 10. The reference's Random first tries the target.
TABLE_8_2_READING = (
    "Reading: the ordering is the reference's (X-Ray > Largest > Random; X-Ray solves heaps Largest does not "
    "and almost never the reverse). Our rates run 5-10 points above the reference's: the heaps are simulated "
    "(the reference's generator settings with our household meshes and a 4.5 cm target) and a grasp lifts when "
    "the nominal contact model says so, without sensor noise. X-Ray's margin over Largest is about 10 points "
    "(200 heaps of seeds 5000-5199: 10.0 [4.0, 16.0]), below the reference's 15, which lies inside the "
    "intervals.")
TABLE_8_2_ROWS = (("Random", "preempted_random"), ("Largest", "largest"), ("X-Ray", "xray"))
TABLE_8_2_REF = _refs(("Random", "Largest", "X-Ray"), ("success", "actions quartiles (successes)"),
                      [(42, "4 / 7 / 9"), (67, "4 / 5 / 7"), (82, "3 / 5 / 6")]) + (
    Ref("X-Ray - Largest", "success margin (points)", 15),)


# ----------------------------------------------------------------------------------- the registry
def _counts(*keys: str) -> Callable[[dict], int]:
    """Work items of a size: the product of these counts."""
    return lambda size: int(np.prod([size[k] for k in keys]))


RECIPES: dict[str, Recipe] = {r.name: r for r in (
    Recipe("table_2_1", "Table 2.1: grasp quality contact models (soft point, elliptical, REACH) against physics "
           "labels, AP / AR",
           TABLE_2_1_REF, small=dict(objects=21, grasps=15, trials=2), full=dict(objects=21, grasps=25, trials=5),
           run=partial(_grasp_table, models=TABLE_2_1_MODELS, rows=TABLE_2_1_ROWS),
           total=partial(_grasp_total, TABLE_2_1_MODELS),
           interval="grasped objects resampled, the leave-one-object-out table recomputed (200 resamples)",
           minutes_small=4.1),
    Recipe("table_3_1", "Table 3.1: 6DFC vs soft point, REACH and MFE grasp quality against physics labels, AP / AR",
           TABLE_3_1_REF, small=dict(objects=12, grasps=25, trials=2), full=dict(objects=12, grasps=125, trials=5),
           run=partial(_grasp_table, models=TABLE_3_1_MODELS, rows=TABLE_3_1_ROWS),
           total=partial(_grasp_total, TABLE_3_1_MODELS),
           interval="grasped objects resampled, the leave-one-object-out table recomputed (200 resamples)",
           minutes_small=4.7),
    Recipe("fig_4_2", "Fig. 4.2: linear push policies on improvable bin heaps, separation and grasp-quality gains",
           FIG_4_2_REF, small=dict(heaps=16), full=dict(heaps=481), run=_fig_4_2, total=_counts("heaps"),
           interval="heaps resampled (2,000 resamples)", minutes_small=6.3),
    Recipe("table_b_1", "Table B.1: depth instance segmentation of bin images, learned vs point-cloud baselines, "
           "COCO AP / AR", TABLE_B_1_REF, small=dict(images=300), full=dict(images=2000), run=_table_b_1,
           total=lambda size: len(SEGMENTATION_BACKENDS) * size["images"], seed_start=100000,
           interval="images resampled, COCO AP / AR recomputed (200 resamples)", minutes_small=10.4),
    Recipe("table_6_1", "Table 6.1: learned collision checking (SceneCollisionNet) vs mesh and SDF baselines on "
           "point clouds, accuracy / AP / time", TABLE_6_1_REF, small=dict(scenes=100), full=dict(scenes=1000),
           run=_table_6_1, total=lambda size: 2 * 4 * size["scenes"], seed_start=100000,
           interval="scenes resampled (2,000 resamples); none for the pooled AP", minutes_small=4.1),
    Recipe("table_6_3", "Table 6.3: Panda tabletop rearrangement with MPPI, learned vs mesh collision checking, "
           "grasps / placements / time", TABLE_6_3_REF, small=dict(scenes=5, objects=10),
           full=dict(scenes=10, objects=10), run=_table_6_3, total=lambda size: 2 * size["scenes"],
           interval="scenes resampled (2,000 resamples)", minutes_small=9.3),
    Recipe("table_8_1", "Table 8.1: learned target occupancy from depth, balanced accuracy / IoU on held-out heaps "
           "and unseen targets", TABLE_8_1_REF, small=dict(test_images=960, ood_images=320),
           full=dict(test_images=2000, ood_images=1000), run=_table_8_1, total=_occupancy_total, seed_start=10,
           interval="images resampled (2,000 resamples)", minutes_small=5.9),
    Recipe("table_9_1", "Table 9.1: shelf search in FOSS, Bluction-DAR vs DAR, DER-3 and oracles, success and steps",
           TABLE_9_1_REF, small=dict(scenes=50), full=dict(scenes=100), run=_table_9_1,
           total=lambda size: len(SHELF_POLICIES_91) * len(size.get("occluders", SHELF_OCCLUDERS)) * size["scenes"],
           interval="scenes resampled, as `bench shelf` reports it (2,000 resamples)", minutes_small=12.4,
           options=("occluders",)),
    Recipe("table_9_2", "Table 9.2: shelf search on the Fetch with the bluction tool in physics, Bluction-DAR vs "
           "DER-3", TABLE_9_2_REF, small=dict(scenes=3), full=dict(scenes=9), run=_table_9_2,
           total=lambda size: len(SHELF_POLICIES_92) * size["scenes"], interval="scenes resampled (2,000 resamples)",
           minutes_small=2.7, options=("horizon",)),
    Recipe("table_c_1", "Table C.1: bin search selectors (Random, Preempted Random, Largest-First, +/- pushing), "
           "success and actions", TABLE_C_1_REF, small=dict(heaps=50), full=dict(heaps=1000),
           run=partial(_bin_search_recipe, setting="ch7", rows=C1_POLICIES, objects=(15,)),
           total=lambda size: len(C1_POLICIES) * size["heaps"], interval="heaps resampled (2,000 resamples)",
           minutes_small=19.1),
    Recipe("fig_7_4", "Fig. 7.4: bin search selectors on heaps of 10, 15 and 20 objects, success and actions",
           FIG_7_4_REF, small=dict(heaps=20), full=dict(heaps=1000),
           run=partial(_bin_search_recipe, setting="ch7", rows=C1_POLICIES, objects=(10, 15, 20)),
           total=lambda size: 3 * len(C1_POLICIES) * size["heaps"], interval="heaps resampled (2,000 resamples)",
           minutes_small=30.3),
    Recipe("table_8_2", "Table 8.2: X-Ray vs Largest vs Random, bin search success", TABLE_8_2_REF,
           small=dict(heaps=60), full=dict(heaps=1000), seed_start=20000,
           run=partial(_bin_search_recipe, setting="table_8_2", rows=TABLE_8_2_ROWS, objects=(14,),
                       margin=("X-Ray", "Largest"), reading=TABLE_8_2_READING),
           total=lambda size: len(TABLE_8_2_ROWS) * size["heaps"],
           interval="heaps resampled (2,000 resamples); the margin paired on the same heaps",
           minutes_small=21.7),
)}


def list_recipes() -> list[Recipe]:
    """Every recipe, in the reference's order of chapters."""
    return list(RECIPES.values())


def get_recipe(name: str) -> Recipe:
    if name not in RECIPES:
        raise ReproduceError(f"unknown recipe {name!r}; choose one of {', '.join(RECIPES)}")
    return RECIPES[name]


# ----------------------------------------------------------------------------------- the markdown
def _fmt(value, fmt: str) -> str:
    """`value` by `fmt` ("auto": two significant decimals below 10, none from 100 up)."""
    if isinstance(value, str):
        return value
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if fmt == "auto":
        fmt = "{:,.0f}" if abs(value) >= 100 else "{:.1f}" if abs(value) >= 10 else "{:.2f}"
    return fmt.format(value)


def _interval_text(m: Measure) -> str:
    if m.interval is None or isinstance(m.value, str):
        return "-"
    return f"[{_fmt(m.interval[0], m.fmt)}, {_fmt(m.interval[1], m.fmt)}]"


def _row_order(reference: tuple[Ref, ...], measures: list[Measure]) -> list[str]:
    """The reference's rows in its order, each of our other rows after the row we list before it."""
    rows = list(dict.fromkeys(r.row for r in reference))
    previous = None
    for row in dict.fromkeys(m.row for m in measures):
        if row not in rows:
            rows.insert(rows.index(previous) + 1 if previous is not None else len(rows), row)
        previous = row
    return rows


def markdown_table(recipe: Recipe, measures: list[Measure]) -> str:
    """One line per (row, metric), each with ours, our interval and the reference's figure: the rows in
    the reference's order (ours merged in), the metrics of a row in the order we report them."""
    ours = {(m.row, m.metric): m for m in measures}
    refs = {(r.row, r.metric): r for r in recipe.reference}
    metric_fmt = {m.metric: m.fmt for m in measures}
    metrics = list(dict.fromkeys([m.metric for m in measures] + [r.metric for r in recipe.reference]))
    keys = [(row, metric) for row in _row_order(recipe.reference, measures) for metric in metrics
            if (row, metric) in ours or (row, metric) in refs]
    lines = ["| | metric | ours | 95 % interval | reference |", "|---|---|---|---|---|"]
    for key in keys:
        m, r = ours.get(key), refs.get(key)
        fmt = m.fmt if m is not None else metric_fmt.get(key[1], "{:g}")
        lines.append(f"| {key[0]} | {key[1]} | {_fmt(m.value, m.fmt) if m else '-'} | "
                     f"{_interval_text(m) if m else '-'} | {_fmt(r.value, fmt) if r else '-'} |")
    return "\n".join(lines)


def _command(name: str, size: str, seed_start: int, workers: int, use_ray: bool, out: Path, sizes) -> str:
    if sizes:
        return (f"reproduce({name!r}, size={size!r}, seed_start={seed_start}, workers={workers}, use_ray={use_ray}, "
                f"out={str(out)!r}, sizes={sizes!r})  # Python API")
    return (f"ms-drake reproduce {name} --size {size} --seed-start {seed_start} --workers {workers}"
            + (" --ray" if use_ray else "") + f" --out {out}")


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children (the worker pools)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _write_markdown(recipe: Recipe, result: Result, path: Path, command: str, size: str, counts: dict,
                    wall: float, cpu: float) -> None:
    rel = lambda p: os.path.relpath(p, path.parent)
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    parts = [f"# {recipe.title}", "",
             f"Command: `{command}`", "",
             f"Size: {size} ({', '.join(f'{k} {v}' for k, v in counts.items())}). Machine: {platform.platform()}, "
             f"{os.cpu_count()} CPUs ({platform.processor() or platform.machine()}). Date: {now}. Code: "
             f"{code_version()}. This run: {wall / 60:.1f} min wall, {cpu / 60:.1f} CPU-min (work its records "
             "already held is not redone).", "",
             markdown_table(recipe, result.measures), "",
             f"Interval: percentile bootstrap 95 %, {recipe.interval}.", ""]
    parts += [n + "\n" for n in result.notes]
    parts += [f"![{p.stem}]({rel(p)})\n" for p in result.figures]
    if result.bench_table:
        parts += ["The bench's own table:", "", result.bench_table, ""]
    parts += ["Records: " + ", ".join(f"`{rel(p)}`" for p in result.records), ""]
    path.write_text("\n".join(parts))


# ----------------------------------------------------------------------------------- entry point
def reproduce(name: str, size: str = "small", seed_start: int | None = None, workers: int = 1, use_ray: bool = False,
              out: Path = DEFAULT_OUT, progress: Callable[[int, int], None] | None = None, sizes: dict | None = None,
              log: Callable[[str], None] | None = None, command: str | None = None) -> Path:
    """Run recipe `name` at `size` ("small" | "full") into OUT/NAME/ (resuming from the records
    there) and write OUT/NAME/NAME.md; returns that file. seed_start: the first seed (None: the
    recipe's); workers / use_ray: for the benches that run jobs in parallel (the others run in this
    process); progress(done, total): work items done, resumed ones included; sizes: counts that
    replace the size's (Python API only, e.g. tiny runs in the tests); log: the benches' messages
    (default: dropped); command: the command line to record (default: the `ms-drake reproduce` one)."""
    recipe = get_recipe(name)
    if size not in SIZES:
        raise ReproduceError(f"unknown size {size!r} for recipe {name}; choose one of {', '.join(SIZES)}")
    counts = dict(getattr(recipe, size))
    if sizes:
        unknown = sorted(set(sizes) - set(counts) - set(recipe.options))
        if unknown:
            raise ReproduceError(f"sizes {', '.join(unknown)} unknown for recipe {name}; "
                                 f"give some of {', '.join(list(counts) + list(recipe.options))}")
        counts.update(sizes)
    if workers < 1:
        raise ReproduceError(f"workers {workers}: give 1 or more")
    seed = recipe.seed_start if seed_start is None else int(seed_start)
    folder = Path(out) / name
    folder.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), _cpu_seconds()
    run = Run(folder, counts, seed, int(workers), bool(use_ray), Progress(progress, recipe.total(counts)),
              log or (lambda msg: None))
    result = recipe.run(run)
    run.progress.set(run.progress.total)
    path = folder / f"{name}.md"
    _write_markdown(recipe, result, path, command or _command(name, size, seed, workers, use_ray, Path(out), sizes),
                    size, counts, time.perf_counter() - t0, _cpu_seconds() - c0)
    return path


__all__ = ["RECIPES", "Recipe", "ReproduceError", "list_recipes", "reproduce"]
