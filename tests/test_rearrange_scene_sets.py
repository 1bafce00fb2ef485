"""The rearrangement's scene sets (ms_drake.experiments.rearrange.set_scene): table, barrier, one_side."""

import json

import numpy as np
import pytest
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.common.eigen_geometry import Quaternion

from ms_drake.config_files import config_dict
from ms_drake.experiments.rearrange import (
    BARRIER,
    REACH,
    SCENARIO,
    SCENE_SETS,
    RearrangeError,
    bench_params,
    category_objects,
    rearrange_rollout,
    rearrange_table,
    run_rearrange_bench,
    set_scene,
)
from ms_drake.objects import get_object
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.scenes.tabletop import _stable_poses
from ms_drake.station import MakeStation, get_plant, station_objects


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(None, SCENARIO)


def _pose(o) -> RigidTransform:
    w, x, y, z, *p = o.q
    return RigidTransform(RotationMatrix(Quaternion(np.array([w, x, y, z]) / np.linalg.norm([w, x, y, z]))), p)


def _hull_world(o) -> np.ndarray:
    """The object's convex hull vertices in the world at its pose."""
    v = _stable_poses(o.name)[2]
    X = _pose(o)
    return v @ X.rotation().matrix().T + X.translation()


@pytest.mark.parametrize("seed", [0, 7])
def test_barrier_stands_across_the_table_between_the_objects_and_the_zone(scenario, seed):
    scene = set_scene(scenario, "barrier", seed, 10)
    top = float(scenario.environment.position[2])
    assert scene.fixtures == (0,) and scene.heap.objects[0].name == BARRIER
    assert len(scene.movable) == 10 and 0 not in scene.movable
    barrier = scene.heap.objects[0]
    size = np.asarray(get_object(BARRIER).extents)
    assert size[2] >= 0.25  # a tall box
    X = _pose(barrier)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size / 2
    B = corners @ X.rotation().matrix().T + X.translation()
    assert B[:, 2].min() == pytest.approx(top, abs=1e-3) and B[:, 2].max() >= top + 0.25  # standing on the table
    # across the reachable table: it spans the reach along its long side
    long_axis = X.rotation().matrix()[:, int(np.argmax(size[:2]))]
    normal = np.cross([0, 0, 1], long_axis)
    x0, x1, y0, y1 = REACH
    reach_corners = np.array([[x, y, top] for x in (x0, x1) for y in (y0, y1)])
    assert (B @ long_axis).min() <= (reach_corners @ long_axis).min() + 0.01
    assert (B @ long_axis).max() >= (reach_corners @ long_axis).max() - 0.01
    # the objects on one side of it, the whole zone on the other
    lo, hi = (B @ normal).min(), (B @ normal).max()
    sides = []
    for k in scene.movable:
        d = _hull_world(scene.heap.objects[k]) @ normal
        assert d.max() < lo or d.min() > hi, scene.heap.objects[k].name  # clear of the barrier
        sides.append(np.sign(d.mean() - (lo + hi) / 2))
    assert len(set(sides)) == 1
    zx0, zx1, zy0, zy1 = scene.zone
    zone_d = np.array([[x, y, top] for x in (zx0, zx1) for y in (zy0, zy1)]) @ normal
    assert np.all(np.sign(zone_d - (lo + hi) / 2) == -sides[0]) and (zone_d.min() > hi or zone_d.max() < lo)
    assert x0 - 1e-9 <= zx0 < zx1 <= x1 + 1e-9 and y0 - 1e-9 <= zy0 < zy1 <= y1 + 1e-9  # a reachable zone


def test_one_side_is_the_barrier_scene_without_the_barrier(scenario):
    barrier, one = set_scene(scenario, "barrier", 3, 10), set_scene(scenario, "one_side", 3, 10)
    assert one.fixtures == () and BARRIER not in [o.name for o in one.heap.objects]
    assert one.heap.objects == barrier.heap.objects[1:] and one.zone == barrier.zone
    zx0, zx1, zy0, zy1 = one.zone
    for o in one.heap.objects:  # every object starts outside the zone: each placement fills it further
        assert not (zx0 <= o.q[4] <= zx1 and zy0 <= o.q[5] <= zy1)


