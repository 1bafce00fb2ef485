"""Depth sensor models (ms_drake.station.sensor_model), their scenario key and the one depth
preprocessing (geometry.preprocess_depth)."""

import copy
import dataclasses
import textwrap

import numpy as np
import pytest
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

from conftest import no_robot
from ms_drake.errors import ScenarioError
from ms_drake.geometry import depth_holes, preprocess_depth
from ms_drake.scenario import DEPTH_SENSOR_PRESETS, DepthSensorConfig, load_scenario
from ms_drake.station import MakeStation
from ms_drake.station.sensor_model import (
    PRESETS,
    DepthSensorModel,
    DepthSensorParams,
    apply_depth_sensor,
    depth_sensor_params,
    image_rng,
)

W, H, F = 640, 480, 685.0
INTRINSICS = (W, H, F, F, (W - 1) / 2, (H - 1) / 2)
NOISY = ("phoxi", "l515", "primesense")


def _plane(z: float) -> np.ndarray:
    return np.full((H, W), z, np.float32)


def _step() -> np.ndarray:
    """A floor at 0.8 m with a 10 cm box (top at 0.7 m) in the middle."""
    d = _plane(0.8)
    d[180:300, 240:400] = 0.7
    return d


def _image(d: np.ndarray) -> ImageDepth32F:
    img = ImageDepth32F(W, H)
    img.mutable_data[:, :, 0] = d
    return img


def _apply(preset, d, seed=0, t=0.0, rgb=None, name="overhead"):
    p = PRESETS[preset] if isinstance(preset, str) else preset
    return apply_depth_sensor(d, p, image_rng(seed, name, t), *INTRINSICS[2:], rgb=rgb)


def _eval(system, depth, rgb=None, t=0.0):
    ctx = system.CreateDefaultContext()
    ctx.SetTime(t)
    system.GetInputPort("depth_image").FixValue(ctx, _image(depth))
    if rgb is not None:
        img = ImageRgba8U(W, H)
        img.mutable_data[:] = rgb
        system.GetInputPort("rgb_image").FixValue(ctx, img)
    return np.array(system.GetOutputPort("depth_image").Eval(ctx).data)[:, :, 0]


# --- the LeafSystem alone ---------------------------------------------------------------------


def test_system_alone_fixed_inputs():
    system = DepthSensorModel("phoxi", INTRINSICS, seed=3, camera_name="overhead")
    clean = _step()
    out = _eval(system, clean)
    assert out.shape == (H, W) and out.dtype == np.float32
    lost = out == 0
    assert 0 < lost.mean() < 0.05  # PhoXi: few holes
    ok = ~lost
    assert np.abs(out[ok] - clean[ok]).max() < 0.003  # sub-millimetre noise (5 sigma < 1.5 mm)
    assert np.abs(out[ok] - clean[ok]).std() > 1e-5
    # the output is cached per time: the same context time gives the same image, another time another
    assert np.array_equal(_eval(system, clean), out)
    assert not np.array_equal(_eval(system, clean, t=0.1), out)


def test_none_is_identity():
    clean = _step()
    clean[0, :10] = np.inf  # beyond the clipping range
    clean[1, :10] = 0.0  # too close
    out = _eval(DepthSensorModel("none", INTRINSICS), clean)
    assert np.array_equal(out, clean)
    assert np.array_equal(_apply("none", clean), clean)
    assert PRESETS["none"].is_identity() and not any(PRESETS[p].is_identity() for p in NOISY)


