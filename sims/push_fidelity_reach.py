"""Which of the push study's recorded pushes the YuMi's right arm can plan, at the recorded height
and with the tool centre raised (ms_drake.experiments.push_fidelity.reach_probe; planning only).

    .venv/bin/python sims/push_fidelity_reach.py --heap-dir docs/data/push_heaps --heaps 27 --out docs/data/push_fidelity_reach.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ms_drake.experiments.push_fidelity import reach_probe


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--heap-dir", type=Path, action="append", required=True)
    ap.add_argument("--heaps", type=int, default=27)
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    res = reach_probe(a.heap_dir, a.heaps, a.seed_start)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res))


if __name__ == "__main__":
    main()
