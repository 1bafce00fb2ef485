"""Target matching (App. C.2): the siamese matcher, TargetDetector('learned') alone and in the
bin-search controller, MaskAssociation alone and wired, the matcher data / training / benchmark."""

import dataclasses

import numpy as np
import pytest
import torch
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I, ImageRgba8U

from ms_drake.errors import DatasetError, PerceptionError
from ms_drake.experiments.matcher_data import (
    bench_target_detection,
    detection_metrics,
    matcher_shard_job,
)
from ms_drake.experiments.matcher_learning import PairSampler
from ms_drake.experiments.rollout import build_search
from ms_drake.perception.association import MaskAssociation, associate
from ms_drake.perception.matcher_net import (
    SIZE,
    crop,
    default_weights,
    make_net,
    occlude,
)
from ms_drake.perception.target import TargetDetector, Template, render_templates
from ms_drake.policies.bin_search import (
    BinSearchConfig,
    ControllerError,
    load_bin_search_config,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import set_heap_poses
from ms_drake.types import InstanceMasks, object_of

OBJ_A, OBJ_B = "ycb/010_potted_meat_can", "procedural/box_330"


def rgba_image(rgb: np.ndarray) -> ImageRgba8U:
    img = ImageRgba8U(rgb.shape[1], rgb.shape[0])
    a = np.array(img.mutable_data, copy=False)
    a[:, :, :3] = rgb
    a[:, :, 3] = 255
    return img


def test_crop_keeps_scale_and_blanks_the_background():
    rgb = np.full((480, 640, 3), 200, np.uint8)
    mask = np.zeros((480, 640), bool)
    mask[100:130, 200:260] = True  # 30 x 60 px
    x = crop(rgb, mask)
    assert x.shape == (4, SIZE, SIZE) and x.dtype == np.float32
    assert x[3].sum() == pytest.approx(30 * 60 / 9, rel=0.05)  # fixed 3 x 3 averaging: the size survives
    assert np.allclose(x[:3][:, x[3] == 0], 0.0)  # outside the mask no colour
    big = np.zeros_like(mask)
    big[100:160, 200:320] = True
    assert crop(rgb, big)[3].sum() > 3.5 * x[3].sum()
    with pytest.raises(PerceptionError, match="empty"):
        crop(rgb, np.zeros_like(mask))


def test_occlusion_removes_20_to_80_percent():
    rng = np.random.default_rng(0)
    m = np.zeros((64, 64), bool)
    m[10:50, 5:60] = True
    for _ in range(50):
        cut = occlude(m, rng)
        frac = 1 - cut.sum() / m.sum()
        assert 0.18 <= frac <= 0.82 and not (cut & ~m).any()


def test_training_step_lowers_the_loss(tmp_path):
    torch.manual_seed(0)
    net = make_net()
    rng = np.random.default_rng(0)
    a = torch.from_numpy(rng.random((16, 4, SIZE, SIZE), dtype=np.float32))
    b = torch.from_numpy(rng.random((16, 4, SIZE, SIZE), dtype=np.float32))
    y = torch.from_numpy((np.arange(16) % 2).astype(np.float32))
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    losses = []
    for _ in range(15):
        opt.zero_grad()
        loss = torch.nn.functional.binary_cross_entropy_with_logits(net(a, b), y)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]


@pytest.fixture(scope="module")
def red_views():
    s = load_scenario(None, "BinHeap15")
    return {name: render_templates(s, name, k=4, seed=3) for name in (OBJ_A, OBJ_B)}


def compose(views: list[Template]):
    """A 480 x 640 dark image with the views side by side, and their masks."""
    rgb = np.full((480, 640, 3), 25, np.uint8)
    masks = []
    x = 40
    for v in views:
        h, w = v.mask.shape
        m = np.zeros((480, 640), bool)
        m[150:150 + h, x:x + w] = v.mask
        rgb[m] = v.rgb[v.mask]
        masks.append(m)
        x += w + 60
    return rgb, InstanceMasks(np.stack(masks), tuple(f"m{k}" for k in range(len(masks))), np.ones(len(masks)))


