"""MakeStation: ports, environments, objects, cameras, model packages."""

import copy

import numpy as np
import pytest
from pydrake.multibody.plant import MultibodyPlant
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from conftest import no_robot
from ms_drake.paths import make_parser, models_dir
from ms_drake.scenario import DEFAULT_SIZES, load_scenario
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.station.environments import environment_sdf


def _ports(station):
    return {station.get_output_port(i).get_name() for i in range(station.num_output_ports())}


@pytest.mark.parametrize("name,cam", [("BinHeap15", "overhead"), ("PandaTable", "front"), ("FetchShelf", "front")])
def test_station_ports_and_images(name, cam):
    s = no_robot(load_scenario(None, name))
    s.objects.count = 3
    station = MakeStation(s)
    ports = _ports(station)
    for p in (f"{cam}.rgb_image", f"{cam}.depth_image", f"{cam}.label_image", "body_poses", "query_object",
              "contact_results"):
        assert p in ports
    ctx = station.CreateDefaultContext()
    depth = np.array(station.GetOutputPort(f"{cam}.depth_image").Eval(ctx).data)[:, :, 0]
    rgb = np.array(station.GetOutputPort(f"{cam}.rgb_image").Eval(ctx).data)
    assert depth.shape == (480, 640) and rgb.shape == (480, 640, 4)
    finite = depth[np.isfinite(depth)]
    assert finite.size > 0.6 * depth.size  # the environment fills most of the view
    assert 0.1 < np.median(finite) < 3.0


def test_objects_are_named_and_labelled(bin_scenario):
    s = copy.deepcopy(bin_scenario)
    s.objects.count = 5
    station = MakeStation(s)
    plant = get_plant(station)
    objs = station_objects(plant)
    assert [o.index for o in objs] == list(range(5))
    ctx = station.CreateDefaultContext()
    labels = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[:, :, 0]
    # Objects start in a grid above the bin: every one of them is visible from above.
    for o in objs:
        assert (labels == int(o.body_index)).sum() > 50, o.full_name


def test_objects_fall_into_the_bin_and_stay(bin_scenario):
    s = copy.deepcopy(bin_scenario)
    s.objects.count = 3
    station = MakeStation(s)
    sim = Simulator(station)
    sim.AdvanceTo(1.0)
    plant = get_plant(station)
    pc = plant.GetMyContextFromRoot(sim.get_context())
    size = s.environment.resolved_size()
    for o in station_objects(plant):
        p = plant.EvalBodyPoseInWorld(pc, plant.get_body(o.body_index)).translation()
        assert np.all(np.abs(p[:2]) < size[:2] / 2) and -0.001 < p[2] < size[2], (o.full_name, p)


def test_object_sampling_is_seeded(bin_scenario):
    from ms_drake.station import resolve_object_names

    s = copy.deepcopy(bin_scenario)
    a = resolve_object_names(s)
    assert a == resolve_object_names(s) and len(a) == 15
    s.random_seed = 1
    assert resolve_object_names(s) != a


def test_models_package_resolves_and_drake_models_is_refused():
    plant = MultibodyPlant(0.0)
    parser = make_parser(plant)
    assert parser.package_map().GetPath("ms_drake_models") == str(models_dir())
    assert not parser.package_map().Contains("drake_models")
    with pytest.raises(RuntimeError):
        parser.AddModels(url="package://drake_models/iiwa_description/sdf/iiwa14_no_collision.sdf")


def test_an_object_knocked_off_the_support_lands_on_the_room_floor(bin_scenario):
    # Without the room floor a body falling for tens of seconds spins up until the step diverges.
    s = copy.deepcopy(bin_scenario)
    s.objects.count = 1
    station = MakeStation(s)
    sim = Simulator(station)
    plant = get_plant(station)
    pc = plant.GetMyMutableContextFromRoot(sim.get_mutable_context())
    body = plant.get_body(station_objects(plant)[0].body_index)
    plant.SetFreeBodyPose(pc, body, RigidTransform([1.0, 0.0, 0.2]))  # beyond the support's edge (0.8 m)
    sim.AdvanceTo(2.0)
    p = plant.EvalBodyPoseInWorld(pc, body).translation()
    floor = -s.environment.wall_thickness - 0.7
    assert np.all(np.isfinite(plant.GetPositionsAndVelocities(pc)))
    assert floor - 0.005 < p[2] < floor + 0.2 and abs(p[0] - 1.0) < 0.3, p


def test_default_environment_files_match_generator():
    for t in ("bin", "shelf", "table"):
        wall = 0.02 if t == "shelf" else 0.03
        text = (models_dir() / "environments" / f"{t}.sdf").read_text()
        assert text == environment_sdf(t, DEFAULT_SIZES[t], wall, model_name=t)
        plant = MultibodyPlant(0.0)
        make_parser(plant).AddModels(url=f"package://ms_drake_models/environments/{t}.sdf")


def test_shelf_is_open_at_the_front():
    s = no_robot(load_scenario(None, "FetchShelf"))
    s.objects.count = 0
    station = MakeStation(s)
    ctx = station.CreateDefaultContext()
    depth = np.array(station.GetOutputPort("front.depth_image").Eval(ctx).data)[:, :, 0]
    # The centre pixel sees the back wall: 0.95 m to the shelf centre + 0.3 m depth.
    d = depth[240, 320]
    assert 1.1 < d < 1.35


def test_mesh_objects_rest_on_the_bin_floor(bin_scenario):
    """Rigid mesh objects get support spheres from the converter, so point contact holds them."""
    from ms_drake.objects import get_object, get_object_set

    for set_name in ("ycb", "random_urdfs"):
        s = copy.deepcopy(bin_scenario)
        s.objects.count = 0
        s.objects.names = [o.full_name for o in get_object_set(set_name).objects[:6]]
        station = MakeStation(s)
        sim = Simulator(station)
        sim.AdvanceTo(1.0)
        plant = get_plant(station)
        pc = plant.GetMyContextFromRoot(sim.get_context())
        for o in station_objects(plant):
            X = plant.EvalBodyPoseInWorld(pc, plant.get_body(o.body_index))
            v = np.asarray(get_object(o.full_name).trimesh().vertices) @ X.rotation().matrix().T + X.translation()
            assert v[:, 2].min() > -0.004, (o.full_name, v[:, 2].min())
