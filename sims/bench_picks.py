"""Benchmark of the full-fidelity picks: real-time factor of each task from the home pose.

    .venv/bin/python sims/bench_picks.py [--repeats 3] [--tasks yumi_jaw ...] [--out docs/bench_picks.json]

For every task (ms_drake.experiments.picks.TASKS) the pick is planned (IK + ruckig, not timed) and
simulated without visualization; reported per run: simulated seconds, wall seconds, CPU seconds of
this process, RTF = simulated / wall and RTF(cpu) = simulated / CPU. On a shared machine the CPU
figure is the one-core cost (the wall figure also counts time the process waited for a core).
The compliant-pad pick of the issue's speed target is `yumi_jaw` (target RTF >= 0.5 on one core).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import numpy as np


def main(argv=None):
    from ms_drake.experiments.picks import TASKS, run_task

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--tasks", nargs="*", default=list(TASKS))
    parser.add_argument("--out", default="docs/bench_picks.json")
    args = parser.parse_args(argv)
    rows = {}
    for name in args.tasks:
        runs = [run_task(TASKS[name], from_home=True) for _ in range(args.repeats if name == "yumi_jaw" else 1)]
        rows[name] = {
            "success": [bool(r.success) for r in runs],
            "sim_seconds": runs[0].sim_seconds,
            "wall_seconds": [r.wall_seconds for r in runs],
            "cpu_seconds": [r.cpu_seconds for r in runs],
            "rtf_wall_median": float(np.median([r.real_time_factor for r in runs])),
            "rtf_cpu_median": float(np.median([r.cpu_real_time_factor for r in runs])),
            "lifted": [r.lifted for r in runs], "moved": [r.moved for r in runs],
        }
        r = rows[name]
        print(f"{name:14s} success={all(r['success'])} sim={r['sim_seconds']:.2f}s "
              f"RTF(cpu)={r['rtf_cpu_median']:.2f} RTF(wall)={r['rtf_wall_median']:.2f} runs={len(runs)}", flush=True)
    result = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, no GPU, shared",
              "load_average_at_end": os.getloadavg(), "tasks": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print("wrote", args.out)


if __name__ == "__main__":
    main()