@pytest.mark.skipif(not default_weights().is_file(), reason="matcher weights not trained")
def test_learned_detector_alone_tells_the_target_from_another_red_object(red_views):
    templates = red_views[OBJ_A][:3]  # three views of A; the fourth is the candidate
    det = TargetDetector("learned", templates=templates)
    rgb, masks = compose([red_views[OBJ_B][0], red_views[OBJ_A][3]])
    ctx = det.CreateDefaultContext()
    det.GetInputPort("rgb_image").FixValue(ctx, rgba_image(rgb))
    det.GetInputPort("masks").FixValue(ctx, masks)
    est = det.GetOutputPort("target").Eval(ctx)
    assert est.visible and est.instance_index == 1 and est.confidence >= 0.9
    assert np.array_equal(est.mask, masks.masks[1])
    s = det.learned.scores(rgb, masks)
    assert s[1] > s[0]
    # Only the other red object: not the target.
    rgb_b, masks_b = compose([red_views[OBJ_B][1]])
    det.GetInputPort("rgb_image").FixValue(ctx, rgba_image(rgb_b))
    det.GetInputPort("masks").FixValue(ctx, masks_b)
    assert not det.GetOutputPort("target").Eval(ctx).visible


def test_learned_detector_needs_templates_and_a_known_backend():
    with pytest.raises(PerceptionError, match="template"):
        TargetDetector("learned", templates=[])
    with pytest.raises(PerceptionError, match="color, template, learned"):
        TargetDetector("siamese")
    with pytest.raises(ControllerError, match="color, template, learned"):
        BinSearchConfig(detector="sift")


def test_mask_association_alone():
    labels = np.zeros((20, 30), np.int16)
    labels[:, :10] = 5
    labels[:, 10:] = 7
    m = np.zeros((3, 20, 30), bool)
    m[0, :, :14] = True  # mostly object 5
    m[1, :, 14:] = True  # object 7
    m[2, :2, :3] = True  # a smaller piece of object 5
    masks = InstanceMasks(m, ("seg_0", "seg_1", "seg_2"), np.array([0.9, 0.8, 0.7]))
    out = associate(masks, labels, {5: "a", 7: "b"})
    # the smaller piece names its object too, uniquely; object_of gives the object back
    assert out.ids == ("a", "b", "a@2") and np.array_equal(out.masks, m) and np.allclose(out.scores, masks.scores)
    assert [object_of(i) for i in out.ids] == ["a", "b", "a"]
    bin_only = np.zeros((1, 20, 30), bool)
    bin_only[0, :, 8:12] = True  # half on object 5, half on 7: no object covers half of it
    labels_bin = labels.copy()
    labels_bin[:, 9:11] = 0  # (the bin's label)
    assert associate(InstanceMasks(bin_only, ("a@1",), np.ones(1)), labels_bin, {5: "a", 7: "b"}).ids == ("seg_0",)
    sys = MaskAssociation({5: "a", 7: "b"}, width=30, height=20)
    ctx = sys.CreateDefaultContext()
    img = ImageLabel16I(30, 20)
    np.array(img.mutable_data, copy=False)[:, :, 0] = labels
    sys.GetInputPort("label_image").FixValue(ctx, img)
    sys.GetInputPort("masks").FixValue(ctx, masks)
    assert sys.GetOutputPort("masks").Eval(ctx).ids == ("a", "b", "a@2")
    with pytest.raises(PerceptionError, match="differ"):
        associate(masks, labels[:10], {5: "a"})


