"""Full-fidelity pick 'yumi_suction' from the home pose; writes a Meshcat recording (sims/out/yumi_suction.html).

    .venv/bin/python sims/pick_yumi_suction.py [--html PATH] [--speed M_PER_S]    # = ms-drake pick yumi_suction ...
"""

import sys

from ms_drake.cli import main

if __name__ == "__main__":
    sys.argv = ["ms-drake", "pick", "yumi_suction", "--html", "sims/out/yumi_suction.html", *sys.argv[1:]]
    main()
