"""Full-fidelity pick 'fetch_push' from the home pose; writes a Meshcat recording (sims/out/fetch_push.html).

    .venv/bin/python sims/pick_fetch_push.py [--html PATH] [--speed M_PER_S]    # = ms-drake pick fetch_push ...
"""

import sys

from ms_drake.cli import main

if __name__ == "__main__":
    sys.argv = ["ms-drake", "pick", "fetch_push", "--html", "sims/out/fetch_push.html", *sys.argv[1:]]
    main()
