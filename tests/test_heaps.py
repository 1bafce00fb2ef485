"""Heaps: seeded, settled, inside the bin, target = least visible object, reloadable exactly."""

import dataclasses
import json

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from ms_drake.errors import HeapError, ScenarioError
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import (HeapParams, generate_heap, heap_from_dict, heap_to_dict, load_heap, save_heap,
                                   scenario_with_heap, set_heap_poses)
from ms_drake.scenes.tabletop import place_objects
from ms_drake.station import MakeStation, get_plant, station_objects


def test_heap_is_deterministic_for_a_seed(bin_scenario, small_heap):
    from ms_drake.scenes.heaps import SEARCH_HEAPS

    again = generate_heap(bin_scenario, 4, seed=3, params=SEARCH_HEAPS)  # small_heap's params
    assert again.object_names() == small_heap.object_names()
    for a, b in zip(again.objects, small_heap.objects):
        np.testing.assert_array_equal(a.matrix(), b.matrix())
    bullet = [generate_heap(bin_scenario, 4, seed=3) for _ in range(2)]  # the default engine (Bullet) too
    assert bullet[0] == dataclasses.replace(bullet[1], seconds=bullet[0].seconds)
    other = generate_heap(bin_scenario, 4, seed=4, params=SEARCH_HEAPS)
    assert other.object_names() == ["procedural/packaged_290", "procedural/packaged_377", "procedural/cylinder_352",
                                    "procedural/box_204"]  # seed 4: other objects than seed 3


def test_heap_lies_in_the_bin_and_target_is_least_visible(bin_scenario, small_heap):
    size = bin_scenario.environment.resolved_size()
    assert 1 <= len(small_heap.objects) <= 4
    for o in small_heap.objects:
        p = o.matrix()[:3, 3]
        assert np.all(np.abs(p[:2]) <= size[:2] / 2 + 1e-3) and -0.02 < p[2] < size[2] + 0.2
    r = np.array(small_heap.visible_ratios)
    assert np.all((r >= 0) & (r <= 1.0 + 1e-6))
    assert small_heap.target_index == int(np.argmin(r))
    assert small_heap.target == small_heap.objects[small_heap.target_index].name


def test_heap_reloads_exactly_and_stays_put(bin_scenario, small_heap, tmp_path):
    save_heap(small_heap, tmp_path / "h.json")
    heap = load_heap(tmp_path / "h.json")
    assert heap == small_heap  # frozen dataclass equality: names, every pose float, target
    s = scenario_with_heap(bin_scenario, heap)
    station = MakeStation(s, target_index=heap.target_index)
    sim = Simulator(station)
    ctx = sim.get_mutable_context()
    set_heap_poses(station, ctx, heap)
    plant = get_plant(station)
    pc = plant.GetMyContextFromRoot(ctx)
    for o, op in zip(station_objects(plant), heap.objects):
        np.testing.assert_array_equal(plant.GetPositions(pc, o.model_instance), np.asarray(op.q))
        np.testing.assert_allclose(plant.EvalBodyPoseInWorld(pc, plant.get_body(o.body_index)).GetAsMatrix4(),
                                   op.matrix(), atol=1e-12)
    sim.AdvanceTo(0.3)  # a settled heap barely moves in the station's own (rigid, point) physics
    moved = [np.linalg.norm(plant.EvalBodyPoseInWorld(pc, plant.get_body(o.body_index)).translation()
                            - op.matrix()[:3, 3]) for o, op in zip(station_objects(plant), heap.objects)]
    assert np.median(moved) < 0.005 and max(moved) < 0.05, moved


def test_heap_json_round_trip_is_exact(small_heap):
    d = json.loads(json.dumps(heap_to_dict(small_heap)))
    assert heap_from_dict(d) == small_heap


def test_impossible_heaps_are_clear_errors(bin_scenario):
    with pytest.raises(HeapError, match="do not fit"):
        generate_heap(bin_scenario, 5000, seed=0)
    with pytest.raises(HeapError, match="at least 1"):
        generate_heap(bin_scenario, 0, seed=0)
    with pytest.raises(ScenarioError, match="bin environment"):
        generate_heap(load_scenario(None, "PandaTable"), 3, seed=0)


def test_failed_attempts_are_resampled(bin_scenario):
    # Force every settle check to fail for attempt 0 by giving no time to settle; the
    # generator must report the reason instead of returning an unsettled heap.
    params = HeapParams(max_final_time=0.05, min_final_time=0.05, settle_linear=1e-9, max_attempts=2)
    with pytest.raises(HeapError, match=r"did not settle.*still moving at"):
        generate_heap(bin_scenario, 2, seed=1, params=params)


