"""Full-fidelity pick 'panda_jaw' from the home pose; writes a Meshcat recording (sims/out/panda_jaw.html).

    .venv/bin/python sims/pick_panda_jaw.py [--html PATH] [--speed M_PER_S]    # = ms-drake pick panda_jaw ...
"""

import sys

from ms_drake.cli import main

if __name__ == "__main__":
    sys.argv = ["ms-drake", "pick", "panda_jaw", "--html", "sims/out/panda_jaw.html", *sys.argv[1:]]
    main()