@pytest.mark.skipif(not default_weights().is_file(), reason="matcher weights not trained")
def test_controller_with_the_learned_detector_and_segmenter_finds_the_target(small_heap):
    # The heap's own target is nearly hidden (78 px); the test makes its most visible object (a
    # procedural box, ~17,000 px) the target, drawn red.
    heap = dataclasses.replace(small_heap, target_index=0, target=small_heap.objects[0].name)
    s = load_scenario(None, "FloatingGripperBin")
    est = {}
    for seg, det in (("ground_truth", "color"), ("ground_truth", "learned"), ("learned", "learned")):
        system = build_search(s, heap, load_bin_search_config("ch7", policy="largest", seed=1, segmenter=seg,
                                                              detector=det))
        assert system.controller.GetSubsystemByName("target_detector").backend == det
        ctx = system.diagram.CreateDefaultContext()
        set_heap_poses(system.station, ctx, heap)
        est[seg, det] = system.output(ctx, "target")
        masks = system.output(ctx, "masks")
        if seg == "learned":  # named after the objects behind them (MaskAssociation)
            assert system.target_id in masks.ids
            assert system.controller.HasInputPort("overhead.label_image")
    color, learned = est["ground_truth", "color"], est["ground_truth", "learned"]
    assert color.visible and learned.visible and learned.confidence >= 0.9
    assert np.array_equal(color.mask, learned.mask)  # the same (red) target mask
    both = est["learned", "learned"]
    assert both.visible and (both.mask & color.mask).sum() > 0.5 * both.mask.sum()


def test_matcher_shard_and_pairs(tmp_path):
    r = matcher_shard_job((str(tmp_path), 0, 3, 2))
    assert r["crops"] >= 2 and not r["skipped"]
    z = dict(np.load(tmp_path / "matcher_00000_train.npz"))
    assert z["heap"].shape[1:] == (4, SIZE, SIZE) and z["templates"].shape[1:] == (2, 4, SIZE, SIZE)
    assert matcher_shard_job((str(tmp_path), 0, 3, 2))["skipped"]
    ps = PairSampler(z)
    a, b, y = ps.pairs(20, np.random.default_rng(0))
    assert a.shape == b.shape == (20, 4, SIZE, SIZE) and y.sum() == 10
    neg = [p for p in range(20) if y[p] == 0]
    for p in neg:  # a negative never pairs an object with itself
        assert not np.array_equal(b[p], a[p])


def test_detection_metrics_and_unknown_backend(tmp_path):
    recs = [dict(detected=True, correct=True), dict(detected=True, correct=False), dict(detected=False, correct=False)]
    m = detection_metrics(recs)
    assert (m["precision"], m["recall"]) == (0.5, pytest.approx(1 / 3)) and m["f1"] == pytest.approx(0.4)
    with pytest.raises(DatasetError, match="color, template, learned"):
        bench_target_detection("hsv", 1, 0, tmp_path / "x.json")


# ---------------------------------------------------------------------------------------------
# The template backend's geometric check (depth): a visible part of the target is no larger than
# the target, and a mask that nothing hides shows a whole object, which must be the target's size.

RED = (230, 26, 26)


class _Cam:
    fx = fy = 500.0
    cx, cy = 60.0, 50.0


def _plane_points(width: float, height: float, z: float = 0.7, n: int = 40) -> np.ndarray:
    x, y = np.meshgrid(np.linspace(0, width, n), np.linspace(0, height, n))
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1).astype(np.float32)


def geometry_scene():
    """A 100 x 120 px view of a floor 0.8 m away (_Cam: 1.52 mm per px at 0.76 m), three red flat
    objects of one shade lying on it, their tops at 0.76 m: 0, 9.1 x 6.1 cm, nothing around it;
    1, 4.6 x 6.1 cm beside a nearer grey object (at 0.74 m) that may hide the rest; 2, 7.6 x 13.7
    cm. The target: a 9 x 6 cm plate (one template view with its points, from a nearer camera)."""
    rgb = np.full((100, 120, 3), 30, np.uint8)
    depth = np.full((100, 120), 0.8, np.float32)
    m = np.zeros((3, 100, 120), bool)
    m[0, 5:45, 5:65] = True
    m[1, 55:95, 5:35] = True
    m[2, 5:95, 68:118] = True
    for k in range(3):
        rgb[m[k]] = RED
        depth[m[k]] = 0.76
    rgb[55:95, 35:60] = (150, 150, 150)
    depth[55:95, 35:60] = 0.74
    masks = InstanceMasks(m, ("whole", "part", "big"), np.ones(3))
    view = Template(np.full((50, 75, 3), RED, np.uint8), np.ones((50, 75), bool), _plane_points(0.09, 0.06))
    return rgb, depth, masks, view


