"""Scenario files: every shipped scenario loads; bad files give one clear ScenarioError."""

import textwrap

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from pydrake.common.yaml import yaml_load_data

from ms_drake.errors import ScenarioError
from ms_drake.scenario import Scenario, load_scenario, scenario_names

REQUIRED = {"EmptyBin", "FloatingGripperBin", "YuMiBin", "PandaTable", "FetchShelf"}


def test_all_shipped_scenarios_load():
    names = set(scenario_names())
    assert REQUIRED <= names
    environments = {"BinHeap15": "bin", "EmptyBin": "bin", "FloatingGripperBin": "bin", "FloatingGripperBinPhoXi": "bin",
                    "YuMiBin": "bin", "PandaBin": "bin",
                    "FetchShelf": "shelf", "FetchShelfL515": "shelf", "FetchWideShelf": "shelf",
                    "PandaTable": "table"}
    assert names == set(environments)
    for n in names:
        s = load_scenario(None, n)
        assert isinstance(s, Scenario)
        assert s.environment.type == environments[n], n
        assert s.cameras, f"{n} has no camera"
        for cam in s.cameras.values():
            assert (cam.width, cam.height) == (640, 480)
            assert cam.renderer_name == "vtk"
    # the camera-only stations are their base station with the camera's sensor model, nothing else
    for noisy, base, camera, preset in (("FloatingGripperBinPhoXi", "FloatingGripperBin", "overhead", "phoxi"),
                                        ("FetchShelfL515", "FetchShelf", "front", "l515")):
        a, b = load_scenario(None, noisy), load_scenario(None, base)
        assert a.depth_sensors[camera].preset == preset and not b.depth_sensors
        assert (a.environment, a.robot, a.objects, list(a.cameras)) == (b.environment, b.robot, b.objects, list(b.cameras))
        assert a.plant_config.time_step == b.plant_config.time_step


def test_environment_of_each_station():
    assert load_scenario(None, "YuMiBin").environment.type == "bin"
    assert load_scenario(None, "PandaTable").environment.type == "table"
    shelf = load_scenario(None, "FetchShelf")
    assert shelf.environment.type == "shelf"
    assert list(shelf.environment.resolved_size()) == [0.6, 0.6, 0.6]


def _write(tmp_path, body: str):
    p = tmp_path / "s.yaml"
    p.write_text(textwrap.dedent(body))
    return p


def _error(tmp_path, body, name="S"):
    with pytest.raises(ScenarioError) as e:
        load_scenario(_write(tmp_path, body), name)
    return str(e.value)


def test_unknown_key_names_file_scenario_path_and_suggestion(tmp_path):
    msg = _error(tmp_path, """
        S:
          environment: { type: bin, sise: [0.5, 0.4, 0.1] }
        """)
    assert "s.yaml" in msg and "'S'" in msg
    assert "environment.sise" in msg and "did you mean 'size'" in msg


def test_wrong_type_is_reported(tmp_path):
    msg = _error(tmp_path, """
        S:
          objects: { count: many }
        """)
    assert "objects.count" in msg and "'many'" in msg and "integer" in msg


def test_bad_values_list_what_is_allowed(tmp_path):
    msg = _error(tmp_path, "S:\n  environment: { type: cupboard }\n")
    assert "environment.type" in msg and "cupboard" in msg and "bin, shelf, table" in msg
    msg = _error(tmp_path, "S:\n  objects: { set: nosuchset }\n")
    assert "objects.set" in msg and "procedural" in msg
    msg = _error(tmp_path, "S:\n  robot: { name: r2d2 }\n")
    assert "robot.name" in msg and "panda" in msg
    msg = _error(tmp_path, "S:\n  plant_config: { contact_model: jelly }\n")
    assert "plant_config.contact_model" in msg and "hydroelastic" in msg
    msg = _error(tmp_path, "S:\n  objects: { names: [procedural/nope] }\n")
    assert "objects.names[0]" in msg and "nope" in msg


def test_camera_keys_are_checked(tmp_path):
    msg = _error(tmp_path, """
        S:
          cameras:
            top: { name: top, widht: 100 }
        """)
    assert "cameras.top.widht" in msg and "width" in msg


def test_missing_file_scenario_and_bad_yaml(tmp_path):
    with pytest.raises(ScenarioError, match="no such scenario file"):
        load_scenario(tmp_path / "nope.yaml", "S")
    msg = _error(tmp_path, "T:\n  random_seed: 1\n", name="S")
    assert "no scenario named 'S'" in msg and "T" in msg
    msg = _error(tmp_path, "S: [unclosed\n")
    assert "not valid YAML" in msg


FIELDS = ["random_seed", "environment", "objects", "robot", "cameras", "plant_config",
          "scene_graph_config", "simulator_config", "visualization", "hardware", "lcm_url"]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from(FIELDS), data=st.data())
def test_typos_in_top_level_keys_are_errors(tmp_path, field, data):
    # Mutate one character of a real key: the result must be rejected (or be the real key).
    i = data.draw(st.integers(0, len(field) - 1))
    c = data.draw(st.sampled_from("abcdefghijklmnopqrstuvwxyz_"))
    typo = field[:i] + c + field[i + 1:]
    body = f"S:\n  {typo}: 1\n"
    if typo == field:
        return
    with pytest.raises(ScenarioError) as e:
        load_scenario(_write(tmp_path, body), "S")
    assert f"key '{typo}'" in str(e.value) and "unknown key" in str(e.value)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=st.one_of(st.text(max_size=5), st.booleans(), st.lists(st.integers(), max_size=2)))
def test_wrong_types_for_numbers_are_errors(tmp_path, value):
    import json

    body = f"S:\n  environment: {{ wall_thickness: {json.dumps(value)} }}\n"
    try:
        yaml_load_data(body)
        expected = "environment.wall_thickness"  # parsed, then refused for its type
    except Exception:  # noqa: BLE001 - the value broke the YAML syntax
        expected = "not valid YAML"
    with pytest.raises(ScenarioError) as e:
        load_scenario(_write(tmp_path, body), "S")
    assert expected in str(e.value)


def test_bad_gripper_is_caught_at_load_time(tmp_path):
    msg = _error(tmp_path, "S:\n  robot: { name: panda, grippers: [tentacle] }\n")
    assert "'S'" in msg and "robot" in msg and "tentacle" in msg and "parallel_jaw" in msg


def test_scenario_ref_loads_from_its_file_in_a_worker(tmp_path):
    import pickle

    from ms_drake.scenario import ScenarioRef, default_scenarios_file

    f = tmp_path / "mine.yaml"
    f.write_text(default_scenarios_file().read_text().replace("YuMiBin:", "MyYuMi:", 1))
    ref = pickle.loads(pickle.dumps(ScenarioRef("MyYuMi", str(f))))  # as a worker process receives it
    s = ref.load()
    assert s.robot.name == load_scenario(None, "YuMiBin").robot.name and str(ref) == f"MyYuMi of {f}"
    assert ScenarioRef.of("YuMiBin") == ScenarioRef("YuMiBin") and ScenarioRef.of(ref) is ref
    with pytest.raises(ScenarioError, match="MyYuMi"):
        ScenarioRef("MyYuMi").load()  # not in the shipped file
