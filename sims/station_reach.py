"""Station reach: the share of the primitive mode's grasps (the best grasp per gripper kind of
every visible object at the heap's initial state) that bin stations' robots execute
(ms_drake.experiments.station_reach), per station and gripper, with pictures of a few misses.

    .venv/bin/python sims/station_reach.py --scenario YuMiBin PandaBin --heaps 200 --seed-start 9000 \\
        --out out/station_reach.jsonl --misses out/station_reach_misses --heap-dir out/heaps

`--examples DIR` draws one miss per station, gripper and reason from the records instead.
Resumable: heaps already in --out are not measured again. --scenario-file: another scenarios
file (e.g. an older layout: `git show <commit>:diagrams/scenarios.yaml > old.yaml`).
"""

from __future__ import annotations

import argparse
import json
import sys

from ms_drake.experiments.station_reach import (
    draw_examples,
    format_summary,
    read_records,
    run_station_reach,
    summarize,
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", nargs="+", default=["YuMiBin", "PandaBin"], help="bin stations with an arm")
    ap.add_argument("--scenario-file", default=None, help="scenarios file (default: the shipped diagrams/scenarios.yaml)")
    ap.add_argument("--heaps", type=int, default=20)
    ap.add_argument("--seed-start", type=int, default=9000)
    ap.add_argument("--objects", type=int, default=15)
    ap.add_argument("--heap-dir", default=None, help="cache of the generated heaps (shared between runs)")
    ap.add_argument("--out", required=True, help="JSON lines, one per heap (resumable)")
    ap.add_argument("--misses", default=None, help="folder for pictures of missed grasps")
    ap.add_argument("--pictures", type=int, default=6, help="pictures per station")
    ap.add_argument("--summary", default=None, help="also write the summary as JSON here")
    ap.add_argument("--examples", default=None,
                    help="only draw one miss per station, gripper and reason from the records in --out into this folder")
    a = ap.parse_args(argv)
    if a.examples:
        for p in draw_examples(read_records(a.out), a.examples, a.objects, a.heap_dir):
            print(p)
        return 0
    records = run_station_reach(a.scenario, a.heaps, a.seed_start, a.out, scenario_file=a.scenario_file,
                                objects=a.objects, heap_dir=a.heap_dir, misses_dir=a.misses,
                                max_pictures=a.pictures, progress=lambda m: print(m, flush=True))
    summary = summarize(records)
    print(format_summary(summary, len(records)))
    if a.summary:
        with open(a.summary, "w") as f:
            json.dump(summary, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