def test_surface_extents_and_occluded_fraction_on_fixed_inputs():
    from ms_drake.perception.target import (
        mask_points,
        occluded_fraction,
        surface_extents,
    )

    e = surface_extents(_plane_points(0.09, 0.06))
    assert e[0] == pytest.approx(0.09, abs=0.003) and e[1] == pytest.approx(0.06, abs=0.003) and e[2] < 1e-6
    _, depth, masks, _ = geometry_scene()
    e0 = surface_extents(mask_points(depth, masks.masks[0], _Cam()))
    assert e0[0] == pytest.approx(0.0912, abs=0.003) and e0[1] == pytest.approx(0.0608, abs=0.003)
    assert occluded_fraction(depth, masks.masks[0]) == 0.0  # lying on the floor, nothing nearer around it
    assert 0.15 < occluded_fraction(depth, masks.masks[1]) < 0.4  # its right side: the nearer grey object
    edge = np.zeros_like(masks.masks[0])
    edge[0:3, 0:3] = True  # cut by the image's border: counted as hidden
    assert occluded_fraction(depth, edge) > 0.3
    holes = depth.copy()
    holes[55:95, 35:60] = 0.0  # no return (0) is no evidence either way
    assert occluded_fraction(holes, masks.masks[1]) == 0.0


def test_template_backend_checks_the_target_size_on_depth():
    from ms_drake.perception.target import TemplateMatcher

    rgb, depth, masks, view = geometry_scene()
    matcher = TemplateMatcher([view])
    assert matcher.extent_max[:2] == pytest.approx([0.088, 0.059], abs=0.003)
    # Colour alone: every red mask matches (the big one's area is within 1.5 x the template's).
    assert (matcher.scores(rgb, masks) > 0.99).all()
    # With depth: 0 (whole, the target's size) and 1 (4.6 cm wide, but possibly cut by the grey
    # object) may be the target; 2 (13.7 cm long) cannot: no part of a 9 cm plate is that long.
    s = matcher.scores(rgb, masks, depth, _Cam())
    assert s[0] > 0.99 and s[1] > 0.99 and s[2] == 0.0
    assert matcher.detect(rgb, masks, depth, _Cam()).instance_index in (0, 1)
    # A 3 x 4.6 cm red object that nothing hides is whole, and too small to be the plate ...
    small = masks.masks.copy()
    small[0] = False
    small[0, 10:30, 10:40] = True
    depth_small = np.where(masks.masks[0] & ~small[0], np.float32(0.8), depth)
    s = matcher.scores(rgb, InstanceMasks(small, masks.ids, np.ones(3)), depth_small, _Cam())
    assert s[0] == 0.0 and s[1] > 0.99
    # ... while the same mask beside a nearer object may be a part of it.
    depth_small[10:30, 40:50] = 0.74
    assert matcher.scores(rgb, InstanceMasks(small, masks.ids, np.ones(3)), depth_small, _Cam())[0] > 0.99
    # Templates without points, or no depth: colour alone, as before.
    plain = TemplateMatcher([Template(view.rgb, view.mask)])
    assert plain.extent_max is None and (plain.scores(rgb, masks, depth, _Cam()) > 0.99).all()
    # The detector system reads the depth from its optional input port and its camera's intrinsics.
    det = TargetDetector("template", 120, 100, templates=[view], camera=_Cam())
    ctx = det.CreateDefaultContext()
    det.GetInputPort("rgb_image").FixValue(ctx, rgba_image(rgb))
    only_big = InstanceMasks(masks.masks[[2]], ("big",), np.ones(1))
    rgb[masks.masks[0] | masks.masks[1]] = 30  # (red pixels that no mask holds would be the target)
    det.GetInputPort("rgb_image").FixValue(ctx, rgba_image(rgb))
    det.GetInputPort("masks").FixValue(ctx, only_big)
    assert det.GetOutputPort("target").Eval(ctx).visible  # no depth connected: colour alone
    img = ImageDepth32F(120, 100)
    np.array(img.mutable_data, copy=False)[:, :, 0] = depth
    det.GetInputPort("depth_image").FixValue(ctx, img)
    assert not det.GetOutputPort("target").Eval(ctx).visible