def test_table_scene_is_collision_free_and_resting():
    s = load_scenario(None, "PandaTable")
    s.robot.name = ""
    names = ["procedural/box_003", "procedural/cylinder_001", "procedural/packaged_002", "procedural/box_006"]
    scene = place_objects(s, names, seed=5)
    assert scene == place_objects(s, names, seed=5)
    s2 = scenario_with_heap(s, scene)
    station = MakeStation(s2)
    sim = Simulator(station)
    set_heap_poses(station, sim.get_mutable_context(), scene)
    plant = get_plant(station)
    ctx = sim.get_context()
    query = station.GetOutputPort("query_object").Eval(ctx)
    pairs = [p for p in query.ComputePointPairPenetration()]
    objs = {o.model_instance for o in station_objects(plant)}
    # Only object-table touching (depth < 2 mm), never object-object.
    for p in pairs:
        a = plant.GetBodyFromFrameId(query.inspector().GetFrameId(p.id_A)).model_instance()
        b = plant.GetBodyFromFrameId(query.inspector().GetFrameId(p.id_B)).model_instance()
        assert not (a in objs and b in objs)
        assert p.depth < 0.002
    sim.AdvanceTo(0.3)
    for o, op in zip(station_objects(plant), scene.objects):
        p = plant.EvalBodyPoseInWorld(plant.GetMyContextFromRoot(ctx), plant.get_body(o.body_index)).translation()
        assert np.linalg.norm(p - op.matrix()[:3, 3]) < 0.01


def test_heaps_of_mesh_objects(bin_scenario):
    from ms_drake.objects import available_sets

    for set_name in ("ycb", "random_urdfs"):
        assert set_name in available_sets()
        heap = generate_heap(bin_scenario, 3, seed=1, object_set=set_name)
        assert all(o.name.startswith(set_name + "/") for o in heap.objects)
        assert heap.target in heap.object_names()


def test_station_check_sees_penetration_and_motion(bin_scenario, small_heap):
    from dataclasses import replace

    from ms_drake.scenes.heaps import station_check
    from ms_drake.types import ObjectPose

    ok = station_check(bin_scenario, small_heap, seconds=0.1)
    assert all(np.all(np.isfinite(v)) for v in ok.values())
    assert ok["max_penetration"] < 0.02 and ok["max_displacement"] < 0.05, ok
    # Put object 1 where object 0 is: the two overlap deeply and fly apart in the station.
    a, b = small_heap.objects[0], small_heap.objects[1]
    bad = replace(small_heap, objects=(a, ObjectPose(b.name, a.q)) + small_heap.objects[2:])
    c = station_check(bin_scenario, bad, seconds=0.1)
    assert c["max_penetration"] > 0.01 and c["max_displacement"] > ok["max_displacement"], (ok, c)


def test_hydroelastic_tessellation_option_only_changes_round_shapes():
    from ms_drake.objects.sdf import Shape, hydroelastic_xml

    cyl, box = Shape("cylinder", (0.04, 0.1)), Shape("box", (0.1, 0.1, 0.1))
    hint = lambda xml: float(xml.split("<drake:mesh_resolution_hint>")[1].split("<")[0])  # noqa: E731
    assert hint(hydroelastic_xml(cyl, "compliant", 5e6, 8)) > hint(hydroelastic_xml(cyl, "compliant", 5e6))
    assert hydroelastic_xml(box, "compliant", 5e6, 8) == hydroelastic_xml(box, "compliant", 5e6)
    assert hydroelastic_xml(cyl, "rigid", 5e6) == hydroelastic_xml(cyl, "rigid", 5e6, 12)


def test_compliant_station_objects_keep_a_15_object_heap_in_place():
    """Heaps settle with compliant-hydroelastic objects; bin scenarios load them with the same
    contact (objects.compliance: compliant). Rigid objects (point contact) pop apart. The heap is
    a saved one (tests/data) so the check does not depend on the heap generator's version."""
    import copy
    from pathlib import Path

    from ms_drake.scenes.heaps import station_check

    heap = load_heap(Path(__file__).parent / "data" / "heap_N15_s1000.json")
    compliant = load_scenario(None, "BinHeap15")
    assert compliant.objects.compliance == "compliant"
    rigid = copy.deepcopy(compliant)
    rigid.objects.compliance = "rigid"
    c, r = station_check(compliant, heap, 0.3), station_check(rigid, heap, 0.3)
    assert c["median_displacement"] < 0.002, c
    assert c["max_displacement"] < r["max_displacement"] and r["max_displacement"] > 0.01, (c, r)


