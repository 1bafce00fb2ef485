"""Full-fidelity pick 'fetch_push' from the home pose; writes a Meshcat recording (sims/out/fetch_push.html).

    .venv/bin/python sims/pick_fetch_push.py [--html PATH] [--no-meshcat] [--speed M_PER_S]
"""

from ms_drake.experiments.picks import main

if __name__ == "__main__":
    main("fetch_push")
