"""One box pushed 7.5 cm along x (tests/test_push_fidelity.py's scene) by the study's primitive
mode at 10, 5 and 2 ms plant steps and by the YuMi: the box's displacement and yaw change.

    .venv/bin/python sims/push_fidelity_box.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_push_fidelity import X0, Y0, _box_record

from ms_drake.experiments.push_fidelity import FidelityPair
from ms_drake.experiments.push_study import StudyParams
from ms_drake.types import Push


def main():
    rec = _box_record()
    for ts in (0.01, 0.005, 0.002):
        pair = FidelityPair(rec, StudyParams(time_step=ts))
        oid = pair.ids[0]
        push = Push((X0 - 0.045, Y0, 0.025), (X0 + 0.03, Y0, 0.025), oid)
        sides = ("primitive", "full") if ts == 0.01 else ("primitive",)
        for side in sides:
            m = pair.execute(side, push)["motion"][oid]
            step = "2 ms (YuMiBin)" if side == "full" else f"{1000 * ts:.0f} ms"
            print(f"{side:9s} {step:15s} dx {100 * m['dxy'][0]:5.1f} cm  dy {100 * m['dxy'][1]:5.1f} cm  "
                  f"yaw {np.degrees(m['yaw']):6.1f} deg")


if __name__ == "__main__":
    main()
