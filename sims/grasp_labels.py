"""Physics labels and the AP / AR table of the grasp contact models (Table 2.1 / 3.1 analogue).

  python sims/grasp_labels.py labels   [--objects 24] [--grasps 45] [--trials 2] [--pad JSON]
  python sims/grasp_labels.py predict  [--param-sets 8] [--robust 10]
  python sims/grasp_labels.py table

Each stage appends to its file and resumes where it stopped (one process; run in the
background with nohup). Files: out/grasp_labels.jsonl and out/grasp_predictions.jsonl, or --labels and
--predictions.
"""

import argparse
import json
from pathlib import Path

from ms_drake.grasping import labels as L
from ms_drake.robots import PadConfig

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage", choices=["labels", "predict", "table", "all"])
    ap.add_argument("--labels", type=Path, default=ROOT / "out/grasp_labels.jsonl")
    ap.add_argument("--predictions", type=Path, default=ROOT / "out/grasp_predictions.jsonl")
    ap.add_argument("--objects", type=int, default=24)
    ap.add_argument("--object-names", nargs="*", default=None)
    ap.add_argument("--grasps", type=int, default=45)
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--closing-force", type=float, default=10.0)
    ap.add_argument("--pad", type=json.loads, default=None,
                    help="the jaw pad as ms_drake.robots.PadConfig keywords in JSON (default: the station's pad)")
    ap.add_argument("--param-sets", type=int, default=8)
    ap.add_argument("--robust", type=int, default=10)
    ap.add_argument("--models", nargs="*", default=list(L.MODELS))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.stage in ("labels", "all"):
        names = args.object_names or L.default_label_objects(args.objects)
        print("objects:", " ".join(names), flush=True)
        L.generate_labels(names, args.labels, args.grasps, args.trials, args.seed, args.closing_force,
                          pad=PadConfig(**args.pad) if args.pad else None, log=lambda s: print(s, flush=True))
    if args.stage in ("predict", "all"):
        L.predict(args.labels, args.predictions, args.models, args.param_sets, args.robust, args.closing_force,
                  args.seed, log=lambda s: print(s, flush=True))
    if args.stage in ("table", "all"):
        rows = L._read_jsonl(args.labels)
        table = L.loo_table(args.labels, args.predictions)
        text = L.format_table(table, len(rows), len({r["object"] for r in rows}))
        pos = sum(r["label"] >= 0.5 for r in rows)
        text += f" Positives (physics success rate >= 0.5): {pos} / {len(rows)}."
        print(text)
        print(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
