"""Full-fidelity pick 'yumi_jaw' from the home pose; writes a Meshcat recording (sims/out/yumi_jaw.html).

    .venv/bin/python sims/pick_yumi_jaw.py [--html PATH] [--speed M_PER_S]    # = ms-drake pick yumi_jaw ...
"""

import sys

from ms_drake.cli import main

if __name__ == "__main__":
    sys.argv = ["ms-drake", "pick", "yumi_jaw", "--html", "sims/out/yumi_jaw.html", *sys.argv[1:]]
    main()