def test_scenes_are_reproducible_and_drawn_from_the_categories(scenario):
    a, b = set_scene(scenario, "barrier", 5, 10), set_scene(scenario, "barrier", 5, 10)
    assert a == b
    assert set_scene(scenario, "barrier", 6, 10).heap.objects != a.heap.objects
    pool = category_objects()
    assert set(pool) == {"box", "cylinder", "mug"} and all(pool.values())
    names = [o.name for o in a.heap.objects[1:]]
    assert len(set(names)) == len(names)
    cats = {c for c, v in pool.items() for n in names if n in v}
    assert len(cats) >= 2 and all(any(n in v for v in pool.values()) for n in names)
    for n in names:  # the 10 cm jaw holds each from above
        e = sorted(get_object(n).extents)
        assert e[1] < 0.085 and e[2] < 0.20
    assert set_scene(scenario, "table", 5, 6).heap.objects == set_scene(scenario, "table", 5, 6).heap.objects


def test_barrier_scene_loads_without_collision(scenario):
    scene = set_scene(scenario, "barrier", 0, 10)
    scn = scenario_with_heap(scenario, scene.heap)
    scn.cameras = {}
    station = MakeStation(scn)
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, scene.heap)
    plant = get_plant(station)
    barrier = station_objects(plant)[0]  # welded where the heap says
    assert barrier.full_name == BARRIER and plant.num_positions(barrier.model_instance) == 0
    X = plant.EvalBodyPoseInWorld(plant.GetMyContextFromRoot(ctx), plant.get_body(barrier.body_index))
    np.testing.assert_allclose(X.translation(), scene.heap.objects[0].q[4:], atol=1e-9)
    query = station.GetOutputPort("query_object").Eval(ctx)
    inspector = query.inspector()
    pairs = query.ComputePointPairPenetration()
    assert pairs  # the objects rest on the table
    for p in pairs:
        a, b = (plant.GetBodyFromFrameId(inspector.GetFrameId(g)) for g in (p.id_A, p.id_B))
        names = {plant.GetModelInstanceName(a.model_instance()), plant.GetModelInstanceName(b.model_instance())}
        if "environment" in names:
            # resting on the table: a mug's collision pieces reach ~1 mm past its visual mesh's hull
            assert p.depth < 2e-3
        else:
            pytest.fail(f"objects overlap at load: {names} by {p.depth:.4f} m")


def test_bad_scene_sets_and_the_table(scenario, tmp_path):
    for call in (lambda: set_scene(scenario, "shelf", 0), lambda: bench_params("net", 0, "shelf"),
                 lambda: run_rearrange_bench("net", 1, 0, tmp_path / "r.jsonl", scene_set="shelf")):
        with pytest.raises(RearrangeError, match="scene set 'shelf' unknown; choose one of table, barrier, one_side"):
            call()
    with pytest.raises(RearrangeError, match="40 objects: the barrier scenes draw from 32 objects; use fewer"):
        set_scene(scenario, "barrier", 0, 40)
    assert SCENE_SETS == ("table", "barrier", "one_side")
    assert bench_params("net", 0, "barrier").zone == list(set_scene(scenario, "barrier", 0, 2).zone)
    rec = {"seed": 0, "method": "net", "objects": 10, "grasps_attempted": 12, "grasps": 8, "placements": 6,
           "minutes": 3.0, "plan_cpu_seconds": 20.0, "cpu_seconds": 90.0, "config": config_dict(bench_params("net", 0))}
    table = rearrange_table([rec, dict(rec, scene_set="barrier", placed_without_contact=4)])
    assert "| table | net (T=300, H=40) | 1 | 10 | 8 / 12 | 6 | - |" in table
    assert "| barrier | net (T=300, H=40) | 1 | 10 | 8 / 12 | 6 | 4 |" in table
    # a record of another scene set is another run
    f = tmp_path / "r.jsonl"
    f.write_text(json.dumps(dict(rec, config=config_dict(bench_params("net", 0, "barrier")))) + "\n")
    assert run_rearrange_bench("net", 1, 0, f, objects=10, log=lambda *a: None, scene_set="table",
                               zone=list(REACH), max_sim=0.0) != []


def test_a_straight_line_over_the_barrier_touches_it(scenario):
    """ik_line (no collision checking) carries an object from the near side into the zone: the
    monitor sees the arm or the object touch the barrier and says so for that object."""
    r = rearrange_rollout("ik_line", 0, 1, max_sim=40.0, scene_set="barrier")
    assert r["scene_set"] == "barrier" and r["objects"] == 1
    o = r["per_object"][0]
    assert o["grasped"] and o["barrier_contact"] and r["placed_without_contact"] == 0
