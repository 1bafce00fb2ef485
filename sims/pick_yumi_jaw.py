"""Full-fidelity pick 'yumi_jaw' from the home pose; writes a Meshcat recording (sims/out/yumi_jaw.html).

    .venv/bin/python sims/pick_yumi_jaw.py [--html PATH] [--no-meshcat] [--speed M_PER_S]
"""

from ms_drake.experiments.picks import main

if __name__ == "__main__":
    main("yumi_jaw")
