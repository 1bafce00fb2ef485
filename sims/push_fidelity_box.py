"""One box (tests/test_push_fidelity.py's scene) pushed 7.5 cm along x and along the diagonal by
the primitive mode at several plant steps and push speeds, and by the YuMi: the box's
displacement and yaw change (what PRIMITIVE_PUSH_TIME_STEP rests on).

    .venv/bin/python sims/push_fidelity_box.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_push_fidelity import X0, Y0, _box_record

from ms_drake.execution import PrimitiveBackend
from ms_drake.experiments.push_fidelity import FidelityPair
from ms_drake.experiments.push_study import StudyParams
from ms_drake.types import Push

# (plant step [s], push speed [m/s]) of the primitive side; the YuMi runs at its own 2 ms
PRIMITIVE = ((0.01, 0.15), (0.01, 0.10), (0.01, 0.05), (0.007, 0.15), (0.006, 0.15), (0.005, 0.15), (0.002, 0.15))
PUSHES = {"x": ((-0.045, 0.0), (0.03, 0.0)), "diagonal": ((-0.032, -0.032), (0.021, 0.021))}


def main():
    rec = _box_record()
    for k, (ts, speed) in enumerate(PRIMITIVE):
        pair = FidelityPair(rec, StudyParams(time_step=ts))
        w = pair.worlds["primitive"][0]
        b = w.backend
        w.backend = PrimitiveBackend(b.objects, b.workspace, b.tcp_offset, push_speed=speed)
        oid = pair.ids[0]
        for name, (a, e) in PUSHES.items():
            push = Push((X0 + a[0], Y0 + a[1], 0.025), (X0 + e[0], Y0 + e[1], 0.025), oid)
            for side in ("primitive", "full") if k == 0 else ("primitive",):
                m = pair.execute(side, push)["motion"][oid]
                label = "YuMi, 2 ms" if side == "full" else f"{1000 * ts:.0f} ms, {speed:.2f} m/s"
                print(f"{name:8s} {label:17s} dx {100 * m['dxy'][0]:5.1f} cm  dy {100 * m['dxy'][1]:5.1f} cm  "
                      f"yaw {np.degrees(m['yaw']):6.1f} deg", flush=True)


if __name__ == "__main__":
    main()
