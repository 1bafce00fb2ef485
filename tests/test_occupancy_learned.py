"""The learned occupancy (Ch. 8.3): the dataset writer on a tiny count, a training step, the
shipped weights against a uniform baseline, OccupancyEstimator("learned") alone and wired into
the bin-search controller."""

import numpy as np
import pytest
import trimesh
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.errors import DatasetError, PerceptionError
from ms_drake.experiments.occupancy_data import (
    PILE_SPREAD,
    LyingCylinder,
    insert_target,
    layout_heap_params,
    load_dataset,
    sample_target_in_pile,
    shard_split,
    target_shape,
    write_occupancy_dataset,
)
from ms_drake.experiments.occupancy_learning import (
    batch_constraint,
    diagonals,
    make_optimizer,
    occupancy_metrics,
    predict,
    target_scales,
    to_training_scale,
    train_occupancy,
    train_steps,
)
from ms_drake.experiments.rollout import build_search
from ms_drake.policies.bin_search import IMAGE_BEST_MATCH, BinSearchAblation, ControllerError, load_bin_search_config
from ms_drake.scenes.layouts import HEAP_LAYOUTS as SEARCH_LAYOUTS
from ms_drake.scenes.layouts import LID_TARGET as XRAY_TARGET
from ms_drake.scenes.layouts import HeapConfig, layout_heap
from ms_drake.geometry import PinholeCamera, Workspace
from ms_drake.objects import get_object
from ms_drake.perception.occupancy import AnalyticOccupancy, OccupancyEstimator, TargetBox
from ms_drake.perception.occupancy_net import (
    FULL_SHAPE,
    WORK_PX_PER_M,
    WORK_SHAPE,
    LearnedOccupancy,
    constrain_to_visible,
    default_weights,
    estimator_output,
    load_model,
    make_net,
    nearest_ratio,
    visible_support,
)
from ms_drake.policies import select_action
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapParams, set_heap_poses
from ms_drake.station.robots import set_arm_positions
from ms_drake.types import Grasp, InstanceMasks, OccupancyMap, TargetEstimate

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Five shards of one heap and two views each: shards 0-3 train, shard 4 test."""
    out = tmp_path_factory.mktemp("occ")
    res = write_occupancy_dataset(out, count=10, seed=3, views=2, heaps_per_shard=1, sets=("procedural", "ycb"))
    assert res == dict(shards=5, skipped=0, written=5, failed=[])
    return out


def test_dataset_writer_splits_by_object_and_reloads(tiny):
    assert [shard_split(k) for k in range(5)] == ["train"] * 4 + ["test"]
    train, test = load_dataset(tiny, "train"), load_dataset(tiny, "test")
    assert train["x"].shape == (8, 3, *WORK_SHAPE) and test["y"].shape == (2, *WORK_SHAPE)
    for d, split in ((train, "train"), (test, "test")):
        names = {n for s in d["objects"] for n in str(s).split(",")}
        assert names and all(get_object(n).split == split for n in names), split
        y = d["y"].astype(np.float32)
        assert np.all(y >= 0) and np.allclose(y.max(axis=(1, 2)), 1.0, atol=1e-3)  # max-normalized, never empty
        assert np.all(d["ratio"] >= 0) and np.all(d["ratio"] < 10)
    # resuming keeps every shard
    res = write_occupancy_dataset(tiny, count=10, seed=3, views=2, heaps_per_shard=1, sets=("procedural", "ycb"))
    assert res["skipped"] == 5 and res["written"] == 0


def test_compact_layout_drops_as_xray_compact_and_keeps_a_folder_to_one_layout(tmp_path):
    c = layout_heap_params("compact", "train")
    assert (c.center_uniform, c.offset_uniform, c.drop_height, c.split) == (
        *(getattr(SEARCH_LAYOUTS["compact"].params, k) for k in ("center_uniform", "offset_uniform", "drop_height")),
        "train")
    assert layout_heap_params("spread", "test") == HeapParams(engine="bullet", split="test", render=False)
    out = tmp_path / "c"
    assert write_occupancy_dataset(out, count=2, seed=3, views=2, heaps_per_shard=1, sets=("procedural",),
                                   layout="compact")["written"] == 1
    assert [str(np.load(f)["layout"]) for f in out.glob("shard_*.npz")] == ["compact"]
    with pytest.raises(DatasetError, match="holds 'compact' heaps .* and --layout is 'spread'"):
        write_occupancy_dataset(out, count=4, seed=3, views=2, heaps_per_shard=1, sets=("procedural",))
    with pytest.raises(DatasetError, match="holds shards with best_match None .* asked for 0.05"):
        write_occupancy_dataset(out, count=4, seed=3, views=2, heaps_per_shard=1, sets=("procedural",),
                                layout="compact", best_match=0.05)
    with pytest.raises(DatasetError, match="unknown heap layout 'pile'; choose one of spread, compact"):
        write_occupancy_dataset(tmp_path / "p", count=2, layout="pile")


def test_posterior_ground_truth_is_the_targets_own_amodal_mask_placed_in_the_pile(tmp_path):
    """`--ground-truth posterior`: each label is the target's amodal mask (max 1, covering every seen
    target pixel, the box's area), the target within PILE_SPREAD of the objects' mean position; a
    folder keeps one ground truth; best_match belongs to the generator."""
    out = tmp_path / "post"
    write_occupancy_dataset(out, count=8, seed=4, views=4, heaps_per_shard=1, sets=("procedural",),
                            layout="compact", targets=[(0.045, 0.045, 0.005)], ground_truth="posterior")
    d = load_dataset(out, "train")
    assert [str(np.load(f)["ground_truth"]) for f in sorted(out.glob("shard_*.npz"))] == ["posterior"] * 2
    y, seen = d["y"].astype(np.float32), d["x"][:, 0].astype(np.float32) > 0
    assert np.allclose(y.max(axis=(1, 2)), 1.0, atol=1e-3)
    assert not (seen & (y == 0)).any()  # the seen target lies inside its own amodal mask
    side_px = 0.045 * WORK_PX_PER_M  # the 4.5 cm box in working pixels of the nominal camera
    area = y.sum(axis=(1, 2))
    assert np.all((area > 0.7 * side_px ** 2) & (area < 1.4 * side_px ** 2))
    ws = Workspace.from_scenario(load_scenario(None, "BinHeap15"))
    rng = np.random.default_rng(0)

    class _Op:
        def __init__(self, x, y):
            self.q = np.array([1, 0, 0, 0, x, y, 0.0])

    class _Heap:
        objects = [_Op(0.02, 0.01), _Op(0.06, -0.03)]
    xy = np.array([sample_target_in_pile(_Heap(), ws, TargetBox.of((0.045, 0.045, 0.005)), rng)[0]
                   for _ in range(200)])
    assert np.all(np.abs(xy - [0.04, -0.01]) <= PILE_SPREAD + 1e-9)
    with pytest.raises(DatasetError, match="holds shards with the 'posterior' ground truth .* is 'generator'"):
        write_occupancy_dataset(out, count=16, seed=4, views=4, heaps_per_shard=1, sets=("procedural",),
                                layout="compact", targets=[(0.045, 0.045, 0.005)])
    with pytest.raises(DatasetError, match="best_match is a setting of the generator's ground truth"):
        write_occupancy_dataset(tmp_path / "b", count=2, ground_truth="posterior", best_match=0.05)
    with pytest.raises(DatasetError, match="unknown ground truth 'exact'; choose one of generator, posterior"):
        write_occupancy_dataset(tmp_path / "e", count=2, ground_truth="exact")


def test_a_training_step_lowers_the_loss_on_a_fixed_batch(tiny):
    torch.manual_seed(0)
    d = load_dataset(tiny, "train")
    net = make_net()
    opt = make_optimizer(net, lr=3e-3)
    x, y = d["x"][:4].astype(np.float32), d["y"][:4].astype(np.float32)
    losses = train_steps(net, opt, x, y, d["ratio"][:4], 8)
    assert losses[-1] < 0.95 * losses[0]
    # the same under the seen-target constraint and with positives weighted (the shipped settings)
    torch.manual_seed(0)
    net = make_net()
    opt = make_optimizer(net, lr=3e-3)
    losses = train_steps(net, opt, x, y, d["ratio"][:4], 8, diag=diagonals(d["size"][:4]), positive_weight=1.0)
    assert losses[-1] < 0.95 * losses[0]


@pytest.mark.parametrize("name", ["occupancy.pt", "occupancy_compact.pt", "occupancy_bestmatch.pt", "occupancy_1x1.pt",
                                  "occupancy_posterior.pt"])
def test_shipped_weights_load_and_beat_a_uniform_distribution(tiny, name):
    path = default_weights().with_name(name)
    assert path.with_suffix(".md").is_file(), f"{path}: its model card is missing"
    net, ck = load_model(path)
    assert path.stat().st_size < 20e6 and ck["meta"]["epochs_done"] >= 1
    d = load_dataset(tiny, "test")
    y = d["y"].astype(np.float32)
    pred = predict(net, d["x"], d["ratio"])
    uniform = np.zeros_like(y)
    uniform[:, 6:-6, 10:-10] = 1.0
    m, u = occupancy_metrics(pred, y), occupancy_metrics(uniform, y)
    assert m["mse"].mean() < u["mse"].mean()
    assert m["balanced_accuracy"].mean() > u["balanced_accuracy"].mean()
    est = predict(net, d["x"], d["ratio"], diag=diagonals(d["size"]))  # what the estimator returns
    e = occupancy_metrics(est, y)
    assert np.allclose(est.max(axis=(1, 2)), 1.0)
    assert e["balanced_accuracy"].mean() > u["balanced_accuracy"].mean() and e["iou"].mean() > u["iou"].mean()


def test_seen_target_constraint():
    seen = np.zeros(WORK_SHAPE, np.float32)
    seen[40:44, 60:64] = 1.0  # a 4 x 4 block patch fully seen
    seen[44, 60:64] = 0.5  # and a half-seen row
    diag = 0.03 * np.sqrt(2)  # the 3 x 3 cm box
    sup = visible_support(seen, diag)
    r = diag * WORK_PX_PER_M * 1.15 + 1.0
    rows, cols = np.nonzero(sup)
    # every supported pixel lies within r of every seen pixel (the corners of the patch suffice)
    for pr, pc in ((40, 60), (40, 63), (44, 60), (44, 63)):
        assert np.all((rows - pr) ** 2 + (cols - pc) ** 2 <= r * r + 1e-6)
    assert sup[42, 62] and sup[42, 62 + int(r) - 3] and not sup[42, 62 + int(r) + 3]
    pred = np.full(WORK_SHAPE, 0.3, np.float32)
    c = constrain_to_visible(pred, seen, diag)
    assert np.all(c[~sup] == 0) and np.all(c[40:44, 60:64] == 1.0) and c[44, 61] == pytest.approx(0.5)
    assert c[42, 62 + int(r) - 3] == pytest.approx(0.3)
    out = estimator_output(pred * 0.5, seen, diag)
    assert out.max() == pytest.approx(1.0) and np.all(out[~sup] == 0)
    nothing = np.zeros(WORK_SHAPE, np.float32)
    assert visible_support(nothing, diag) is None and constrain_to_visible(pred, nothing, diag) is pred
    sup_b, floor_b = batch_constraint(np.stack([np.stack([seen, pred, pred]), np.stack([nothing, pred, pred])]),
                                      np.array([diag, diag]))
    assert np.array_equal(sup_b[0] > 0, sup) and np.all(sup_b[1] == 1) and np.all(floor_b[1] == 0)


def test_xray_grasps_a_seen_graspable_target_before_the_best_scored_occluder():
    h, w = 60, 80
    m = np.zeros((2, h, w), bool)
    m[0, 5:10, 5:10] = True  # the target, seen
    m[1, 20:50, 0:40] = True  # an occluder
    masks = InstanceMasks(m, ("t", "big"), np.ones(2))
    rho = np.zeros((h, w))
    rho[20:50, 0:40] = 1.0  # all of the occupancy on the occluder
    occ = OccupancyMap(rho / rho.sum())
    seen = TargetEstimate(True, m[0], 0.95, 0)
    g = tuple(Grasp("suction", (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), quality=q, object_id=k)
              for k, q in (("t", 0.5), ("big", 0.9)))
    assert select_action("xray", masks, seen, g, occupancy=occ).grasp.object_id == "t"
    # not graspable: the occluder with the most occupancy
    g_low = (Grasp("suction", (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), quality=0.05, object_id="t"), g[1])
    assert select_action("xray", masks, seen, g_low, occupancy=occ).grasp.object_id == "big"
    # the target not seen: by occupancy
    hidden = TargetEstimate(False, np.zeros((h, w), bool))
    assert select_action("xray", masks, hidden, g, occupancy=occ).grasp.object_id == "big"


def test_missing_weights_name_the_command(tmp_path):
    with pytest.raises(PerceptionError, match="ms-drake train occupancy"):
        LearnedOccupancy((0.03, 0.03, 0.005), weights=tmp_path / "none.pt")


def test_nearest_ratio_and_scale():
    assert nearest_ratio(0.06, 0.06) == (0, pytest.approx(2.0))
    assert nearest_ratio(0.0949, 0.00949)[0] == 9


def test_larger_targets_are_zoomed_to_their_training_box_as_the_estimator_zooms():
    """A 4.5 cm 1:1 target (s = 1.5) is trained at the 3 cm box's size: its seen square and its
    ground truth shrink by 1 / 1.5 about the image centre; a training-box sample is left alone."""
    x = np.zeros((2, 3, *WORK_SHAPE), np.float16)
    x[:, 0, 33:63, 49:79] = 1.0  # a 30 x 30 working-pixel square about the centre (48, 64)
    y = x[:, 0].copy()
    size = np.array([[0.045, 0.045, 0.005], [0.03, 0.03, 0.005]])
    d = dict(x=x, y=y, size=size)
    np.testing.assert_allclose(target_scales(size), [1.5, 1.0])
    assert to_training_scale(d) == 1
    assert d["x"].dtype == np.float16 and d["y"].dtype == np.float16
    side = np.sqrt((d["x"][0, 0].astype(np.float32) > 0.5).sum())
    assert side == pytest.approx(20.0, abs=1.5)
    assert float(d["y"][0].max()) == pytest.approx(1.0, abs=1e-3)
    np.testing.assert_array_equal(d["x"][1], x[1])
    np.testing.assert_allclose(d["size"][0], [0.03, 0.03, 0.005])
    np.testing.assert_allclose(target_scales(d["size"]), [1.0, 1.0])
    assert to_training_scale(d) == 0


def test_training_on_a_larger_target_zooms_it_and_resumes(tmp_path):
    """`ms-drake data occupancy --target` (the 4.5 cm square) then `train occupancy`: every sample
    is zoomed to the 3 cm box, the run writes weights that load, and the same call again resumes
    from its checkpoint without another epoch."""
    data = tmp_path / "data"
    write_occupancy_dataset(data, count=4, seed=5, views=2, heaps_per_shard=1, sets=("procedural",),
                            targets=[(0.045, 0.045, 0.005)])
    d = load_dataset(data, "train")
    np.testing.assert_allclose(target_scales(d["size"]), 1.5)
    out = tmp_path / "w.pt"
    meta = train_occupancy(data, out, epochs=1, batch=2, seed=0)
    assert meta["rescaled_images"] == meta["train_images"] == len(d["x"])
    assert meta["epochs_done"] == 1 and out.is_file() and out.with_suffix(".ckpt").is_file()
    net, ck = load_model(out)
    assert ck["meta"]["rescaled_images"] == len(d["x"])
    again = train_occupancy(data, out, epochs=1, batch=2, seed=0)
    assert again["epochs_done"] == 1 and again["history"] == meta["history"]


def test_learned_estimator_alone():
    est = OccupancyEstimator("learned", target_size=TargetBox.from_object(XRAY_TARGET))
    ctx = est.CreateDefaultContext()
    h, w = FULL_SHAPE
    depth = ImageDepth32F(w, h)
    depth.mutable_data[:] = 0.8
    depth.mutable_data[200:260, 300:380] = 0.7  # an object on the floor
    est.GetInputPort("depth_image").FixValue(ctx, depth)
    est.GetInputPort("target").FixValue(ctx, TargetEstimate(False, np.zeros((h, w), bool)))
    occ = est.GetOutputPort("occupancy").Eval(ctx)
    rho = occ.distribution
    assert isinstance(occ, OccupancyMap) and rho.shape == (h, w)
    assert np.all(rho >= 0) and rho.sum() == pytest.approx(1.0)
    assert not rho[:40].any() and not rho[:, :60].any()  # outside the working crop: 0


def test_learned_estimator_in_the_xray_controller_without_privileged_state():
    heap = layout_heap(HeapConfig("lid", 4), 5002)  # the target seen and graspable (collision-free) at the start
    assert heap.target == XRAY_TARGET and heap.target_index == 0
    system = build_search(load_scenario(None, "FloatingGripperBin"), heap,
                          load_bin_search_config("ch7", policy="xray", horizon=2))
    est = system.controller.GetSubsystemByName("occupancy_estimator")
    assert isinstance(est.backend, LearnedOccupancy)  # from the target's size: no pose anywhere
    assert [est.get_input_port(i).get_name() for i in range(est.num_input_ports())] == ["depth_image", "target"]
    ctx = system.diagram.CreateDefaultContext()
    set_heap_poses(system.station, ctx, heap)
    set_arm_positions(system.plant, system.plant.GetMyMutableContextFromRoot(ctx), "floating",
                      system.controller.initial_commands())
    rho = system.output(ctx, "occupancy").distribution
    assert rho.shape == FULL_SHAPE and rho.sum() == pytest.approx(1.0)
    # the grasp planner scores closed meshes (an open visual mesh scores every grasp 0)
    geo = system.controller.GetSubsystemByName("object_geometry")
    objs = geo.get_output_port(0).Eval(geo.GetMyContextFromRoot(ctx))
    assert len(objs) == len(heap.objects) and all(trimesh.Trimesh(o.vertices, o.faces).is_watertight for o in objs)
    a = system.output(ctx, "action")
    assert system.output(ctx, "target").visible
    assert a.kind == "grasp" and a.grasp.object_id == system.target_id  # X-Ray takes the seen target first


def test_analytic_image_occupancy_is_the_generator_on_the_targets_box_without_its_pose():
    heap = layout_heap(HeapConfig("lid", 4), 5002)
    scenario = load_scenario(None, "FloatingGripperBin")
    est = {occ: build_search(scenario, heap, load_bin_search_config("ch7", [f"ablation.occupancy={occ}"], policy="xray",
                                                                    horizon=2))
           .controller.GetSubsystemByName("occupancy_estimator").backend
           for occ in ("analytic_image", "analytic_image_best", "analytic")}
    box = TargetBox.from_object(heap.target)
    for occ, best_match in (("analytic_image", None), ("analytic_image_best", IMAGE_BEST_MATCH)):
        assert isinstance(est[occ], AnalyticOccupancy) and est[occ].mesh is None
        assert est[occ].box == box and est[occ].best_match == best_match
    assert est["analytic"].mesh is not None  # the privileged one: the target's mesh at its true pose
    with pytest.raises(ControllerError, match="occupancy 'exact' unknown; choose one of learned, analytic_image"):
        BinSearchAblation(occupancy="exact")


def test_flute_target_is_a_lying_cylinder_seen_from_above():
    scenario = load_scenario(None, "BinHeap15")
    cam = PinholeCamera.from_config(scenario.cameras[next(iter(scenario.cameras))])
    ws = Workspace.from_scenario(scenario)
    shape = target_shape(("cylinder", 0.15, 0.015))
    assert isinstance(shape, LyingCylinder) and (shape.length, shape.width, shape.thickness) == (0.15, 0.015, 0.015)
    assert isinstance(target_shape((0.03, 0.06, 0.005)), TargetBox)
    v, _ = shape.mesh_vertices_faces()
    assert np.ptp(v, axis=0) == pytest.approx([0.15, 0.015, 0.015], abs=1e-4)  # its axis along x
    floor = np.full((cam.height, cam.width), cam.X_WC.translation()[2] - ws.floor_z, np.float32)  # the empty floor
    depth, modal = insert_target(floor, cam, ws, shape, ws.center_xy, 0.0)
    z_top = cam.X_WC.translation()[2] - ws.floor_z - shape.thickness
    expected = shape.length * shape.width * (cam.fx / z_top) ** 2  # its footprint seen from the top
    assert modal.sum() == pytest.approx(expected, rel=0.15)
    assert np.all(depth[modal] < floor[modal]) and np.array_equal(depth[~modal], floor[~modal])
    with pytest.raises(DatasetError, match="diameter"):
        LyingCylinder(0.01, 0.02)