def test_object_compliance_is_validated(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text("S:\n  objects: { set: procedural, count: 2, compliance: squishy }\n")
    with pytest.raises(ScenarioError, match="objects.compliance.*squishy.*rigid, compliant"):
        load_scenario(f, "S")


def _contact_properties(plant, inspector, bodies) -> list:
    """Per body, per collision geometry: shape type and every proximity property Python can read."""
    out = []
    for body in bodies:
        for gid in plant.GetCollisionGeometriesForBody(body):
            props, row = inspector.GetProximityProperties(gid), {}
            for group in props.GetGroupNames():
                for name, value in props.GetPropertiesInGroup(group).items():
                    try:
                        v = value.get_value()
                    except RuntimeError:  # HydroelasticType has no Python binding
                        continue
                    if hasattr(v, "static_friction"):  # CoulombFriction
                        v = (v.static_friction(), v.dynamic_friction())
                    row[group, name] = v
            out.append((type(inspector.GetShape(gid)).__name__, row))
    return out


def test_drake_drop_world_objects_are_the_bin_station_objects(bin_scenario):
    """engine="drake": the drop world's objects carry exactly the bin station's contact properties
    (compliant hydroelastic with the same modulus and tessellation, the scenario's friction, the
    default Hunt-Crossley dissipation), so a heap settled there is at rest in the station; the
    drop world's plant uses the "similar" contact approximation."""
    import copy

    from ms_drake.scenes.heaps import _DropWorld

    names = ["procedural/box_003", "procedural/cylinder_001", "procedural/packaged_002"]
    world = _DropWorld(bin_scenario, names, HeapParams(engine="drake", render=False))
    assert world.plant.get_discrete_contact_approximation().name == "kSimilar"
    drop = _contact_properties(world.plant, world.scene_graph.model_inspector(), world.bodies)
    s = copy.deepcopy(bin_scenario)
    s.objects.names, s.objects.count, s.cameras = names, len(names), {}
    station = MakeStation(s)
    plant = get_plant(station)
    ref = _contact_properties(plant, station.GetSubsystemByName("scene_graph").model_inspector(),
                              [plant.get_body(o.body_index) for o in station_objects(plant)])
    assert drop == ref
    assert len(drop) == 4 and all(row["hydroelastic", "hydroelastic_modulus"] > 0 for _, row in drop)
    assert {row["material", "coulomb_friction"] for _, row in drop} == {(bin_scenario.objects.friction,) * 2}
    assert not any(("material", "hunt_crossley_dissipation") in row for _, row in drop)


def test_objects_that_leave_the_bin_are_taken_out_and_tunnelling_is_seen(bin_scenario):
    """An object beyond the bin's outer walls leaves the simulation (parked, joint locked: it
    cannot fall off the support table and keep the heap from settling); an object below the
    bin floor inside its footprint is a tunnel, and the attempt stops at once."""
    from pydrake.math import RigidTransform

    from ms_drake.scenes.heaps import _DropWorld, _take_out_leavers, _tunnelled

    size = bin_scenario.environment.resolved_size()
    wall = bin_scenario.environment.wall_thickness
    origin = np.asarray(bin_scenario.environment.position, float)
    world = _DropWorld(bin_scenario, ["procedural/box_003", "procedural/cylinder_001"],
                       HeapParams(engine="drake", render=False))
    plant, pc = world.plant, world.plant_context
    plant.SetFreeBodyPose(pc, world.bodies[0], RigidTransform(origin + [0.0, 0.0, 0.05]))
    plant.SetFreeBodyPose(pc, world.bodies[1], RigidTransform(origin + [size[0] / 2 + wall + 0.05, 0.0, 0.0]))
    assert not _take_out_leavers(world, [0, 1], origin, size, wall)
    assert world.left == [1] and world.joints[1].is_locked(pc) and not world.joints[0].is_locked(pc)
    assert plant.GetFreeBodyPose(pc, world.bodies[1]).translation()[2] < -10  # parked far away
    world.simulator.AdvanceTo(0.1)
    assert np.all(plant.GetVelocities(pc).reshape(-1, 6)[1] == 0)  # locked: stays put
    plant.SetFreeBodyPose(pc, world.bodies[0], RigidTransform(origin + [0.0, 0.0, -0.03]))
    assert _take_out_leavers(world, [0, 1], origin, size, wall)
    rows = np.array([[0.0, 0.0, 0.02], [0.0, 0.0, -0.03], [0.5, 0.0, -0.04], [0.5, 0.0, -0.1]])
    assert _tunnelled(rows, size, wall).tolist() == [False, True, False, True]


def test_settle_test_uses_speeds_averaged_over_the_check_interval():
    """Pose change over the interval, not the instantaneous velocity (which a thin object
    chattering in the discrete solver flips every step at a fixed pose); objects taken out
    of the simulation are skipped."""
    from pydrake.math import RigidTransform, RotationMatrix

    from ms_drake.scenes.heaps import _mean_speeds

    a = [RigidTransform([0.0, 0.0, 0.1]), RigidTransform(RotationMatrix.MakeZRotation(0.2), [0.1, 0.0, 0.0]),
         RigidTransform([0.3, 0.0, 0.0])]
    b = [RigidTransform([0.0, 0.0015, 0.1]), RigidTransform(RotationMatrix.MakeZRotation(0.23), [0.1, 0.0, 0.0]),
         RigidTransform([9.0, 0.0, 0.0])]
    lin, ang = _mean_speeds(a, b, 0.03, skip=[2])
    assert lin == pytest.approx(0.05) and ang == pytest.approx(1.0)
    assert _mean_speeds(a, a, 0.03, skip=[]) == (0.0, 0.0)


# ---------------------------------------------------------------------------------------------
# The Bullet drop world (ms_drake.scenes.bullet)


def _bullet_world(bin_scenario, names):
    from ms_drake.scenes.bullet import BulletDropWorld
    from ms_drake.scenes.heaps import _DropWorld

    world = _DropWorld(bin_scenario, names, HeapParams(render=False))
    return world, BulletDropWorld(world)


def test_bullet_world_mirrors_the_drake_shapes_and_inertia(bin_scenario):
    """A box and a packaged object (a shape on an off-centre cardboard backing: centre of mass
    off the body origin) dropped flat on the bin floor come to rest where Drake's geometry says:
    lowest point of the body's geometry on the floor (z = 0 of the environment), within 1 mm,
    upright, and the pose round-trips through Bullet's centre-of-mass frame exactly."""
    from pydrake.math import RigidTransform

    from ms_drake.objects import get_object

    names = ["procedural/box_003", "procedural/packaged_002"]
    world, bw = _bullet_world(bin_scenario, names)
    origin = np.asarray(bin_scenario.environment.position, float)
    X0 = RigidTransform(origin + [0.15, 0.1, 0.1])
    bw.set_pose(0, X0)
    np.testing.assert_allclose(bw.pose(0).GetAsMatrix4(), X0.GetAsMatrix4(), atol=1e-9)
    bw.set_pose(1, RigidTransform(origin + [-0.1, -0.05, 0.1]))
    assert bw.advance_to(1.0)
    for i, name in enumerate(names):
        X = bw.pose(i)
        lowest = (get_object(name).trimesh().vertices @ X.rotation().matrix().T + X.translation())[:, 2].min()
        assert abs(lowest - origin[2]) < 1e-3, (name, lowest)
        assert X.rotation().matrix()[2, 2] > 0.999  # still flat
    assert bw.max_speeds()[0] < 1e-3
    bw.take_out(0)
    assert bw.left == [0] and bw.pose(0).translation()[2] < -10
    assert bw.advance_to(1.1) and bw.velocities()[0].tolist() == [0.0] * 6
    bw.close()


def test_bullet_and_drake_engines_give_valid_heaps(bin_scenario):
    """Both engines run the same plan and tests; a bad engine name is a clear error."""
    for engine in ("bullet", "drake"):
        heap, diag = generate_heap(bin_scenario, 4, seed=5, params=HeapParams(engine=engine), return_diagnostics=True)
        assert diag.attempts == 1 and 1 <= len(heap.objects) <= 4
        assert diag.phases["waves_sim"] > 0 and heap.target in heap.object_names()
    with pytest.raises(HeapError, match="engine='ode'"):
        generate_heap(bin_scenario, 2, seed=0, params=HeapParams(engine="ode"))


def test_bullet_heap_polished_in_the_drake_drop_world(bin_scenario):
    """polish_time: after Bullet, the heap settles in the compliant Drake world (its own phase);
    the polished heap is the Bullet heap moved by at most a few cm, and it is valid."""
    plain, _ = generate_heap(bin_scenario, 4, seed=5, return_diagnostics=True)
    heap, diag = generate_heap(bin_scenario, 4, seed=5, params=HeapParams(polish_time=0.3), return_diagnostics=True)
    assert diag.attempts == 1 and 0 < diag.phases["polish_sim"] <= 0.3 + 1e-9
    assert heap.object_names() == plain.object_names()
    moved = [np.linalg.norm(a.matrix()[:3, 3] - b.matrix()[:3, 3]) for a, b in zip(heap.objects, plain.objects)]
    assert max(moved) < 0.03 and any(m > 0 for m in moved), moved
