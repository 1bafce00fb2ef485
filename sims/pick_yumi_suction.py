"""Full-fidelity pick 'yumi_suction' from the home pose; writes a Meshcat recording (sims/out/yumi_suction.html).

    .venv/bin/python sims/pick_yumi_suction.py [--html PATH] [--no-meshcat] [--speed M_PER_S]
"""

from ms_drake.experiments.picks import main

if __name__ == "__main__":
    main("yumi_suction")
