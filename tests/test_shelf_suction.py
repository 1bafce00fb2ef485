"""The bluction tool's suction cup on the Fetch in physics (ms_drake.station.suction): a box held by
its front face, its weight acting behind the cup, is lifted, pulled out and placed while the
moment about the cup's lip is within what the seal holds (about f r = 40 N x 15 mm = 0.6 N m), and
falls when it is beyond (replay_shelf_action: one suction action played on the FetchShelf station)."""

import pytest

from ms_drake.execution.shelf_backend import agreement
from ms_drake.experiments.shelf_physics import DENSITY, ShelfPhysicsError, replay_shelf_action, shelf_object_sdf
from ms_drake.types import ShelfAction, ShelfObject, ShelfScene

# Seed 0's occ05 (8 occluders): 16.5 x 18.7 x 14.3 cm, 0.66 kg at DENSITY; its weight acts 9.4 cm
# behind the cup: 0.61 N m about it.
OCC05 = ShelfObject("occ00", "box", 0.0, -0.05, 0.165, 0.187, 0.143)
TARGET = ShelfObject("target", "box", 0.2, 0.2, 0.06, 0.06, 0.06)
SCENE = ShelfScene((OCC05,), TARGET, 0)
ACTION = ShelfAction("suction", "occ00", -0.15, 0.05)


def _fields(message):
    return dict(tok.split("=", 1) for tok in message.split() if "=" in tok)


@pytest.mark.slow  # ~12 s of simulated time
def test_front_face_grip_of_a_box_like_occ05_lifts_pulls_and_places():
    """Sealed from contact to release, its front lifted, tilted ~20 degrees on the compliant lip.
    At 0.61 N m the box is at the cup's limit f r: with the lift of an empty shelf its back edge
    rests on the floor while it is pulled (lifted clear over taller objects it peels off at ~24
    degrees: docs/results/ch9_shelf.md)."""
    r = replay_shelf_action(SCENE, ACTION)
    f = _fields(r.outcome.message)
    assert r.outcome.success and agreement(r.outcome), r.outcome.message  # where FOSS puts it, nothing else moved
    assert float(f["err"]) < 0.02 and f["toppled"] == "-"
    vacuum = r.log[r.log[:, 1] > 0.5]
    first, last = r.sealed_span()
    assert first <= vacuum[0, 0] + 0.3 and last >= vacuum[-1, 0] - 0.15  # sealed from contact to release
    assert r.max_tilt_sealed() < 25.0  # sagging on the compliant lip, not peeled off
    lifted = r.log[(r.log[:, 2] > 0.5) & (r.log[:, 5] < OCC05.y - 0.1)]
    assert len(lifted) and lifted[:, 6].max() > OCC05.height / 2 + 0.02  # pulled out lifted


@pytest.mark.slow
def test_a_load_beyond_the_seal_falls():
    """The same box at three times the density (1.98 kg, 1.8 N m about the cup, three times f r)."""
    r = replay_shelf_action(SCENE, ACTION, density=3 * DENSITY)
    vacuum = r.log[r.log[:, 1] > 0.5]
    assert not r.outcome.success, r.outcome.message  # moved less than half the way
    assert not vacuum[-1, 2] and r.sealed_span() is not None  # sealed at contact, lost before the release


def test_replay_bad_inputs():
    with pytest.raises(ShelfPhysicsError, match="density"):
        shelf_object_sdf(OCC05, (1, 1, 1, 1), density=0.0)
    tall = ShelfScene((ShelfObject("occ00", "box", 0.0, -0.05, 0.1, 0.1, 0.5),), TARGET, 0)
    with pytest.raises(ShelfPhysicsError, match="does not plan.*shelf_top"):  # the raised blade would hit the top
        replay_shelf_action(tall, ShelfAction("suction", "occ00", -0.15, 0.05))
