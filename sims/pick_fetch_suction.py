"""Full-fidelity pick 'fetch_suction' from the home pose; writes a Meshcat recording (sims/out/fetch_suction.html).

    .venv/bin/python sims/pick_fetch_suction.py [--html PATH] [--speed M_PER_S]    # = ms-drake pick fetch_suction ...
"""

import sys

from ms_drake.cli import main

if __name__ == "__main__":
    sys.argv = ["ms-drake", "pick", "fetch_suction", "--html", "sims/out/fetch_suction.html", *sys.argv[1:]]
    main()