def test_template_backend_scores_the_target_coloured_part_of_a_merged_mask():
    from ms_drake.perception.target import TemplateMatcher

    rgb, depth, masks, view = geometry_scene()
    grey = np.zeros_like(masks.masks[0])
    grey[55:95, 35:60] = True  # the nearer grey object beside mask 1
    # The segmenter merged the red 4.6 x 6.1 cm piece (1,200 px) with the grey object (1,000 px).
    merged = InstanceMasks(np.stack([masks.masks[1] | grey, masks.masks[2]]), ("merged", "big"), np.ones(2))
    whole_only = TemplateMatcher([view], parts=False)
    assert whole_only.scores(rgb, merged, depth, _Cam())[0] < 0.9  # grey in its histogram
    assert not whole_only.detect(rgb, merged, depth, _Cam()).visible
    matcher = TemplateMatcher([view])
    assert matcher.scores(rgb, merged, depth, _Cam())[0] > 0.99
    est = matcher.detect(rgb, merged, depth, _Cam())
    # The estimate is the red part; the instance is the merged mask, which is mostly the target.
    assert est.visible and est.instance_index == 0 and np.array_equal(est.mask, masks.masks[1])
    # A red strip (1.5 cm wide, 400 px) merged with the larger grey object: seen, but no instance.
    strip = np.zeros_like(grey)
    strip[55:95, 25:35] = True
    est = matcher.detect(rgb, InstanceMasks((strip | grey)[None], ("merged",), np.ones(1)), depth, _Cam())
    assert est.visible and est.instance_index == -1 and np.array_equal(est.mask, strip)
    # The part passes the size check like a mask: the 13.7 cm red object merged with grey is not the plate.
    big_grey = masks.masks[2] | grey
    assert matcher.scores(rgb, InstanceMasks(big_grey[None], ("merged",), np.ones(1)), depth, _Cam())[0] == 0.0
    # A mask of the target's colours is judged whole: a red object too large stays 0, however it is cut.
    assert matcher.scores(rgb, masks, depth, _Cam())[2] == 0.0


def test_template_backend_joins_the_pieces_of_a_split_target():
    from ms_drake.perception.target import TemplateMatcher

    rgb = np.full((100, 120, 3), 30, np.uint8)
    depth = np.full((100, 120), 0.8, np.float32)
    plate, below = np.zeros((2, 100, 120), bool)
    plate[5:45, 5:65] = True  # 9.1 x 6.1 cm: the plate
    below[45:85, 5:65] = True  # a second red plate right below it
    for m in (plate, below):
        rgb[m] = RED
        depth[m] = 0.76
    rgb[5:85, 65:75] = (150, 150, 150)
    depth[5:85, 65:75] = 0.74  # a nearer grey object on their right: they may be hidden
    view = Template(np.full((50, 75, 3), RED, np.uint8), np.ones((50, 75), bool), _plane_points(0.09, 0.06))
    # The segmenter cut the plate in a 30 px high piece and a 10 px high sliver: both match.
    top, sliver = plate.copy(), plate.copy()
    top[35:] = False
    sliver[:35] = False
    split = InstanceMasks(np.stack([sliver, top]), ("sliver", "top"), np.ones(2))
    assert (TemplateMatcher([view]).scores(rgb, split, depth, _Cam()) > 0.99).all()
    alone = TemplateMatcher([view], fragments=False).detect(rgb, split, depth, _Cam())
    assert alone.instance_index == 0 and alone.mask.sum() == sliver.sum()  # the best score: the first piece
    est = TargetDetector("template", 120, 100, templates=[view], camera=_Cam()).detect(rgb, split, depth)
    assert est.visible and np.array_equal(est.mask, plate) and est.instance_index == 1  # the larger piece
    # Two plates one below the other are 12.2 cm long together: not joined.
    two = InstanceMasks(np.stack([plate, below]), ("a", "b"), np.ones(2))
    assert (TemplateMatcher([view]).scores(rgb, two, depth, _Cam()) > 0.99).all()
    est = TemplateMatcher([view]).detect(rgb, two, depth, _Cam())
    assert est.visible and est.mask.sum() == plate.sum()
    # Without depth there is no size to bound the union: the pieces stay apart.
    assert TemplateMatcher([view]).detect(rgb, split).mask.sum() in (sliver.sum(), top.sum())
