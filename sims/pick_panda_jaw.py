"""Full-fidelity pick 'panda_jaw' from the home pose; writes a Meshcat recording (sims/out/panda_jaw.html).

    .venv/bin/python sims/pick_panda_jaw.py [--html PATH] [--no-meshcat] [--speed M_PER_S]
"""

from ms_drake.experiments.picks import main

if __name__ == "__main__":
    main("panda_jaw")
