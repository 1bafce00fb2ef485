"""Peak RSS of rollout workers with and without pool recycling (ms_drake.parallel).

    .venv/bin/python sims/bench_pool_memory.py 20 60 [HEAP_DIR]     # recycled every 2 x 20 jobs
    .venv/bin/python sims/bench_pool_memory.py 1000 60 [HEAP_DIR]   # no recycling

60 Largest rollouts of N = 15 heaps (seeds 1000-1059, cached in HEAP_DIR, default
sims/out/tables/heaps, generated there when missing) on 2 workers.
"""

import resource
import sys
import time

from ms_drake.experiments.harness import rollout_job
from ms_drake.parallel import run_jobs


def main():
    max_tasks, n = int(sys.argv[1]), int(sys.argv[2])
    heaps = sys.argv[3] if len(sys.argv) > 3 else "sims/out/tables/heaps"
    jobs = [("largest", 15, 1000 + k, "primitive", None, heaps) for k in range(n)]
    t = time.perf_counter()
    res = list(run_jobs(rollout_job, jobs, workers=2, max_tasks_per_child=max_tasks))
    print(f"max_tasks_per_child={max_tasks}: {n} rollouts, {sum(r.ok for r in res)} ok, "
          f"{time.perf_counter() - t:.0f} s wall, peak RSS of a worker "
          f"{resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024:.0f} MB, "
          f"worker processes {len({r.value['pid'] for r in res if r.ok})}")


if __name__ == "__main__":
    main()
