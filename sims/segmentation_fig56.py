"""Fig. 5.6 analogue: COCO mask AP / AR@100 of the learned depth segmenter against the number of
training images and the fraction of training objects (Ch. 5.6, lines 972-976).

    nice -n 10 .venv/bin/python sims/segmentation_fig56.py --data /work/datasets/segmentation \
        --root /work/seg_fig56 --steps 500 --images 300 --seed-start 100000 --workers 1 \
        --cache /work/datasets/segbench_cache --out docs/data/segmentation_fig56.json \
        --plot docs/img/segmentation_fig56.png

Every run is the shipped recipe (`ms-drake train segmentation`: the same network, AdamW lr 2e-3
with cosine decay, batches of 16 windows of 96 x 128, seed 0, one torch thread) with the same
budget of --steps optimizer steps (5 epochs of steps/5 batches), on
- the first N train images of --data, N in --sizes (the image curve, all objects), and
- all train images with only a fraction of the training objects supervised, per object set
  (--object-fractions; `--object-fraction` of the trainer: the other objects' pixels carry no
  loss, the images stay; the object curve).
Each run's weights are benchmarked on the same held-out images (`ms-drake bench segmentation
--backend learned --images --seed-start --weights`). Weights and benchmark files go under --root
(not in git); a run whose weights are complete and whose benchmark file exists is skipped, and a
killed training resumes from its checkpoint, so rerunning the command resumes. --out gets the
curve data, --plot the figure (matplotlib; dotted: the shipped net on the same images, from
docs/data/segmentation_bench_learned.json).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import matplotlib.ticker
import torch

ROOT = Path(__file__).resolve().parent.parent
CLI = str(ROOT / ".venv" / "bin" / "ms-drake")
EPOCHS = 5


def runs(sizes, fractions, total: int) -> list[dict]:
    """The training runs: (name, max_images or None for all, object fraction or None for all), the
    curves' ends first (an interrupted sweep still spans each axis)."""
    img = [dict(name=f"images_{n}", images=n, fraction=None) for n in sorted(sizes) if n < total]
    obj = [dict(name=f"objects_{f:g}", images=None, fraction=f) for f in sorted(fractions) if f < 1]
    out = [dict(name="images_all", images=None, fraction=None)] + img[:1] + obj[:1]
    mid = img[len(img) // 2:len(img) // 2 + 1]
    return out + mid + obj[1:] + [r for r in img if r not in out + mid]


def weights_complete(path: Path) -> dict | None:
    """The meta of a finished run's weights file, or None (missing or still training)."""
    if not path.exists():
        return None
    meta = torch.load(path, map_location="cpu", weights_only=False)["meta"]
    return meta if meta["epochs_done"] == meta["epochs"] else None


def train(run: dict, args, weights: Path) -> None:
    cmd = [CLI, "train", "segmentation", "--data", str(args.data), "--out", str(weights), "--epochs", str(EPOCHS),
           "--steps-per-epoch", str(args.steps // EPOCHS), "--batch", "16", "--lr", "0.002", "--seed",
           str(args.seed), "--threads", "1", "--max-minutes", "600"]
    if run["images"]:
        cmd += ["--max-images", str(run["images"])]
    if run["fraction"] is not None:
        cmd += ["--object-fraction", str(run["fraction"])]
    print(" ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def bench(args, weights: Path, out: Path) -> None:
    cmd = [CLI, "bench", "segmentation", "--backend", "learned", "--images", str(args.images), "--seed-start",
           str(args.seed_start), "--workers", str(args.workers), "--weights", str(weights), "--out", str(out)]
    if args.cache:
        cmd += ["--cache", str(args.cache)]
    print(" ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def plot(rows: list[dict], path: Path, shipped: dict | None = None) -> None:
    """Both curves; `shipped`: the shipped net's benchmark on the same images (dotted lines)."""
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), sharey=True)
    img = sorted((r for r in rows if r["object_fraction"] is None), key=lambda r: r["train_images"])
    obj = sorted((r for r in rows if r["train_images"] == max(x["train_images"] for x in rows)),
                 key=lambda r: r["objects_trained"])
    for ax, pts, key, label in ((axes[0], img, "train_images", "training images"),
                                (axes[1], obj, "objects_trained", "training objects supervised")):
        for m, style in (("ap", "o-"), ("ar", "s--")):
            ax.plot([p[key] for p in pts], [p[m] for p in pts], style, label=m.upper() if m == "ap" else "AR@100")
        ax.set_xscale("log")
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.set_xticks(sorted({p[key] for p in pts}))
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        if shipped is not None:
            ax.axhline(shipped["ap"], color="C0", ls=":", lw=1, label="shipped net AP (2,000 steps)")
            ax.axhline(shipped["ar"], color="C1", ls=":", lw=1, label="shipped net AR@100")
        ax.set_xlabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("COCO mask AP / AR@100 (held-out)")
    axes[0].legend(fontsize=7)
    n = rows[0]["bench_images"] if rows else 0
    fig.suptitle(f"Learned depth segmentation, {rows[0]['steps'] if rows else 0} steps per run, "
                 f"{n} held-out images", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="dataset folder (ms-drake data segmentation)")
    p.add_argument("--root", type=Path, default=Path("/work/seg_fig56"), help="weights and bench files (not git)")
    p.add_argument("--steps", type=int, default=500, help="optimizer steps per run (a multiple of 5)")
    p.add_argument("--sizes", type=int, nargs="+", default=[250, 500, 1000, 2000], help="training image counts")
    p.add_argument("--object-fractions", type=float, nargs="+", default=[0.25, 0.5], help="object fractions")
    p.add_argument("--images", type=int, default=300, help="held-out benchmark images")
    p.add_argument("--seed-start", type=int, default=100000, help="seed of the first benchmark image")
    p.add_argument("--seed", type=int, default=0, help="training seed (and object subsets)")
    p.add_argument("--workers", type=int, default=1, help="benchmark workers")
    p.add_argument("--cache", type=Path, default=None, help="benchmark image cache (ms-drake bench --cache)")
    p.add_argument("--only", nargs="+", default=None, help="run only these runs (names), e.g. images_250")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "data" / "segmentation_fig56.json")
    p.add_argument("--plot", type=Path, default=ROOT / "docs" / "img" / "segmentation_fig56.png")
    args = p.parse_args(argv)
    if args.steps % EPOCHS:
        p.error(f"--steps {args.steps}: give a multiple of {EPOCHS} (the runs have {EPOCHS} epochs)")
    total = len(json.loads((args.data / "coco_train.json").read_text())["images"])
    rows = []
    for run in runs(args.sizes, args.object_fractions, total):
        weights = args.root / f"{run['name']}.pt"
        result = args.root / f"{run['name']}_bench{args.images}_{args.seed_start}.json"
        meta = weights_complete(weights)
        if meta is None and (args.only is None or run["name"] in args.only):
            train(run, args, weights)
            meta = weights_complete(weights)
        if meta is None:
            continue
        if not result.exists():
            bench(args, weights, result)
        res = json.loads(result.read_text())
        rows.append(dict(run=run["name"], train_images=meta["train_images"], object_fraction=run["fraction"],
                         objects_seen=meta.get("objects_seen"),
                         objects_trained=meta.get("objects_trained") or meta.get("objects_seen"),
                         steps=args.steps, train_seconds=meta["seconds"],
                         final_loss=meta["history"][-1]["loss"], ap=res["ap"], ap50=res["ap50"], ar=res["ar"],
                         bench_images=res["images"], bench_seed_start=args.seed_start, command=meta["command"]))
        print(f"{run['name']}: {meta['train_images']} images, AP {res['ap']:.3f}, AR {res['ar']:.3f}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(dict(runs=rows, steps=args.steps, batch=16, epochs=EPOCHS, seed=args.seed,
                                        data=str(args.data), command=" ".join(sys.argv)), indent=1))
    shipped_file = ROOT / "docs" / "data" / "segmentation_bench_learned.json"
    shipped = json.loads(shipped_file.read_text()) if shipped_file.exists() else None
    if shipped is not None and (shipped["images"], shipped["seed_start"]) != (args.images, args.seed_start):
        shipped = None
    if rows:
        plot(rows, args.plot, shipped)
    print(f"wrote {args.out} and {args.plot} ({len(rows)} runs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