def test_dark_surfaces_use_the_rgb_input():
    p = dataclasses.replace(PRESETS["l515"], holes=0.0, pixel_dropout=0.0)
    system = DepthSensorModel(p, INTRINSICS, seed=1)
    rgb = np.full((H, W, 4), 200, np.uint8)
    rgb[:, :W // 2, :3] = 5  # the left half is black
    out = _eval(system, _plane(0.8), rgb=rgb)
    left, right = (out[:, :W // 2] == 0).mean(), (out[:, W // 2:] == 0).mean()
    assert abs(left - p.dark_dropout) < 0.02 and right < 0.01
    assert (_eval(system, _plane(0.8)) == 0).mean() < 0.01  # rgb not connected: no dark dropout


# --- each preset does what it says ------------------------------------------------------------


@pytest.mark.parametrize("preset", NOISY)
def test_noise_grows_with_depth(preset):
    p = dataclasses.replace(PRESETS[preset], depth_unit=0.0, disparity_step=0.0)  # the noise alone
    stds = []
    for z in (0.5, 1.2):
        out = _apply(p, _plane(z), seed=7)
        ok = out > 0
        stds.append(float(np.std(out[ok] - z)))
        assert stds[-1] == pytest.approx(p.noise_a + p.noise_b * z * z, rel=0.05)
    assert stds[1] > 1.5 * stds[0]
    # with its quantisation the spread still grows with depth
    q = [float(np.std(_apply(preset, _plane(z), seed=7)[_apply(preset, _plane(z), seed=7) > 0])) for z in (0.5, 1.2)]
    assert q[1] > q[0]


@pytest.mark.parametrize("preset", NOISY)
def test_holes_concentrate_at_depth_edges(preset):
    p = dataclasses.replace(PRESETS[preset], holes=0.0)
    clean = _step()
    out = _apply(p, clean, seed=2)
    band = np.zeros((H, W), bool)  # the floor within edge_width px of the box (far side of the edge)
    w = p.edge_width
    band[180 - w:300 + w, 240 - w:400 + w] = True
    band[180:300, 240:400] = False
    elsewhere = np.ones((H, W), bool)
    elsewhere[150:330, 210:430] = False
    rate_band, rate_else = (out[band] == 0).mean(), (out[elsewhere] == 0).mean()
    assert rate_band > 0.5 * p.edge_dropout
    assert rate_band > 10 * rate_else


def test_grazing_surfaces_lose_returns():
    p = dataclasses.replace(PRESETS["l515"], holes=0.0, pixel_dropout=0.0, edge_dropout=0.0)
    assert (_apply(p, _plane(0.8)) == 0).mean() < 0.01  # a plane facing the camera
    # a plane tilted by 80 degrees about the camera's x axis: z = z0 / (1 - tan(80 deg) y / f)
    y = (np.arange(H, dtype=np.float32)[:, None] - INTRINSICS[5]) / F
    den = 1.0 - np.tan(np.radians(80.0)) * y
    steep = np.broadcast_to(np.where(den > 0.2, 0.8 / np.maximum(den, 0.2), np.inf), (H, W)).astype(np.float32)
    out = _apply(p, steep)
    # incidence 77-81 degrees, neighbouring pixels < 1 cm apart (farther down the plane's rows are
    # depth steps: the edge term's, switched off here)
    rows = slice(int(INTRINSICS[5]) - 30, int(INTRINSICS[5]) + 10)
    assert (out[rows] == 0).mean() > 0.4


def test_quantisation_step_is_visible():
    out = _apply("l515", _plane(0.8))
    ok = out[out > 0].astype(np.float64)
    assert np.allclose(ok / 0.00025, np.round(ok / 0.00025), atol=1e-2)  # whole depth units of 0.25 mm
    p = PRESETS["primesense"]
    levels = np.unique(_apply("primesense", _plane(0.8))[_apply("primesense", _plane(0.8)) > 0])
    near = levels[np.abs(levels - 0.8) < 0.01]
    step = np.median(np.diff(near))
    expected = 0.8 ** 2 * p.disparity_step / p.focal_baseline  # dz = z^2 * step / (f b): 1.84 mm
    assert step == pytest.approx(expected, rel=0.05)
    assert 0.0015 < expected < 0.0021  # Smisek et al.: 2.73 z^2 + 0.74 z - 0.58 mm = 1.76 mm at 0.8 m


@pytest.mark.parametrize("preset", NOISY)
def test_reproducible_from_the_seed(preset):
    clean = _step()
    a = _apply(preset, clean, seed=11)
    assert np.array_equal(a, _apply(preset, clean, seed=11))
    assert not np.array_equal(a, _apply(preset, clean, seed=12))
    assert not np.array_equal(a, _apply(preset, clean, seed=11, name="front"))
    assert not np.array_equal(a, _apply(preset, clean, seed=11, t=0.5))


# --- the scenario key and the wired station ---------------------------------------------------


def _station_depth(scenario):
    station = MakeStation(scenario)
    ctx = station.CreateDefaultContext()
    depth = np.array(station.GetOutputPort("overhead.depth_image").Eval(ctx).data)[:, :, 0]
    labels = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[:, :, 0]
    return station, depth, labels


def test_station_applies_the_scenario_sensor_model(bin_scenario):
    s = no_robot(bin_scenario)
    s.objects.count = 3
    station, clean, clean_labels = _station_depth(s)
    assert not any(station.GetSystems()[i].get_name().startswith("depth_sensor_")
                   for i in range(len(station.GetSystems())))  # `none`: no system at all
    noisy = copy.deepcopy(s)
    noisy.depth_sensors = {"overhead": DepthSensorConfig(preset="primesense")}
    station2, depth, labels = _station_depth(noisy)
    assert station2.HasSubsystemNamed("depth_sensor_overhead")
    assert depth.dtype == np.float32 and depth.shape == clean.shape
    assert 0.01 < (depth == 0).mean() < 0.5
    ok = depth > 0
    assert 0.0005 < np.std(depth[ok] - clean[ok]) < 0.005
    assert np.array_equal(labels, clean_labels)  # labels come from the perfect depth
    assert np.array_equal(_station_depth(noisy)[1], depth)  # one scenario, one image
    other = copy.deepcopy(noisy)
    other.random_seed += 1
    assert not np.array_equal(_station_depth(other)[1], depth)


def _write(tmp_path, body: str):
    p = tmp_path / "s.yaml"
    p.write_text(textwrap.dedent(body))
    return p


CAMERA = """
S:
  cameras:
    overhead: { name: overhead, width: 640, height: 480, depth: true }
"""


def test_scenario_file_sets_presets_and_overrides(tmp_path):
    f = _write(tmp_path, CAMERA + "  depth_sensors:\n    overhead: { preset: l515, noise_b: 0.002, edge_width: 3 }\n")
    s = load_scenario(f, "S")
    p = depth_sensor_params(s.depth_sensors["overhead"])
    assert p == dataclasses.replace(PRESETS["l515"], noise_b=0.002, edge_width=3)
    assert depth_sensor_params("phoxi") == PRESETS["phoxi"]


@pytest.mark.parametrize("entry, key, words", [
    ("overhead: { preset: kinect }", "depth_sensors.overhead.preset", ["'kinect'", "none, phoxi, l515, primesense"]),
    ("front: { preset: l515 }", "depth_sensors.front", ["'front'", "overhead"]),
    ("overhead: { preset: l515, edge_dropout: 1.5 }", "depth_sensors.overhead.edge_dropout", ["1.5", "between 0 and 1"]),
    ("overhead: { preset: l515, noise_a: -0.001 }", "depth_sensors.overhead.noise_a", ["-0.001", ">= 0"]),
    ("overhead: { preset: l515, grazing_deg: 120 }", "depth_sensors.overhead.grazing_deg", ["120", "0 and 90"]),
    ("overhead: { preset: l515, noize_a: 0.001 }", "depth_sensors.overhead.noize_a",
     ["did you mean 'noise_a'", "allowed keys of DepthSensorConfig"]),
    ("overhead: { preset: l515, noise_a: lots }", "depth_sensors.overhead.noise_a", ["'lots'", "a number"]),
])
def test_scenario_errors(tmp_path, entry, key, words):
    f = _write(tmp_path, CAMERA + f"  depth_sensors:\n    {entry}\n")
    with pytest.raises(ScenarioError) as e:
        load_scenario(f, "S")
    msg = str(e.value)
    assert str(f) in msg and "scenario 'S'" in msg and f"key '{key}'" in msg, msg
    for w in words:
        assert w in msg, msg


def test_camera_without_depth_is_an_error(tmp_path):
    f = _write(tmp_path, CAMERA.replace("depth: true", "depth: false")
               + "  depth_sensors:\n    overhead: { preset: phoxi }\n")
    with pytest.raises(ScenarioError, match="renders no depth image"):
        load_scenario(f, "S")


def test_presets_match_the_scenario_schema():
    assert tuple(PRESETS) == DEPTH_SENSOR_PRESETS
    overrides = {f.name for f in dataclasses.fields(DepthSensorConfig)} - {"preset"}
    assert overrides == {f.name for f in dataclasses.fields(DepthSensorParams)}


# --- the one preprocessing --------------------------------------------------------------------


def test_preprocess_leaves_clean_images_unchanged(bin_scenario):
    s = no_robot(bin_scenario)
    s.objects.count = 3
    _, clean, _ = _station_depth(s)
    assert not depth_holes(clean).any()
    assert np.array_equal(preprocess_depth(clean), clean)
    assert np.array_equal(preprocess_depth(_image(clean)), clean)  # an ImageDepth32F too
    far = clean.copy()
    far[:5] = np.inf  # nothing within range is not a hole
    assert np.array_equal(preprocess_depth(far), far)


def test_preprocess_fills_holes():
    clean = _step()
    noisy = _apply(dataclasses.replace(PRESETS["primesense"], noise_a=0.0, noise_b=0.0, disparity_step=0.0),
                   clean, seed=5)
    noisy[0, :20] = np.nan
    holes = depth_holes(noisy)
    assert holes.mean() > 0.01
    filled = preprocess_depth(noisy)
    assert not depth_holes(filled).any()
    assert np.array_equal(filled[~holes], noisy[~holes])  # valid pixels are kept
    err = np.abs(filled - clean)[holes]
    assert np.median(err) < 1e-4 and err.max() <= 0.1 + 1e-6  # inside the scene's depth range


def test_occupancy_samples_see_the_sensor_on_the_same_images(bin_scenario, small_heap):
    from ms_drake.experiments.occupancy_data import make_samples

    def samples(sensor):
        return make_samples(bin_scenario, small_heap, 1, np.random.default_rng(4), sensor=sensor)[0]

    clean, noisy = samples("none"), samples("primesense")
    assert np.array_equal(clean["y"], noisy["y"]) and clean["ratio"] == noisy["ratio"]  # same image, same truth
    assert not np.array_equal(clean["x"][1], noisy["x"][1])  # the network's depth input differs
    assert np.array_equal(clean["x"][0], noisy["x"][0])  # the target's modal mask does not
    assert np.array_equal(samples("primesense")["x"], noisy["x"])
